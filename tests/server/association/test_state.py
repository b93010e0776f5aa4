"""The association checkpoint format (``state.encode``/``decode``): a restored associator goes on
exactly as the original, every data type round-trips, malformed blobs raise ``CheckpointError``
naming the fault, and the module runs no code a blob names."""

from __future__ import annotations

import ast
import builtins
import dataclasses
import math
import pickle
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from factories import CAMERA, MeasurementFactory, camera_looking_along_y, object_pose

import wardmap.server.association.state as state_module
from wardmap.server.association.associator import AssociationConfig, Associator
from wardmap.server.association.hdp import HdpConfig
from wardmap.server.association.state import FORMAT, VERSION, CheckpointError, decode, encode
from wardmap.server.association.types import Landmark, LandmarkChange
from wardmap.server.perception.types import ObjectMeasurement
from wardmap.shared.errors import WardmapError

DOOR = np.array([0.06, 1.16, 2.18])
BED = np.array([2.1, 1.0, 0.6])
FOOT = np.array([0.6, 0.7, 0.55])
Keyframe = tuple[str, list[ObjectMeasurement], np.ndarray]


def _ward(make: MeasurementFactory, n_keyframes: int = 36, seed: int = 0) -> list[Keyframe]:
    """Two robots in one corridor, interleaved: robot ``a`` drives +x past a row of five identical
    chairs 0.55 m apart, two doors and a bed, robot ``b`` drives back the other way; ``a`` starts
    a second session half-way. 4 cm position noise, one chair view in eight measured as a
    wheelchair, the bed's foot measured as a cart as well in its first views (a class confusion
    the merge takes back), random colour histograms and ORB descriptors. Returns
    ``(stream, measurements, T_world_camera)`` per keyframe, in order."""
    rng = np.random.default_rng(seed)
    objects = [(k + 1, "chair", object_pose(0.55 * k, 3.0), None) for k in range(5)]
    objects += [(10, "door", object_pose(-1.5, 4.2, 1.09, np.pi / 2), DOOR),
                (11, "door", object_pose(0.2, 4.2, 1.09, np.pi / 2), DOOR),
                (20, "bed", object_pose(3.2, 3.6, 0.3), BED),
                (20, "cart", object_pose(3.8, 3.6, 0.275), FOOT)]
    out: list[Keyframe] = []
    for i in range(n_keyframes):
        robot = "a" if i % 2 == 0 else "b"
        step = i // 2
        if robot == "a":
            stream, x = ("a/s1" if step < n_keyframes // 4 else "a/s2"), -1.2 + 0.25 * step
        else:
            stream, x = "b/s1", 3.6 - 0.25 * step
        T = camera_looking_along_y(x, 0.1 * rng.normal())
        ms = []
        for gid, category, T_wo, size in objects:
            if category == "chair" and rng.random() < 0.125:
                category = "wheelchair"
            if category == "cart" and i > n_keyframes // 2:
                continue
            kwargs = {"size": size} if size is not None else {}
            try:
                m = make(T_wo, T, category=category, gt=gid, keyframe=f"{stream}/{step}", stamp=float(i),
                         offset=tuple(rng.normal(0, 0.04, 3)), **kwargs)
            except ValueError:  # not in view
                continue
            hist = rng.random(8).astype(np.float32)
            orb = rng.integers(0, 256, (int(rng.integers(0, 6)), 32), dtype=np.uint8)
            ms.append(dataclasses.replace(m, color_hist=hist / hist.sum(), descriptors=orb,
                                          confidence=float(rng.uniform(0.5, 1))))
        out.append((stream, ms, T))
    return out


class _Server:
    """What the mapping stage checkpoints: the associator, per-landmark colour sums, each robot's
    open session, and the closures at the cursor; fed as the stage feeds it (a robot's new
    session first flushes its previous one)."""

    def __init__(self, cfg: AssociationConfig) -> None:
        self.associator = Associator(cfg)
        self.hist_sum: dict[int, np.ndarray] = {}
        self.open_stream: dict[str, str] = {}

    def state(self) -> dict[str, Any]:
        return {"associator": self.associator, "hist_sum": self.hist_sum, "open_stream": self.open_stream,
                "closed_at_cursor": ["a/s0"]}

    @classmethod
    def restored(cls, blob: bytes) -> _Server:
        got = decode(blob)
        assert isinstance(got, dict) and isinstance(got["associator"], Associator)
        server = cls.__new__(cls)
        server.associator, server.hist_sum, server.open_stream = (got["associator"], got["hist_sum"],
                                                                  got["open_stream"])
        assert got["closed_at_cursor"] == ["a/s0"]
        return server

    def feed(self, keyframes: list[Keyframe], *, flush: bool = True) -> Iterator[list[LandmarkChange]]:
        """The changes after each keyframe (and each flush); ``flush``: flush every stream at the end."""
        for stream, ms, T in keyframes:
            robot = stream.split("/", 1)[0]
            previous = self.open_stream.get(robot)
            if previous is not None and previous != stream:
                yield self._collect(self.associator.flush(previous))
            self.open_stream[robot] = stream
            yield self._collect(self.associator.add_keyframe(ms, T, CAMERA, stream=stream))
        if flush:
            yield self._collect(self.associator.flush())

    def _collect(self, changes: list[LandmarkChange]) -> list[LandmarkChange]:
        for c in changes:
            if c.kind == "merged":
                gone = self.hist_sum.pop(c.landmark.id, None)
                if gone is not None:
                    self.hist_sum[c.into] = self.hist_sum.get(c.into, 0.0) + gone
            elif c.added:
                total = np.sum([m.color_hist.astype(np.float64) for m in c.added], axis=0)
                self.hist_sum[c.landmark.id] = self.hist_sum.get(c.landmark.id, 0.0) + total
        return changes


def _landmark(lm: Landmark) -> tuple:
    """Everything a landmark reports, arrays by their bytes."""
    return (lm.id, lm.category, lm.T_world_object.tobytes(), lm.size.tobytes(), lm.confidence,
            lm.n_measurements, lm.confirmed,
            tuple((m.keyframe, m.box_xyxy.tobytes(), m.T_world_object.tobytes(), m.color_hist.tobytes())
                  for m in lm.measurements))


def _changes(changes: list[LandmarkChange]) -> list[tuple]:
    return [(c.kind, _landmark(c.landmark), tuple(m.keyframe for m in c.added), c.into) for c in changes]


@pytest.mark.parametrize("method, keep, splits", [
    ("hierarchical", False, (5, 17)),  # the server's settings
    ("hierarchical", True, (17,)),
    ("per_keyframe_hdp", False, (17,)),
    ("nearest", False, (17,)),
])
def test_a_restored_associator_goes_on_exactly_as_the_original(make_measurement: MeasurementFactory,
                                                               method: str, keep: bool,
                                                               splits: tuple[int, ...]) -> None:
    """Checkpointed part-way (mid-group, with keyframes of both robots waiting in open groups),
    restored, and fed the same further keyframes, the copy reports the same changes after every
    keyframe and ends with the same landmarks (ids, classes, poses, sizes, confidences,
    measurement counts, the measurements themselves) and colour sums as the original. (Fewer
    Gibbs sweeps than the default, to keep the test short: the sampler's random stream is what
    must continue identically, however long it runs.)"""
    scene = _ward(make_measurement)
    cfg = AssociationConfig(method=method, keep_measurements=keep, max_history=16,  # type: ignore[arg-type]
                            hdp=HdpConfig(sweeps=10, burn_in=2))
    for split in splits:
        original = _Server(cfg)
        for _ in original.feed(scene[:split], flush=False):
            pass
        if method == "hierarchical":
            assert original.associator.pending_keyframes > 0  # open groups travel in the state
        blob = encode(original.state())
        copy = _Server.restored(blob)
        assert _same(original.state(), copy.state())  # every field of every object
        rest = scene[split:]
        for ours, theirs in zip(original.feed(rest), copy.feed(rest), strict=True):
            assert _changes(ours) == _changes(theirs)
        assert [_landmark(lm) for lm in original.associator.landmarks()] == \
            [_landmark(lm) for lm in copy.associator.landmarks()]
        assert original.associator.landmarks()  # the scene made some
        assert original.hist_sum.keys() == copy.hist_sum.keys()
        for lid, total in original.hist_sum.items():
            np.testing.assert_array_equal(total, copy.hist_sum[lid])
        assert original.associator.beyond_range == copy.associator.beyond_range


def test_the_scene_merges(make_measurement: MeasurementFactory) -> None:
    """The round-trip scene exercises what the restored state must carry on with: a merge of a
    class confusion (the bed's foot, measured as a cart, ends in the bed), landmarks of several
    classes, and more measurements than max_history."""
    server = _Server(AssociationConfig(keep_measurements=False, max_history=16))
    for _ in server.feed(_ward(make_measurement)):
        pass
    landmarks = server.associator.landmarks()
    assert {"chair", "door", "bed"} <= {lm.category for lm in landmarks}
    assert "cart" not in {lm.category for lm in landmarks}
    (bed,) = [lm for lm in landmarks if lm.category == "bed"]
    assert "cart" in {m.category for m in bed.measurements}
    assert max(lm.n_measurements for lm in landmarks) > 16


def test_size_is_within_twice_pickle(make_measurement: MeasurementFactory) -> None:
    """The server's state (keep_measurements off) after the whole scene is no more than twice its
    pickle (it is in fact smaller: fields by position, no class paths)."""
    server = _Server(AssociationConfig(keep_measurements=False, max_history=16))
    for _ in server.feed(_ward(make_measurement, n_keyframes=60)):
        pass
    pickled = len(pickle.dumps(server.state(), protocol=pickle.HIGHEST_PROTOCOL))
    ours = len(encode(server.state()))
    assert ours <= 2 * pickled, (ours, pickled)


def _same(a: object, b: object) -> bool:
    """Equal values of equal types, recursively; nan equals nan; arrays by dtype, shape and bytes;
    other objects by their attributes."""
    if type(a) is not type(b):
        return False
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray)
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if isinstance(a, float):
        assert isinstance(b, float)
        return (math.isnan(a) and math.isnan(b)) or (a == b and math.copysign(1, a) == math.copysign(1, b))
    if isinstance(a, np.generic):
        return a.tobytes() == b.tobytes()  # type: ignore[attr-defined]
    if isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple))
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, defaultdict):  # SpatialGrid's cell index, rebuilt on decode: its order is not used
        return a == b
    if isinstance(a, dict):
        assert isinstance(b, dict)
        return list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (set, frozenset, str, bytes, bytearray, int)) or a is None:
        return a == b
    return _same(vars(a), vars(b))


def test_every_data_type_round_trips() -> None:
    """Atoms (nan, inf, -0.0, 64-bit and larger ints, bytes), containers (tuples, sets, frozensets,
    dicts with int, str and tuple keys), numpy arrays of many dtypes, shapes and memory layouts,
    and numpy scalars come back equal and of the same type; arrays come back writeable."""
    rng = np.random.default_rng(7)
    arrays = [
        rng.random((4, 4)), rng.random(3).astype(np.float32), np.float16([1.5, -2]),
        rng.integers(0, 255, (5, 32), dtype=np.uint8), np.array([True, False]), np.zeros((0, 32), np.uint8),
        np.zeros((0, 0), bool), np.array(3.5), np.arange(6, dtype=">i4").reshape(2, 3),
        np.asfortranarray(rng.random((3, 2))), rng.random((6, 6))[::2, 1::3], np.array([1 + 2j]),
        np.array(["bed", "chair"]), np.array([b"ab"]), np.array(["2024-01-01"], "datetime64[ns]"),
        np.array([np.nan, np.inf, -np.inf]),
    ]
    value = {
        "atoms": [None, True, False, 0, -1, 2**63 - 1, -(2**63), 2**64 - 1, 2**70, -(2**90), 1.5, -0.0,
                  math.nan, math.inf, -math.inf, "", "chaise é", b"", b"\x00\xff", bytearray(b"xy")],
        "arrays": arrays,
        "scalars": [np.float32(0.25), np.float64(2.0), np.int64(-3), np.uint8(7), np.bool_(True)],
        "containers": ((), (1, (2, 3)), {1, 2, 3}, frozenset({"a", "b"}), set(), frozenset()),
        5: {(1, "a"): [1], -2: "x", frozenset({1}): ()},
    }
    got = decode(encode(value))
    assert _same(value, got)
    assert isinstance(got, dict)
    assert got["containers"][2:] == value["containers"][2:]  # sets compare by value
    assert all(a.flags.writeable for a in got["arrays"])
    for a, b in zip(arrays, got["arrays"], strict=True):
        np.testing.assert_array_equal(a, b)


def test_shared_references_stay_shared() -> None:
    """An object held in two places is one object after decoding (mutating it through one holder
    shows through the other), as it was before encoding; equal but distinct objects stay distinct."""
    shared_list, shared_array = [1, 2], np.zeros(3)
    value = {"a": shared_list, "b": shared_list, "c": [1, 2], "x": (shared_array, shared_array, np.zeros(3))}
    got = decode(encode(value))
    assert isinstance(got, dict)
    assert got["a"] is got["b"] and got["a"] is not got["c"]
    assert got["x"][0] is got["x"][1] and got["x"][0] is not got["x"][2]


def test_shared_measurements_in_the_associator_stay_shared(make_measurement: MeasurementFactory) -> None:
    """A measurement of a keyframe still in an open group is held by that keyframe's view and by its
    landmark; after a round trip both hold one object, as before."""
    assoc = Associator(AssociationConfig())
    for _, ms, T in _ward(make_measurement)[:14:2]:  # robot a: a group done, its last views wait
        assoc.add_keyframe(ms, T, CAMERA)

    def holders(a: Associator) -> list[tuple[int, int]]:
        in_views = {id(m): k for st in a._streams.values() for k, v in st.views.items()
                    for m in v.measurements}
        return sorted((in_views[id(m)], lm.id) for lm in a._landmarks.values() for m in lm.measurements
                      if id(m) in in_views)

    restored = decode(encode(assoc))
    assert isinstance(restored, Associator)
    assert holders(assoc) and holders(restored) == holders(assoc)


def test_a_cycle_is_refused() -> None:
    """A list that holds itself cannot be written (the associator's state has no cycles)."""
    loop: list[object] = []
    loop.append(loop)
    with pytest.raises(CheckpointError, match="cycle"):
        encode(loop)


@pytest.mark.parametrize("value, match", [
    (lambda: 1, "cannot encode a builtins.function"),
    (np.array([object()], dtype=object), "object dtype"),
    (np.zeros(2, dtype=[("a", "<i4")]), "structured"),
    (Path("/tmp"), "cannot encode"),
    ({"ok": [1, {2: print}]}, "builtin_function_or_method"),
])
def test_values_that_are_not_data_are_refused_on_encode(value: object, match: str) -> None:
    """Callables, arrays of object or structured dtype and unregistered classes are not written."""
    with pytest.raises(CheckpointError, match=match):
        encode(value)


def test_an_attribute_the_registry_does_not_list_is_refused() -> None:
    """An associator given an attribute state.py does not know of is not silently half-written:
    encoding names the attribute (the registry needs an entry)."""
    assoc = Associator(AssociationConfig())
    assoc.new_cache = {}  # type: ignore[attr-defined]
    with pytest.raises(CheckpointError, match=r"Associator: .*new_cache"):
        encode(assoc)


def _blob(head: object, body: object) -> bytes:
    return msgpack.packb(head) + msgpack.packb(body)


GOOD = encode({"x": [1, np.zeros(2)], "c": AssociationConfig()})
CONFIG_FIELDS = [f.name for f in dataclasses.fields(AssociationConfig)]


@pytest.mark.parametrize("blob, match", [
    (b"", "truncated before its header"),
    (GOOD[:3], "truncated before its header"),
    (GOOD[:-1], "truncated"),
    (GOOD[: len(GOOD) // 2], "truncated"),
    (GOOD + b"\x00", "1 bytes after the state"),
    (b"\x80\x04\x95 not msgpack", "not a wardmap.association.state blob"),
    (pickle.dumps({"x": 1}), "not a wardmap.association.state blob"),
    (_blob(["other.format", 1], [[], None]), "not a wardmap.association.state blob"),
    (_blob([FORMAT, VERSION + 1], [[], None]), f"version {VERSION + 1} is not supported"),
    (_blob([FORMAT, True], [[], None]), "version True is not supported"),
    (_blob([FORMAT, VERSION], [[], [42, 1]]), "unknown node tag 42"),
    (_blob([FORMAT, VERSION], [[], ["LIST", 1]]), "unknown node tag LIST"),
    (_blob([FORMAT, VERSION], [[], []]), "unknown node tag None"),
    (_blob([FORMAT, VERSION], [[["os.system", []]], [8, 0]]), "class 'os.system' is not in the registry"),
    (_blob([FORMAT, VERSION], [[["builtins.eval", ["x"]]], [8, 0, "1"]]), "'builtins.eval' is not in the"),
    (_blob([FORMAT, VERSION], [[["AssociationConfig", ["method"]]], None]), "written with fields"),
    (_blob([FORMAT, VERSION], [[], [8, 0]]), "not in the blob's table"),
    (_blob([FORMAT, VERSION], [[["AssociationConfig", CONFIG_FIELDS]], [8, 0, "x"]]), "holds 1 values"),
    (_blob([FORMAT, VERSION], [[], [6, "|O", [1], b"\x00" * 8]]), "object dtype"),
    (_blob([FORMAT, VERSION], [[], [7, "|O", b"\x00" * 8]]), "object dtype"),
    (_blob([FORMAT, VERSION], [[], [6, "[('a', '|O')]", [1], b"\x00" * 8]]), "not a plain numpy dtype"),
    (_blob([FORMAT, VERSION], [[], [6, "<f8", [2, 2], b"\x00" * 8]]), "needs 32 bytes, has 8"),
    (_blob([FORMAT, VERSION], [[], [6, "<f8", [-1], b""]]), "shape"),
    (_blob([FORMAT, VERSION], [[], [1, [0, 0]]]), "reference .* to no value"),
    (_blob([FORMAT, VERSION], [[], [3, [1, 5], 2]]), "unhashable"),
    (_blob([FORMAT, VERSION], [[], [3, 1]]), "odd number"),
    (_blob([FORMAT, VERSION], [[], [9, "12a"]]), "big int"),
    (_blob([FORMAT, VERSION], [[], {"a": 1}]), "unexpected dict"),
    (_blob([FORMAT, VERSION], [[], msgpack.ExtType(5, b"code")]), "extension type 5"),
    (_blob([FORMAT, VERSION], [[], [1, msgpack.Timestamp(0)]]), "unexpected Timestamp"),
    (_blob([FORMAT, VERSION], "root"), "body must be"),
])
def test_malformed_blobs_raise_a_named_error(blob: bytes, match: str) -> None:
    """Each kind of bad blob raises CheckpointError (a WardmapError) whose message names the fault."""
    with pytest.raises(CheckpointError, match=match) as info:
        decode(blob)
    assert isinstance(info.value, WardmapError)


def test_an_invalid_configuration_is_refused() -> None:
    """A configuration rebuilt from a blob goes through its own checks (max_history >= 1 here)."""
    values = [dataclasses.asdict(AssociationConfig())[name] for name in CONFIG_FIELDS]
    good = encode(AssociationConfig())
    assert isinstance(decode(good), AssociationConfig)
    body = msgpack.unpackb(good[len(msgpack.packb([FORMAT, VERSION])):])
    root = body[1]
    k = CONFIG_FIELDS.index("max_history")
    assert root[2 + k] == values[k]
    root[2 + k] = 0
    with pytest.raises(CheckpointError, match="AssociationConfig: invalid: max_history"):
        decode(_blob([FORMAT, VERSION], body))


def test_the_module_names_no_code_loader() -> None:
    """state.py imports no pickle, marshal or importlib, and calls no eval, exec, compile,
    __import__, getattr or loads (no name from a blob can reach a loader)."""
    tree = ast.parse(Path(state_module.__file__).read_text())
    modules = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import)
               for alias in node.names}
    modules |= {node.module.split(".")[0] for node in ast.walk(tree)
                if isinstance(node, ast.ImportFrom) and node.module}
    assert modules <= {"__future__", "dataclasses", "re", "collections", "typing", "msgpack", "numpy",
                       "wardmap"}
    names = {node.id for node in ast.walk(tree) if isinstance(node, ast.Name)}
    assert not names & {"pickle", "marshal", "importlib", "__import__", "eval", "exec", "compile", "getattr",
                        "globals", "locals", "vars"}
    attrs = {node.attr for node in ast.walk(tree) if isinstance(node, ast.Attribute)}
    assert not attrs & {"import_module", "find_class", "load", "loads", "eval", "exec", "__import__"}


def test_decoding_imports_nothing(make_measurement: MeasurementFactory,
                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """Decoding a whole associator state runs with imports and pickle disabled."""
    server = _Server(AssociationConfig(keep_measurements=False))
    for _ in server.feed(_ward(make_measurement)[:13], flush=False):
        pass
    blob = encode(server.state())

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError(f"decode tried to import or unpickle: {args[:1]}")

    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(pickle, "Unpickler", refuse)
    real_import = builtins.__import__
    builtins.__import__ = refuse
    try:
        got = decode(blob)
    finally:
        builtins.__import__ = real_import
    assert isinstance(got, dict) and isinstance(got["associator"], Associator)

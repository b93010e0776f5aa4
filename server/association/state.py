"""The association checkpoint format: a versioned, data-only encoding of the associator's state.

:func:`encode` turns an object graph (the :class:`Associator` with everything it holds, and the
plain dicts, lists and arrays around it) into bytes, and :func:`decode` turns them back. Unlike
pickle, decoding never runs code named by the blob and never imports by name: it builds only
Python's plain data types, numpy arrays and the classes of :data:`REGISTRY`, each rebuilt with
``object.__new__`` and its fields set from the blob. Whoever can write the database file can
feed the server a wrong map, but not run code in it.

Layout (msgpack, two values one after the other)::

    header: [FORMAT, VERSION]
    body:   [classes, root]
    classes: [[name, [field, ...]], ...]   # registry names used, with their fields, in order
    root:    a value

A value is ``None``, a bool, an int (64-bit), a float (nan and inf included), a str or bytes
as msgpack has them, or a tagged node, a msgpack array ``[tag, ...]``:

=============  ==========================================  ===========================
tag            node                                         value
=============  ==========================================  ===========================
0 ``REF``      ``[0, index]``                               the memo's ``index``-th value
1 ``LIST``     ``[1, item, ...]``                           list
2 ``TUPLE``    ``[2, item, ...]``                           tuple
3 ``DICT``     ``[3, key, value, key, value, ...]``         dict (insertion order kept)
4 ``SET``      ``[4, item, ...]``                           set
5 ``FROZEN``   ``[5, item, ...]``                           frozenset
6 ``ARRAY``    ``[6, dtype str, [dim, ...], bytes]``        numpy array, C order
7 ``SCALAR``   ``[7, dtype str, bytes]``                    numpy scalar (``np.float32``)
8 ``OBJECT``   ``[8, class index, field value, ...]``       instance of a registry class
9 ``BIGINT``   ``[9, decimal str]``                         int beyond 64 bits
10 ``BYTEARR`` ``[10, bytes]``                              bytearray
=============  ==========================================  ===========================

Shared references: every list, tuple, dict, set, frozenset, bytearray, array and object is
written once; a second reference to the same object (``is``) is a ``REF`` to it, numbered in
the order the values are completed (post-order), as pickle's memo does. So the decoded graph
shares exactly what the encoded one shared. What the associator shares, and why it is kept:

- a measurement is held by its keyframe's view (``_Stream.views``, until its groups are done),
  by its landmark's ``measurements`` and maybe as the landmark's ``first``; the measurements of
  one keyframe share their ``T_world_camera`` array with the view; with ``keep_measurements``
  off every slimmed measurement shares one empty descriptor and one empty histogram array.
  The association compares measurements by id (``mid``), not by identity, except
  ``Associator._fresh`` (``list.remove``), which is empty between calls, when a checkpoint is
  taken. So identity does not change behaviour today; the memo keeps it anyway, because it is
  exact whatever the associator comes to rely on, and because it writes each measurement once
  instead of up to three times (the memo makes the blob smaller, not larger).
- Reference cycles are refused on encode (:class:`CheckpointError`): the associator's state
  has none, and a format without them cannot be made to build half-made objects.

Not data: ``SpatialGrid._cells`` is a ``defaultdict(set)`` (its factory is a callable) and an
index derived from ``SpatialGrid._where``: it is not written, and is rebuilt from ``_where``
on decode. Everything else of the associator is written as it is, caches included
(``Associator._poses_cache``: it is keyed by a measurement count, so a restored copy must hold
the same entries to repeat the original exactly; it is 10-20 % of the size). The knowledge
graph is not held by the associator (only the pairs of related classes it derived, a set of
frozensets), so it is not part of the state.

Decoding checks the structure (the header, every node's shape and tag, each class name
against the registry and its field list against this code's, array dtypes, shapes and sizes,
reference indexes) and reruns the ``__post_init__`` checks of the configuration classes; any
failure raises :class:`CheckpointError` naming it. It does not check the type of every field
of every object: a blob written by other code is refused by its field lists and, in the
server, by the checkpoint's key (the association code's digest).
"""

from __future__ import annotations

import dataclasses
import re
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final

import msgpack
import numpy as np

from wardmap.server.association.associator import AssociationConfig, Associator, _LandmarkState, _Stream
from wardmap.server.association.baselines import NearestConfig
from wardmap.server.association.groups import KeyframeGrouper
from wardmap.server.association.hdp import HdpConfig
from wardmap.server.association.mot import KeyframeView, MotConfig
from wardmap.server.association.refine import RefineConfig
from wardmap.server.association.spatial import SpatialGrid
from wardmap.server.association.types import Landmark, LandmarkChange
from wardmap.server.perception.types import ObjectMeasurement
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import WardmapError

__all__ = ["FORMAT", "REGISTRY", "VERSION", "CheckpointError", "decode", "encode"]

FORMAT: Final = "wardmap.association.state"
"""The format's name, first in the header."""
VERSION: Final = 2
"""Bumped when the layout or a registry entry's fields change; :func:`decode` reads this one only."""


class CheckpointError(WardmapError):
    """An association state cannot be encoded (an unsupported type, a cycle) or a blob cannot be
    decoded (truncated, another format or version, a malformed node, an unknown class)."""


REF, LIST, TUPLE, DICT, SET, FROZEN, ARRAY, SCALAR, OBJECT, BIGINT, BYTEARR = range(11)
_TAG_NAMES: Final = ("REF", "LIST", "TUPLE", "DICT", "SET", "FROZEN", "ARRAY", "SCALAR", "OBJECT",
                     "BIGINT", "BYTEARR")

_INT_MIN, _INT_MAX = -(2**63), 2**64 - 1  # what msgpack holds as an int
# dtype.str of a plain (not structured, not object) numpy dtype: byte order, kind, item size and
# a datetime unit ('<f8', '|b1', '<U5', '<M8[ns]'); parsed by np.dtype only once it matches.
_DTYPE = re.compile(r"[<>|=][biufcmMSUV][0-9]{1,9}(\[[0-9]*[a-zA-Z]{1,2}\])?")


# ---------------------------------------------------------------------------- registry


@dataclass(frozen=True)
class _Codec:
    """How one class is written and rebuilt.

    Attributes:
        name: its name in the blob (stable: not the module path, which may move).
        cls: the class; only exactly this type is written (no subclasses).
        fields: the instance attributes written, in this order; an instance with others is
            refused on encode, a blob with other fields on decode.
        check: rebuilt instances run the class's ``__post_init__`` (configuration checks).
        derived: attributes not written: ``rebuild`` sets them from ``fields`` on decode.
        rebuild: sets ``derived`` on a rebuilt instance.
    """

    name: str
    cls: type
    fields: tuple[str, ...]
    check: bool = False
    derived: tuple[str, ...] = ()
    rebuild: Callable[[Any], None] | None = None

    def state(self, obj: object) -> list[object]:
        attrs = obj.__dict__
        if len(attrs) != len(self.fields) + len(self.derived) or any(f not in attrs for f in self.fields):
            extra = sorted(set(attrs) - set(self.fields) - set(self.derived))
            missing = sorted(set(self.fields) - set(attrs))
            raise CheckpointError(f"{self.name}: attributes differ from the registry's (not written: "
                                  f"{', '.join(extra) or '-'}; missing: {', '.join(missing) or '-'})")
        return [attrs[f] for f in self.fields]

    def build(self, values: Sequence[object]) -> object:
        obj: Any = object.__new__(self.cls)
        for name, value in zip(self.fields, values, strict=True):
            object.__setattr__(obj, name, value)  # frozen dataclasses too
        if self.rebuild is not None:
            self.rebuild(obj)
        if self.check:
            try:
                obj.__post_init__()
            except (ValueError, TypeError, WardmapError) as exc:
                raise CheckpointError(f"{self.name}: invalid: {exc}") from exc
        return obj


def _dataclass(name: str, cls: type, *, check: bool = False) -> _Codec:
    return _Codec(name, cls, tuple(f.name for f in dataclasses.fields(cls)), check=check)


def _rebuild_grid(grid: SpatialGrid) -> None:
    """``SpatialGrid._cells`` (cell -> keys) from ``_where`` (key -> (cell, position))."""
    where = grid.__dict__["_where"]
    if not isinstance(where, dict):
        raise CheckpointError(f"SpatialGrid: _where must be a dict, got {type(where).__name__}")
    cells: defaultdict[tuple[int, int, int], set[int]] = defaultdict(set)
    for key, entry in where.items():
        if not (isinstance(entry, tuple) and len(entry) == 2 and isinstance(entry[0], tuple)):
            raise CheckpointError(f"SpatialGrid: _where[{key!r}] must be (cell, position), got {entry!r}")
        cells[entry[0]].add(key)
    grid.__dict__.pop("_where")
    grid._cells, grid._where = cells, where  # the constructor's attribute order


_ASSOCIATOR_FIELDS: Final = (
    "config", "_checked", "_min_width", "_min_height", "_together", "_on_floor", "_full_extent",
    "_completed", "_within", "_fitting", "_group_shape", "_streams", "_next_keyframe", "_next_mid",
    "_next_id", "_groups_done", "_landmarks", "_owner", "_sigma", "_extent", "_box", "_solid", "_retired",
    "_grid",
    "_merge_radius", "_poses_cache", "_grown", "_fresh", "_merged", "beyond_range",
)

REGISTRY: Final[tuple[_Codec, ...]] = (
    _Codec("Associator", Associator, _ASSOCIATOR_FIELDS),
    _dataclass("AssociationConfig", AssociationConfig, check=True),
    _dataclass("MotConfig", MotConfig, check=True),
    _dataclass("HdpConfig", HdpConfig, check=True),
    _dataclass("RefineConfig", RefineConfig, check=True),
    _dataclass("NearestConfig", NearestConfig, check=True),
    _dataclass("LandmarkState", _LandmarkState),
    _dataclass("Stream", _Stream),
    _Codec("KeyframeGrouper", KeyframeGrouper,
           ("size", "overlap", "_first", "_next_group", "_last", "_covered")),
    _Codec("SpatialGrid", SpatialGrid, ("cell_m", "_where"), derived=("_cells",), rebuild=_rebuild_grid),
    _dataclass("KeyframeView", KeyframeView),
    _dataclass("PinholeCamera", PinholeCamera, check=True),
    _dataclass("ObjectMeasurement", ObjectMeasurement),
    _dataclass("Landmark", Landmark),
    _dataclass("LandmarkChange", LandmarkChange),
)
"""The classes a state may hold: nothing else is written or rebuilt. A class added to the
associator's state needs an entry here (and :data:`VERSION` bumped); encoding one that has none
raises :class:`CheckpointError` naming it."""

_BY_TYPE: Final = {c.cls: c for c in REGISTRY}
_BY_NAME: Final = {c.name: c for c in REGISTRY}


# ---------------------------------------------------------------------------- encode


def encode(obj: object) -> bytes:
    """The state ``obj`` as bytes (see the module docstring for the layout).

    Args:
        obj: None, bool, int, float, str, bytes, bytearray, list, tuple, dict, set, frozenset,
            numpy arrays and scalars (not of object or structured dtype), instances of
            :data:`REGISTRY` classes, nested in any way without reference cycles.

    Raises:
        CheckpointError: a value of another type, an array of object or structured dtype, a
            registry instance with attributes the registry does not list, a reference cycle.
    """
    enc = _Encoder()
    try:
        root = enc.value(obj)
        head = msgpack.packb([FORMAT, VERSION])
        body = msgpack.packb([enc.table, root])
    except RecursionError as exc:
        raise CheckpointError("state nested too deeply to encode") from exc
    except UnicodeEncodeError as exc:
        raise CheckpointError(f"a str is not valid unicode (lone surrogate): {exc}") from exc
    except ValueError as exc:  # str() of an int beyond sys.get_int_max_str_digits()
        raise CheckpointError(f"cannot encode: {exc}") from exc
    return head + body


class _Encoder:
    def __init__(self) -> None:
        self.memo: dict[int, tuple[int, object]] = {}  # id -> (index, the object: kept alive)
        self.active: set[int] = set()  # ids being written (a second visit is a cycle)
        self.classes: dict[str, int] = {}
        self.table: list[list[object]] = []
        self.dtypes: dict[np.dtype[Any], str] = {}  # checked once each

    def value(self, x: object) -> object:
        t = type(x)
        if x is None or t is bool or t is float or t is str or t is bytes:
            return x
        if t is int:
            return x if _INT_MIN <= x <= _INT_MAX else [BIGINT, str(x)]  # type: ignore[operator]
        key = id(x)
        hit = self.memo.get(key)
        if hit is not None:
            return [REF, hit[0]]
        if isinstance(x, np.generic):
            return [SCALAR, self._dtype(x.dtype, t.__name__), x.tobytes()]
        if key in self.active:
            raise CheckpointError(f"reference cycle through a {t.__name__}: not supported")
        self.active.add(key)
        node = self._node(x, t)
        self.active.discard(key)
        self.memo[key] = (len(self.memo), x)
        return node

    def _node(self, x: Any, t: type) -> list[object]:
        value = self.value
        if t is list:
            return [LIST, *map(value, x)]
        if t is tuple:
            return [TUPLE, *map(value, x)]
        if t is dict:
            node: list[object] = [DICT]
            for k, v in x.items():
                node.append(value(k))
                node.append(value(v))
            return node
        if t is set:
            return [SET, *map(value, x)]
        if t is frozenset:
            return [FROZEN, *map(value, x)]
        if t is np.ndarray:
            return [ARRAY, self._dtype(x.dtype, "array"), list(x.shape), x.tobytes(order="C")]
        if t is bytearray:
            return [BYTEARR, bytes(x)]
        codec = _BY_TYPE.get(t)
        if codec is None:
            raise CheckpointError(f"cannot encode a {t.__module__}.{t.__qualname__}: not a data type nor a "
                                  "registry class (server/association/state.py REGISTRY)")
        index = self.classes.get(codec.name)
        if index is None:
            index = self.classes[codec.name] = len(self.table)
            self.table.append([codec.name, list(codec.fields)])
        return [OBJECT, index, *map(value, codec.state(x))]

    def _dtype(self, dtype: np.dtype[Any], what: str) -> str:
        text = self.dtypes.get(dtype)
        if text is None:
            if dtype.hasobject:
                raise CheckpointError(f"{what} of object dtype: refused (it would hold arbitrary objects)")
            text = dtype.str
            if dtype.names is not None or dtype.subdtype is not None or not _DTYPE.fullmatch(text):
                raise CheckpointError(f"{what} of dtype {dtype}: only plain (not structured) dtypes "
                                      "are written")
            self.dtypes[dtype] = text
        return text


# ---------------------------------------------------------------------------- decode


def decode(blob: bytes) -> object:
    """The state :func:`encode` wrote into ``blob``; it builds only data types and :data:`REGISTRY`
    classes, and runs no code the blob names.

    Raises:
        CheckpointError: naming what is wrong: not this format, another version, truncated or
            trailing bytes, a malformed node, an unknown tag, a class not in the registry or
            with other fields, an array of object dtype or whose bytes do not fit its shape, a
            reference to nothing, an invalid configuration.
    """
    if not isinstance(blob, (bytes, bytearray, memoryview)):
        raise CheckpointError(f"association state must be bytes, got {type(blob).__name__}")
    data = bytes(blob)
    unpacker = msgpack.Unpacker(use_list=True, raw=False, strict_map_key=True,
                                max_buffer_size=max(len(data), 1), ext_hook=_refuse_ext)
    unpacker.feed(data)
    try:
        head = unpacker.unpack()
    except msgpack.OutOfData as exc:
        raise CheckpointError(f"not a {FORMAT} blob: truncated before its header "
                              f"({len(data)} bytes)") from exc
    except (ValueError, msgpack.UnpackException, CheckpointError) as exc:
        raise CheckpointError(f"not a {FORMAT} blob: unreadable header "
                              f"({type(exc).__name__}: {exc})") from exc
    if not (isinstance(head, list) and len(head) == 2 and head[0] == FORMAT):
        raise CheckpointError(f"not a {FORMAT} blob (header {str(head)[:80]})")
    if type(head[1]) is not int or head[1] != VERSION:
        raise CheckpointError(f"{FORMAT} version {head[1]!r} is not supported (this code reads version "
                              f"{VERSION})")
    try:
        body = unpacker.unpack()
    except msgpack.OutOfData as exc:
        raise CheckpointError(f"{FORMAT}: truncated ({len(data)} bytes)") from exc
    except (ValueError, msgpack.UnpackException, CheckpointError) as exc:
        raise CheckpointError(f"{FORMAT}: malformed ({type(exc).__name__}: {exc})") from exc
    if unpacker.tell() != len(data):
        raise CheckpointError(f"{FORMAT}: {len(data) - unpacker.tell()} bytes after the state")
    if not (isinstance(body, list) and len(body) == 2 and isinstance(body[0], list)):
        raise CheckpointError(f"{FORMAT}: the body must be [classes, root]")
    dec = _Decoder(_class_table(body[0]))
    try:
        return dec.value(body[1])
    except RecursionError as exc:
        raise CheckpointError(f"{FORMAT}: nested too deeply") from exc


def _refuse_ext(code: int, data: bytes) -> object:
    raise CheckpointError(f"msgpack extension type {code} is not part of {FORMAT}")


def _class_table(entries: list[object]) -> list[_Codec]:
    out = []
    for k, entry in enumerate(entries):
        if not (isinstance(entry, list) and len(entry) == 2 and isinstance(entry[0], str)
                and isinstance(entry[1], list)):
            raise CheckpointError(f"{FORMAT}: class table entry {k} must be [name, [field, ...]]")
        name, fields = entry
        codec = _BY_NAME.get(name)
        if codec is None:
            raise CheckpointError(f"{FORMAT}: class {name[:80]!r} is not in the registry: refused")
        if tuple(fields) != codec.fields:
            raise CheckpointError(f"{FORMAT}: {name} was written with fields {fields} but this code has "
                                  f"{list(codec.fields)}")
        out.append(codec)
    return out


class _Decoder:
    def __init__(self, classes: list[_Codec]) -> None:
        self.classes = classes
        self.memo: list[object] = []
        self.dtypes: dict[str, np.dtype[Any]] = {}

    def value(self, v: object) -> object:
        t = type(v)
        if v is None or t is bool or t is int or t is float or t is str or t is bytes:
            return v
        if t is not list:
            raise CheckpointError(f"{FORMAT}: unexpected {t.__name__} where a value belongs")
        node: list[Any] = v  # type: ignore[assignment]
        tag = node[0] if node else None
        if type(tag) is not int or not 0 <= tag < len(_TAG_NAMES):
            raise CheckpointError(f"{FORMAT}: unknown node tag {str(tag)[:40]}")
        if tag == REF:
            return self._ref(node)
        if tag == BIGINT:
            return _bigint(node)
        if tag == SCALAR:
            return _scalar(node, self.dtypes)
        out = self._node(tag, node)
        self.memo.append(out)
        return out

    def _ref(self, node: list[Any]) -> object:
        if len(node) != 2 or type(node[1]) is not int or not 0 <= node[1] < len(self.memo):
            raise CheckpointError(f"{FORMAT}: reference {str(node[1:])[:40]} to no value "
                                  f"({len(self.memo)} so far)")
        return self.memo[node[1]]

    def _node(self, tag: int, node: list[Any]) -> object:
        value = self.value
        items = node[1:]
        try:
            if tag == LIST:
                return [value(x) for x in items]
            if tag == TUPLE:
                return tuple(value(x) for x in items)
            if tag == DICT:
                if len(items) % 2:
                    raise CheckpointError(f"{FORMAT}: a dict node holds an odd number of keys and values")
                out = {}
                for k in range(0, len(items), 2):
                    key = value(items[k])
                    out[key] = value(items[k + 1])
                return out
            if tag == SET:
                return {value(x) for x in items}
            if tag == FROZEN:
                return frozenset(value(x) for x in items)
        except TypeError as exc:  # an unhashable key or member
            raise CheckpointError(f"{FORMAT}: {_TAG_NAMES[tag]} node: {exc}") from exc
        if tag == ARRAY:
            return _array(node, self.dtypes)
        if tag == BYTEARR:
            if len(node) != 2 or type(node[1]) is not bytes:
                raise CheckpointError(f"{FORMAT}: a bytearray node must be [tag, bytes]")
            return bytearray(node[1])
        # OBJECT
        if len(node) < 2 or type(node[1]) is not int or not 0 <= node[1] < len(self.classes):
            raise CheckpointError(f"{FORMAT}: object node names class {str(node[1:2])[:40]}, not in the "
                                  f"blob's table of {len(self.classes)}")
        codec = self.classes[node[1]]
        if len(node) - 2 != len(codec.fields):
            raise CheckpointError(f"{FORMAT}: {codec.name} node holds {len(node) - 2} values for "
                                  f"{len(codec.fields)} fields")
        return codec.build([value(x) for x in node[2:]])


def _dtype(text: object, known: dict[str, np.dtype[Any]]) -> np.dtype[Any]:
    """The dtype written as ``text``; ``known``: those already checked in this blob."""
    dtype = known.get(text) if type(text) is str else None
    if dtype is not None:
        return dtype
    if type(text) is not str:
        raise CheckpointError(f"{FORMAT}: a dtype must be a str, got {type(text).__name__}")
    if text[1:2] == "O":
        raise CheckpointError(f"{FORMAT}: array of object dtype ({text!r}): refused")
    if not _DTYPE.fullmatch(text):
        raise CheckpointError(f"{FORMAT}: dtype {text[:40]!r} is not a plain numpy dtype")
    try:
        dtype = known[text] = np.dtype(text)
    except TypeError as exc:
        raise CheckpointError(f"{FORMAT}: dtype {text!r}: {exc}") from exc
    return dtype


def _array(node: list[Any], dtypes: dict[str, np.dtype[Any]]) -> np.ndarray:
    if len(node) != 4 or type(node[2]) is not list or type(node[3]) is not bytes:
        raise CheckpointError(f"{FORMAT}: an array node must be [tag, dtype, shape, bytes]")
    dtype = _dtype(node[1], dtypes)
    shape = node[2]
    count = 1
    for n in shape:
        if type(n) is not int or n < 0 or len(shape) > 32:
            raise CheckpointError(f"{FORMAT}: array shape {str(shape)[:80]} is not up to 32 sizes >= 0")
        count *= n
    raw: bytes = node[3]
    if count * dtype.itemsize != len(raw):
        raise CheckpointError(f"{FORMAT}: array {dtype.str} {tuple(shape)} needs {count * dtype.itemsize} "
                              f"bytes, has {len(raw)}")
    if not raw:
        return np.zeros(shape, dtype)
    return np.frombuffer(raw, dtype).reshape(shape).copy()  # writeable, owns its memory


def _scalar(node: list[Any], dtypes: dict[str, np.dtype[Any]]) -> object:
    if len(node) != 3 or type(node[2]) is not bytes:
        raise CheckpointError(f"{FORMAT}: a numpy scalar node must be [tag, dtype, bytes]")
    dtype = _dtype(node[1], dtypes)
    if dtype.itemsize == 0 or len(node[2]) != dtype.itemsize:
        raise CheckpointError(f"{FORMAT}: numpy scalar {dtype.str} needs {dtype.itemsize} bytes, "
                              f"has {len(node[2])}")
    return np.frombuffer(node[2], dtype)[0]


def _bigint(node: list[Any]) -> int:
    if len(node) != 2 or type(node[1]) is not str or not re.fullmatch(r"-?[0-9]{1,4300}", node[1]):
        raise CheckpointError(f"{FORMAT}: a big int node must be [tag, decimal str]")
    return int(node[1])

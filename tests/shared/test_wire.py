"""Tests of wardmap.shared.wire: round trips, lossless rasters, malformed input, fuzzing, sizes."""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any, get_args

import cv2
import msgpack
import numpy as np
import pytest
from factories import (
    T0,
    TH,
    TW,
    H,
    W,
    depth_image,
    full_keyframe,
    mutate,
    noise_jpeg,
    pack,
    random_pose,
    raster_bomb,
    thermal_image,
    with_jpeg_size,
    zero_raster_stream,
)

from wardmap.edge.tracker import PoseSource as TrackerPoseSource
from wardmap.shared import wire
from wardmap.shared.dataset import DatasetReader, Frame
from wardmap.shared.errors import WireError
from wardmap.shared.se3 import se3_exp
from wardmap.shared.wire import (
    AckMsg,
    HeartbeatMsg,
    Intrinsics,
    KeyframeMsg,
    Keypoints,
    PackedRaster,
    RasterMeta,
)

# --------------------------------------------------------------------------- helpers


def wire_dict(msg: wire.Message) -> dict[str, Any]:
    return dict(msgpack.unpackb(wire.encode(msg), raw=False))


def assert_keyframes_equal(a: KeyframeMsg, b: KeyframeMsg) -> None:
    assert (a.robot_id, a.session_id, a.seq, a.stamp, a.pose_source) == (
        b.robot_id, b.session_id, b.seq, b.stamp, b.pose_source)
    np.testing.assert_allclose(a.T_odom_camera, b.T_odom_camera, atol=1e-12)
    if a.T_odom_base is None:
        assert b.T_odom_base is None
    else:
        assert b.T_odom_base is not None
        np.testing.assert_allclose(a.T_odom_base, b.T_odom_base, atol=1e-12)
    if a.T_map_odom is None:
        assert b.T_map_odom is None
    else:
        assert b.T_map_odom is not None
        np.testing.assert_allclose(a.T_map_odom, b.T_map_odom, atol=1e-12)
    for name in ("uv", "octave", "angle_deg", "depth_m", "descriptors", "point_id"):
        x, y = getattr(a.keypoints, name), getattr(b.keypoints, name)
        if x is None:
            assert y is None, name
            continue
        assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert a.rgb_jpeg == b.rgb_jpeg
    assert a.depth == b.depth and a.thermal == b.thermal
    assert a.intrinsics == b.intrinsics and a.calib_ref == b.calib_ref


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("thermal", [True, False])
@pytest.mark.parametrize("intrinsics", [True, False])
@pytest.mark.parametrize("base", [True, False])
def test_keyframe_round_trip(thermal: bool, intrinsics: bool, base: bool) -> None:
    """A keyframe with every combination of optional parts decodes to an equal keyframe:
    arrays and bytes exactly, poses to 1e-12 (they travel as translation + quaternion)."""
    rng = np.random.default_rng(1)
    msg = full_keyframe(rng, thermal=thermal, intrinsics=intrinsics, base=base)
    back = wire.decode_keyframe(wire.encode(msg))
    assert_keyframes_equal(msg, back)


def test_keyframe_without_keypoints_round_trips() -> None:
    """A keyframe with zero keypoints (e.g. a blank wall) is valid and round trips."""
    rng = np.random.default_rng(2)
    msg = full_keyframe(rng, n=0)
    back = wire.decode_keyframe(wire.encode(msg))
    assert len(back.keypoints) == 0
    assert back.keypoints.descriptors.shape == (0, 32)


def test_int16_octaves_round_trip() -> None:
    """Octaves may travel as int16 (SIFT-style -1 included); the dtype is preserved."""
    rng = np.random.default_rng(3)
    msg = full_keyframe(rng, n=5)
    kp = msg.keypoints
    kp16 = Keypoints(kp.uv, np.array([-1, 0, 1, 2, 31], np.int16), kp.angle_deg, kp.depth_m, kp.descriptors)
    msg16 = KeyframeMsg(msg.robot_id, msg.session_id, msg.seq, msg.stamp, msg.T_odom_camera, "thermal",
                        kp16, msg.rgb_jpeg, msg.depth, intrinsics=msg.intrinsics)
    back = wire.decode_keyframe(wire.encode(msg16))
    assert back.keypoints.octave.dtype == np.int16
    assert back.keypoints.octave.tolist() == [-1, 0, 1, 2, 31]


def test_point_ids_are_optional_and_round_trip() -> None:
    """Map point ids travel as int32 when the robot sends them and are absent (not an empty
    array) when it does not: a keyframe from a robot without them decodes without them."""
    rng = np.random.default_rng(4)
    msg = full_keyframe(rng, n=6)
    assert msg.keypoints.point_id is not None
    back = wire.decode_keyframe(wire.encode(msg))
    assert back.keypoints.point_id is not None and back.keypoints.point_id.dtype == np.int32
    assert back.keypoints.point_id.tolist() == [-1, 1001, 1002, 1003, 1004, -1]
    plain = replace(msg, keypoints=replace(msg.keypoints, point_id=None))
    assert "point_id" not in wire_dict(plain)["keypoints"]
    assert wire.decode_keyframe(wire.encode(plain)).keypoints.point_id is None


def test_pose_through_quaternion_is_rigid_and_close() -> None:
    """50 random poses survive the (t, q_xyzw) encoding to 1e-12 and stay proper rotations."""
    rng = np.random.default_rng(4)
    msg = full_keyframe(rng)
    for _ in range(50):
        T = random_pose(rng)
        m = KeyframeMsg(msg.robot_id, msg.session_id, 1, 1.0, T, "odometry", msg.keypoints, msg.rgb_jpeg,
                        msg.depth, calib_ref="c")
        back = wire.decode_keyframe(wire.encode(m)).T_odom_camera
        np.testing.assert_allclose(back, T, atol=1e-12)
        np.testing.assert_allclose(back[:3, :3] @ back[:3, :3].T, np.eye(3), atol=1e-12)


def test_ack_and_heartbeat_round_trip() -> None:
    """Acks and heartbeats decode to equal messages; typed decoders reject the other schemas."""
    ack = AckMsg("robot_0", "s1", 7, "rejected", "depth.data: corrupt — robot ✓")
    hb = HeartbeatMsg("robot_0", "s1", T0, {"queue_len": 3, "track_ms": 12.5, "big": 2**64 - 1, "neg": -4})
    assert wire.decode(wire.encode(ack)) == ack
    assert wire.decode_ack(wire.encode(ack)) == ack
    assert wire.decode_heartbeat(wire.encode(hb)) == hb
    with pytest.raises(WireError) as e:
        wire.decode_keyframe(wire.encode(ack))
    assert e.value.field == "schema"
    with pytest.raises(WireError) as e:
        wire.decode_ack(wire.encode(hb))
    assert e.value.field == "schema"


@pytest.mark.parametrize("status", ["stored", "duplicate", "rejected", "retry"])
def test_every_ack_status_round_trips(status: str) -> None:
    """Every ack status, including ``retry`` (the server's storage failed: keep and resend),
    encodes and decodes to an equal message."""
    ack = AckMsg("robot_0", "s1", 3, status, "server storage: cannot store; resend later")  # type: ignore[arg-type]
    assert wire.decode_ack(wire.encode(ack)) == ack
    assert wire.ACK_STATUSES == ("stored", "duplicate", "rejected", "retry")


def test_pose_sources_match_tracker() -> None:
    """The wire's pose sources are exactly the tracker's (shared/ cannot import edge/)."""
    assert set(wire.POSE_SOURCES) == set(get_args(TrackerPoseSource))


# --------------------------------------------------------------------------- rasters


@pytest.mark.parametrize("unit_m", [0.001, 0.0002, 0.005])
def test_depth_is_lossless_at_its_unit(unit_m: float) -> None:
    """Decoded depth equals round(depth / unit) * unit as float32 exactly; holes (0, NaN,
    negative, inf) decode as 0; re-encoding the decoded image gives identical bytes."""
    rng = np.random.default_rng(5)
    d = depth_image(rng, 97, 61) * np.float32(unit_m / 0.001 / 8 * 13)  # stay within 65535 units
    d[0, :4] = [np.nan, -1.0, np.inf, 0.0]
    data, meta = wire.encode_depth(d, unit_m=unit_m)
    assert (meta.width, meta.height, meta.unit) == (97, 61, unit_m)
    out = wire.decode_depth(data, meta)
    clean = np.where(np.isfinite(d) & (d > 0), d, 0).astype(np.float64)
    expected = (np.rint(clean / unit_m) * unit_m).astype(np.float32)
    assert out.dtype == np.float32 and out.shape == d.shape
    assert np.array_equal(out, expected)
    assert np.max(np.abs(out - clean)) <= unit_m / 2 + 1e-6
    assert wire.encode_depth(out, unit_m=unit_m)[0] == data


def test_raster_codec_extremes() -> None:
    """The delta codec is exact at the uint16 extremes (residuals that wrap around 2**16)."""
    counts = np.zeros((8, 9), np.uint16)
    counts[1::2] = 65535
    counts[:, ::3] = 1
    data, meta = wire.encode_depth(counts.astype(np.float64) * 0.001)
    assert np.array_equal(PackedRaster(data, meta).counts(), counts)


def test_thermal_is_lossless_at_centikelvin() -> None:
    """Thermal decodes to round(K / 0.01) * 0.01 exactly, with its own size."""
    rng = np.random.default_rng(6)
    t = thermal_image(rng)
    data, meta = wire.encode_thermal(t)
    assert (meta.width, meta.height) == (TW, TH)
    out = wire.decode_thermal(data, meta)
    assert np.array_equal(out, (np.rint(t.astype(np.float64) / 0.01) * 0.01).astype(np.float32))


def test_raster_out_of_range_raises() -> None:
    """Depth beyond 65535 units is an error, never silently clipped; so is a 3-D array."""
    with pytest.raises(WireError) as e:
        wire.encode_depth(np.full((4, 4), 70.0, np.float32))
    assert e.value.field == "depth"
    with pytest.raises(WireError) as e:
        wire.encode_thermal(np.zeros((4, 4, 2), np.float32))
    assert e.value.field == "thermal"


def test_jpeg_size_reads_header() -> None:
    """jpeg_size reads width, height and channels from the SOF header of real JPEGs."""
    rng = np.random.default_rng(7)
    assert wire.jpeg_size(noise_jpeg(rng, 123, 45)) == (123, 45, 3)
    assert wire.jpeg_size(noise_jpeg(rng, 20, 10, channels=1)) == (20, 10, 1)


# --------------------------------------------------------------------------- malformed input

Mutation = Callable[[dict[str, Any]], Any]


def _set(path: str, value: Any) -> Mutation:
    def f(d: dict[str, Any]) -> Any:
        *parents, last = path.split(".")
        node = d
        for p in parents:
            node = node[p]
        node[last] = value
        return d
    return f


def _delete(path: str) -> Mutation:
    def f(d: dict[str, Any]) -> Any:
        *parents, last = path.split(".")
        node = d
        for p in parents:
            node = node[p]
        del node[last]
        return d
    return f


def _reshape_uv(d: dict[str, Any]) -> Any:
    n = d["keypoints"]["uv"]["shape"][0]
    d["keypoints"]["uv"] = {"dtype": "float32", "shape": [n, 3], "data": bytes(12 * n)}
    return d


def _uv_nan(d: dict[str, Any]) -> Any:
    uv = np.frombuffer(d["keypoints"]["uv"]["data"], "<f4").copy()
    uv[3] = np.nan
    d["keypoints"]["uv"]["data"] = uv.tobytes()
    return d


def _array_values(name: str, dtype: str, value: float) -> Mutation:
    def f(d: dict[str, Any]) -> Any:
        a = np.frombuffer(d["keypoints"][name]["data"], dtype).copy()
        a[0] = value
        d["keypoints"][name]["data"] = a.tobytes()
        return d
    return f


def _octave_count(d: dict[str, Any]) -> Any:
    d["keypoints"]["octave"] = {"dtype": "int8", "shape": [3], "data": bytes(3)}
    return d


def _uv_float64(d: dict[str, Any]) -> Any:
    n = d["keypoints"]["uv"]["shape"][0]
    d["keypoints"]["uv"] = {"dtype": "float64", "shape": [n, 2], "data": bytes(16 * n)}
    return d


def _both_cameras(d: dict[str, Any]) -> Any:
    d["calib_ref"] = "abc"
    return d


def _jpeg_size(width: int, height: int) -> Mutation:
    def f(d: dict[str, Any]) -> Any:
        d["rgb_jpeg"] = noise_jpeg(np.random.default_rng(0), width, height)
        return d
    return f


def _grey_jpeg(d: dict[str, Any]) -> Any:
    d["rgb_jpeg"] = noise_jpeg(np.random.default_rng(0), W, H, channels=1)
    return d


def _corrupt(path: str) -> Mutation:
    def f(d: dict[str, Any]) -> Any:
        raster = d[path]
        raster["data"] = raster["data"][:10] + b"\x00" * 8 + raster["data"][18:]
        return d
    return f


def _depth_size(d: dict[str, Any]) -> Any:
    d["depth"] = dict(zip(("data", "meta"), wire.encode_depth(np.ones((H, W - 1), np.float32)), strict=True))
    meta = d["depth"].pop("meta")
    d["depth"].update(codec=meta.codec, width=meta.width, height=meta.height, unit=meta.unit)
    return d


KEYFRAME_CASES: list[tuple[str, Mutation, str]] = [
    ("robot_id wrong type", _set("robot_id", 5), "robot_id"),
    ("robot_id missing", _delete("robot_id"), "robot_id"),
    ("robot_id bad chars", _set("robot_id", "robot 0!"), "robot_id"),
    ("robot_id empty", _set("robot_id", ""), "robot_id"),
    ("robot_id too long", _set("robot_id", "r" * 65), "robot_id"),
    ("session_id bad", _set("session_id", "a/b"), "session_id"),
    ("seq negative", _set("seq", -1), "seq"),
    ("seq too large", _set("seq", 2**63), "seq"),
    ("seq string", _set("seq", "1"), "seq"),
    ("seq bool", _set("seq", True), "seq"),
    ("seq float", _set("seq", 1.0), "seq"),
    ("stamp NaN", _set("stamp", math.nan), "stamp"),
    ("stamp inf", _set("stamp", math.inf), "stamp"),
    ("stamp zero", _set("stamp", 0.0), "stamp"),
    ("stamp string", _set("stamp", "now"), "stamp"),
    ("stamp missing", _delete("stamp"), "stamp"),
    ("pose missing", _delete("T_odom_camera"), "T_odom_camera"),
    ("pose wrong type", _set("T_odom_camera", [1, 2, 3]), "T_odom_camera"),
    ("pose non-unit quaternion", _set("T_odom_camera.q_xyzw", [0.0, 0.0, 0.0, 1.01]), "T_odom_camera.q_xyzw"),
    ("pose zero quaternion", _set("T_odom_camera.q_xyzw", [0.0, 0.0, 0.0, 0.0]), "T_odom_camera.q_xyzw"),
    ("pose NaN translation", _set("T_odom_camera.t", [math.nan, 0.0, 0.0]), "T_odom_camera.t[0]"),
    ("pose short translation", _set("T_odom_camera.t", [0.0, 0.0]), "T_odom_camera.t"),
    ("pose missing quaternion", _delete("T_odom_camera.q_xyzw"), "T_odom_camera.q_xyzw"),
    ("pose extra key", _set("T_odom_camera.R", [1]), "T_odom_camera.R"),
    ("base non-unit quaternion", _set("T_odom_base.q_xyzw", [0.5, 0.0, 0.0, 0.5]), "T_odom_base.q_xyzw"),
    ("map pose NaN", _set("T_map_odom.t", [0.0, math.nan, 0.0]), "T_map_odom.t[1]"),
    ("map pose wrong type", _set("T_map_odom", "dock"), "T_map_odom"),
    ("pose_source unknown", _set("pose_source", "teleport"), "pose_source"),
    ("pose_source wrong type", _set("pose_source", 3), "pose_source"),
    ("keypoints missing", _delete("keypoints"), "keypoints"),
    ("keypoints wrong type", _set("keypoints", b"x"), "keypoints"),
    ("uv wrong shape", _reshape_uv, "keypoints.uv"),
    ("uv float64", _uv_float64, "keypoints.uv.dtype"),
    ("uv object dtype", _set("keypoints.uv.dtype", "object"), "keypoints.uv.dtype"),
    ("uv dtype wrong type", _set("keypoints.uv.dtype", 7), "keypoints.uv.dtype"),
    ("uv data short", _set("keypoints.uv.data", b"\x00" * 8), "keypoints.uv.data"),
    ("uv shape negative", _set("keypoints.uv.shape", [-1, 2]), "keypoints.uv.shape"),
    ("uv shape huge", _set("keypoints.uv.shape", [2**40, 2]), "keypoints.uv.shape"),
    ("uv NaN", _uv_nan, "keypoints.uv"),
    ("uv outside image", _array_values("uv", "<f4", 1e4), "keypoints.uv"),
    ("octave count mismatch", _octave_count, "keypoints.octave"),
    ("octave out of range", _array_values("octave", "i1", -5), "keypoints.octave"),
    ("angle out of range", _array_values("angle_deg", "<f4", 400.0), "keypoints.angle_deg"),
    ("keypoint depth negative", _array_values("depth_m", "<f4", -1.0), "keypoints.depth_m"),
    ("descriptors wrong shape", _set("keypoints.descriptors.shape", [20, 16]), "keypoints.descriptors"),
    ("keypoints extra field", _set("keypoints.score", 1), "keypoints.score"),
    ("point_id float", _set("keypoints.point_id.dtype", "float32"), "keypoints.point_id.dtype"),
    ("point_id int16", _set("keypoints.point_id.dtype", "int16"), "keypoints.point_id.dtype"),
    ("point_id int64", _set("keypoints.point_id.dtype", "int64"), "keypoints.point_id.dtype"),
    ("point_id count mismatch", _set("keypoints.point_id.shape", [3]), "keypoints.point_id.data"),
    ("point_id below -1", _array_values("point_id", "<i4", -2), "keypoints.point_id"),
    ("unknown top-level field", _set("bogus", 1), "bogus"),
    ("both camera sources", _both_cameras, "intrinsics"),
    ("no camera source", _delete("intrinsics"), "intrinsics"),
    ("intrinsics fx negative", _set("intrinsics.fx", -1.0), "intrinsics.fx"),
    ("intrinsics cx NaN", _set("intrinsics.cx", math.nan), "intrinsics.cx"),
    ("intrinsics width string", _set("intrinsics.width", "64"), "intrinsics.width"),
    ("intrinsics distortion short", _set("intrinsics.distortion", [0.0] * 4), "intrinsics.distortion"),
    ("intrinsics missing fy", _delete("intrinsics.fy"), "intrinsics.fy"),
    ("jpeg size differs from intrinsics", _jpeg_size(W + 16, H), "rgb_jpeg"),
    ("jpeg wrong magic", _set("rgb_jpeg", b"\x89PNG\r\n\x1a\n" + bytes(100)), "rgb_jpeg"),
    ("jpeg truncated header", _set("rgb_jpeg", b"\xff\xd8\xff\xe0\x00\x10JF"), "rgb_jpeg"),
    ("jpeg empty", _set("rgb_jpeg", b""), "rgb_jpeg"),
    ("jpeg as string", _set("rgb_jpeg", "jpeg"), "rgb_jpeg"),
    ("jpeg greyscale", _grey_jpeg, "rgb_jpeg"),
    ("depth missing", _delete("depth"), "depth"),
    ("depth unknown codec", _set("depth.codec", "png"), "depth.codec"),
    ("depth unit zero", _set("depth.unit", 0.0), "depth.unit"),
    ("depth unit huge", _set("depth.unit", 5.0), "depth.unit"),
    ("depth width wrong", _set("depth.width", W // 2), "depth"),  # sizes: checked before inflating
    ("depth height huge", _set("depth.height", 10**6), "depth.height"),
    ("depth corrupt stream", _corrupt("depth"), "depth.data"),
    ("depth trailing bytes", lambda d: _set("depth.data", d["depth"]["data"] + b"x")(d), "depth.data"),
    ("depth not colour size", _depth_size, "depth"),
    ("thermal corrupt stream", _corrupt("thermal"), "thermal.data"),
    ("thermal wrong type", _set("thermal", 3), "thermal"),
    ("version unknown", _set("version", 2), "version"),
    ("version missing", _delete("version"), "version"),
    ("version string", _set("version", "1"), "version"),
    ("schema unknown", _set("schema", "wardmap.map"), "schema"),
    ("schema missing", _delete("schema"), "schema"),
    ("top level not a map", lambda d: [d], ""),
]


@pytest.fixture(scope="module")
def keyframe_wire() -> dict[str, Any]:
    return wire_dict(full_keyframe(np.random.default_rng(8)))


@pytest.mark.parametrize(("mutation", "field"), [c[1:] for c in KEYFRAME_CASES],
                         ids=[c[0] for c in KEYFRAME_CASES])
def test_invalid_keyframe_names_field(keyframe_wire: dict[str, Any], mutation: Mutation, field: str) -> None:
    """Each malformed variant of a valid keyframe raises WireError whose .field names the culprit."""
    payload = pack(mutation(copy.deepcopy(keyframe_wire)))
    with pytest.raises(WireError) as e:
        wire.decode(payload)
    assert e.value.field == field, str(e.value)


def test_wrong_shape_message_says_expected_and_got(keyframe_wire: dict[str, Any]) -> None:
    """The error for a (N, 3) uv array says what was expected and what came."""
    with pytest.raises(WireError, match=r"keypoints\.uv: expected shape \(N, 2\), got \(20, 3\)"):
        wire.decode(pack(_reshape_uv(copy.deepcopy(keyframe_wire))))


ACK = AckMsg("robot_0", "s1", 3, "stored", "")
HEARTBEAT = HeartbeatMsg("robot_0", "s1", T0, {"fps": 9.5, "queue_len": 2})

OTHER_CASES: list[tuple[str, wire.Message, Mutation, str]] = [
    ("ack status unknown", ACK, _set("status", "maybe"), "status"),
    ("ack reason too long", ACK, _set("reason", "é" * 1025), "reason"),
    ("ack reason wrong type", ACK, _set("reason", None), "reason"),
    ("ack seq negative", ACK, _set("seq", -3), "seq"),
    ("ack missing session", ACK, _delete("session_id"), "session_id"),
    ("ack extra field", ACK, _set("stamp", 1.0), "stamp"),
    ("heartbeat stat NaN", HEARTBEAT, _set("stats.fps", math.nan), "stats.fps"),
    ("heartbeat stat bool", HEARTBEAT, _set("stats.fps", True), "stats.fps"),
    ("heartbeat stat string", HEARTBEAT, _set("stats.fps", "9"), "stats.fps"),
    ("heartbeat stat nested", HEARTBEAT, _set("stats.fps", {"a": 1}), "stats.fps"),
    ("heartbeat stat key too long", HEARTBEAT, _set("stats." + "k" * 65, 1), "stats"),
    ("heartbeat too many stats", HEARTBEAT, _set("stats", {f"k{i}": i for i in range(65)}), "stats"),
    ("heartbeat stats not a map", HEARTBEAT, _set("stats", [1, 2]), "stats"),
    ("heartbeat stamp negative", HEARTBEAT, _set("stamp", -1.0), "stamp"),
]


@pytest.mark.parametrize(("msg", "mutation", "field"), [c[1:] for c in OTHER_CASES],
                         ids=[c[0] for c in OTHER_CASES])
def test_invalid_ack_and_heartbeat_name_field(msg: wire.Message, mutation: Mutation, field: str) -> None:
    """Malformed acks and heartbeats raise WireError naming the field."""
    with pytest.raises(WireError) as e:
        wire.decode(pack(mutation(wire_dict(msg))))
    assert e.value.field == field, str(e.value)


def test_payload_level_errors() -> None:
    """Oversize, truncated, garbage, non-map, non-bytes, ext types and deep nesting all raise
    WireError with the empty field (the payload as a whole)."""
    good = wire.encode(full_keyframe(np.random.default_rng(9)))
    deep = b"\x91" * 100_000 + b"\x00"  # 100k nested one-element arrays
    bad_utf8 = pack({"schema": "x"})[:-1] + b"\xff"
    cases: list[Any] = [good[: len(good) // 2], good[:1], b"", b"\xc1\xc1\xc1", good + b"\x00", deep,
                        bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8)),
                        pack([1, 2]), pack(msgpack.ExtType(5, b"abc")), bad_utf8, "not bytes",
                        pack({1: 2})]
    for payload in cases:
        with pytest.raises(WireError) as e:
            wire.decode(payload)
        assert e.value.field == "", (payload[:20], str(e.value))
    with pytest.raises(WireError) as e:
        wire.decode(good, max_bytes=len(good) - 1)
    assert e.value.field == "" and "exceeds" in str(e.value)


def test_constructors_validate() -> None:
    """Messages validate on construction too, so an invalid message cannot be encoded."""
    rng = np.random.default_rng(10)
    kf = full_keyframe(rng)
    cases: list[tuple[Callable[[], object], str]] = [
        (lambda: AckMsg("r", "s", 0, "ok"), "status"),
        (lambda: HeartbeatMsg("r", "s", 1.0, {"x": float("nan")}), "stats.x"),
        (lambda: Keypoints(kf.keypoints.uv.astype(np.float64), kf.keypoints.octave, kf.keypoints.angle_deg,
                           kf.keypoints.depth_m, kf.keypoints.descriptors), "keypoints.uv"),
        (lambda: KeyframeMsg("r", "s", 0, 1.0, np.eye(4) * 2, "rgb", kf.keypoints, kf.rgb_jpeg, kf.depth,
                             calib_ref="c"), "T_odom_camera"),
        (lambda: KeyframeMsg("r", "s", 0, 1.0, np.eye(4), "rgb", kf.keypoints, kf.rgb_jpeg,
                             PackedRaster(b"junk", kf.depth.meta), calib_ref="c"), "depth.data"),
        (lambda: RasterMeta(10, 10, 0.001, "png"), "codec"),
    ]
    for build, field in cases:
        with pytest.raises(WireError) as e:
            build()
        assert e.value.field == field, str(e.value)
    with pytest.raises(WireError):
        wire.encode("not a message")


# --------------------------------------------------------------------------- fuzzing

def test_fuzz_decode_raises_only_wire_errors() -> None:
    """1000 seeded random mutations (bit flips, truncations, insertions, structural edits of
    the decoded tree) of valid keyframes, acks and heartbeats: decode either returns a
    message or raises WireError -- never any other exception."""
    rng = np.random.default_rng(11)
    bases = [
        wire.encode(full_keyframe(rng, thermal=True, intrinsics=True)),
        wire.encode(full_keyframe(rng, thermal=False, intrinsics=False, base=False)),
        wire.encode(ACK),
        wire.encode(HEARTBEAT),
    ]
    outcomes = {"ok": 0, "wire_error": 0}
    for trial in range(1000):
        payload = mutate(bases[trial % len(bases)], rng)
        assert len(payload) <= wire.MAX_MESSAGE_BYTES
        try:
            wire.decode(payload)
            outcomes["ok"] += 1
        except WireError:
            outcomes["wire_error"] += 1
        except Exception as exc:  # the property under test
            pytest.fail(f"trial {trial}: {type(exc).__name__}: {exc}")
    assert outcomes["wire_error"] > 500


# --------------------------------------------------------------------------- sizes on simulated data


@pytest.fixture(scope="module")
def sim_frames(tmp_path_factory: pytest.TempPathFactory) -> list[Frame]:
    from wardmap.sim.runner import generate

    out = tmp_path_factory.mktemp("wire_sim")
    generate("walking_staff", 0, out, frames=5)
    reader = DatasetReader(out)
    return [reader.frame(i) for i in range(len(reader.stamps))]


def sim_keyframe(frame: Frame, rng: np.random.Generator, *, depth_stride: int = 1,
                 thermal: bool = True) -> KeyframeMsg:
    """A keyframe as a robot would send it: JPEG q85 colour, 1000 ORB features, mm depth."""
    bgr = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 85])
    assert ok
    orb = cv2.ORB.create(nfeatures=1000)
    kps, desc = orb.detectAndCompute(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), None)
    n = len(kps)
    uv = np.array([k.pt for k in kps], np.float32).reshape(n, 2)
    ij = np.clip(np.rint(uv).astype(int), 0, [frame.rgb.shape[1] - 1, frame.rgb.shape[0] - 1])
    h, w = frame.depth_m.shape
    return KeyframeMsg(
        "robot_0", "sim", frame.index, frame.stamp, se3_exp(rng.normal(size=6)), "rgb",
        Keypoints(uv, np.array([k.octave for k in kps], np.int8),
                  np.array([k.angle for k in kps], np.float32),
                  frame.depth_m[ij[:, 1], ij[:, 0]].astype(np.float32),
                  desc if desc is not None else np.zeros((0, 32), np.uint8)),
        bytes(buf.tobytes()),
        PackedRaster(*wire.encode_depth(frame.depth_m[::depth_stride, ::depth_stride])),
        intrinsics=Intrinsics(w, h, 525.0, 525.0, 319.5, 239.5, (0.0, 0.0, 0.0, 0.0, 0.0), 5000.0),
        T_odom_base=se3_exp(rng.normal(size=6)),
        thermal=PackedRaster(*wire.encode_thermal(frame.thermal_k))
        if thermal and frame.thermal_k is not None else None,
    )


def test_depth_codec_smaller_than_png(sim_frames: list[Frame]) -> None:
    """On simulated depth the delta16-zlib stream is smaller than a 16-bit PNG of the same
    millimetre counts (OpenCV, zlib level 3), and decodes exactly."""
    for frame in sim_frames:
        data, meta = wire.encode_depth(frame.depth_m)
        counts = PackedRaster(data, meta).counts()
        ok, png = cv2.imencode(".png", counts, [cv2.IMWRITE_PNG_COMPRESSION, 3])
        assert ok
        assert len(data) < len(png)
        assert np.array_equal(wire.decode_depth(data, meta), (counts * 0.001).astype(np.float32))


def test_keyframe_with_quarter_depth_under_150kb(sim_frames: list[Frame]) -> None:
    """With depth sent at 1/4 resolution (160x120 mm) and no thermal -- a configuration the
    schema allows -- simulated keyframes with 1000 keypoints fit the 150 KB budget."""
    rng = np.random.default_rng(13)
    for frame in sim_frames:
        msg = sim_keyframe(frame, rng, depth_stride=4, thermal=False)
        assert len(msg.keypoints) > 500
        payload = wire.encode(msg)
        assert len(payload) < 150_000
        assert_keyframes_equal(msg, wire.decode_keyframe(payload))


# --------------------------------------------------------------------------- bounded cost


def test_raster_bomb_is_refused_before_anything_is_inflated() -> None:
    """A 300 KB keyframe whose colour, depth and thermal headers declare 8192x8192 (valid streams of
    128 MiB each) is refused from its headers: WireError on ``rgb_jpeg`` in well under a second with
    under 8 MiB allocated at the peak (it took 5.9 s and 0.9 GB when the rasters were decoded)."""
    import time
    import tracemalloc

    payload = raster_bomb(np.random.default_rng(3))
    assert len(payload) < 400_000
    tracemalloc.start()
    t = time.perf_counter()
    try:
        with pytest.raises(WireError, match="MAX_DECODED_BYTES") as e:
            wire.decode(payload)
        elapsed = time.perf_counter() - t
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert e.value.field == "rgb_jpeg"
    assert elapsed < 0.5 and peak < 8 * 2**20, (elapsed, peak)


def test_decoded_size_is_capped_per_message(keyframe_wire: dict[str, Any]) -> None:
    """The cap counts colour (3 bytes a pixel), depth and thermal (2 each) from the headers:
    a colour header alone over the cap names ``rgb_jpeg``; a thermal raster that tips the sum
    over names ``thermal``; a 2048x2048 raster inside the cap is inflated and accepted."""
    big = dict(keyframe_wire, calib_ref="sha256:" + "ab" * 32)
    big.pop("intrinsics", None)
    side = 4200  # colour alone over 48 MiB
    big["rgb_jpeg"] = with_jpeg_size(big["rgb_jpeg"], side, side)
    big["depth"] = {**big["depth"], "width": side // 4, "height": side // 4,
                    "data": zero_raster_stream(side // 4, side // 4)}
    big.pop("thermal", None)
    with pytest.raises(WireError) as e:
        wire.decode(pack(big))
    assert e.value.field == "rgb_jpeg"
    ok = dict(big, rgb_jpeg=with_jpeg_size(big["rgb_jpeg"], 2048, 2048))
    ok["depth"] = {**big["depth"], "width": 2048, "height": 2048, "data": zero_raster_stream(2048, 2048)}
    assert wire.decode_keyframe(pack(ok)).depth.meta.width == 2048
    tipped = dict(ok, thermal={**ok["depth"], "unit": 0.01, "width": 4096, "height": 4096,
                               "data": zero_raster_stream(4096, 4096)})
    with pytest.raises(WireError) as e:
        wire.decode(pack(tipped))
    assert e.value.field == "thermal"

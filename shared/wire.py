"""Wire schema v1: the messages robots and the map server exchange over Zenoh.

Every message is one msgpack map ``{"schema": ..., "version": 1, ...fields}`` (the layout of
each field is in ``docs/wire.md``). Arrays travel as ``{"dtype", "shape", "data"}`` with
little-endian ``data`` bytes and a whitelisted dtype; poses as ``{"t": [x, y, z],
"q_xyzw": [x, y, z, w]}``; colour as JPEG; depth and thermal as quantised uint16 rasters
compressed losslessly (:func:`encode_depth`, :func:`encode_thermal`).

The message dataclasses validate themselves on construction, so a message that exists is a
valid message. :func:`decode` is the boundary for untrusted bytes: msgpack is unpacked
with size limits, every field is checked, and *any* malformed input raises
:class:`~wardmap.shared.errors.WireError` whose ``field`` is the dotted wire name of the
offending field (``""`` for the payload as a whole) -- never another exception type.
Nothing is ever pickled.

Frames and units follow docs/ARCHITECTURE.md: ``T_a_b`` maps points in frame b to frame a,
metres, seconds, kelvin.
"""

from __future__ import annotations

import math
import re
import struct
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Final, Literal, TypeAlias, TypeVar, get_args

import msgpack
import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import GeometryError, WireError
from wardmap.shared.se3 import check_transform, make_transform, quat_to_rotation, rotation_to_quat

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
U16 = NDArray[np.uint16]

SCHEMA_VERSION: Final = 1
"""The only wire version this module reads and writes."""
SCHEMA_KEYFRAME: Final = "wardmap.keyframe"
SCHEMA_ACK: Final = "wardmap.ack"
SCHEMA_HEARTBEAT: Final = "wardmap.heartbeat"

MAX_MESSAGE_BYTES: Final = 4 * 2**20
"""Largest payload :func:`decode` accepts by default and :func:`encode` produces (4 MiB)."""
MAX_KEYPOINTS: Final = 16384
"""Most keypoints one keyframe may carry."""
POINT_ID_MODULUS: Final = 2**31
"""Map point ids travel modulo this (int32, ``Keypoints.point_id``)."""
POINT_ID_SPAN: Final = POINT_ID_MODULUS // MAX_KEYPOINTS
"""Keypoints with one wire id are one point only in keyframes of a session fewer than this
many apart in ``seq`` (131072): a robot making fewer than :data:`MAX_KEYPOINTS` points per
keyframe sent does not come round to an id within that span."""
MAX_IMAGE_SIDE: Final = 8192
"""Largest width or height in pixels of any image on the wire."""
MAX_DECODED_BYTES: Final = 48 * 2**20
"""Most bytes one keyframe's images may decode to: 3 per colour pixel plus 2 per depth and
thermal pixel, as their headers declare (48 MiB: a 3840x2160 colour image with full-size
depth fits). Checked before anything is inflated, so a small message cannot declare huge
rasters (an 8192x8192 raster is 128 MiB)."""
_INFLATE_CHUNK: Final = 2**20
"""Validation inflates a raster this many bytes at a time and keeps none of them."""
MAX_TEXT_LEN: Final = 1024
"""Longest string anywhere in a message (e.g. an ack's reason), in characters."""
MAX_STATS: Final = 64
"""Most entries in a heartbeat's ``stats``."""
MAX_STAT_KEY_LEN: Final = 64
QUAT_NORM_TOL: Final = 1e-3
"""A transmitted quaternion must have norm within this of 1; it is then renormalised."""

DEPTH_UNIT_M: Final = 0.001
"""Default depth quantum: 1 mm. The depth sensor's axial noise is 2-10 mm at 1-4 m, so a
millimetre step keeps everything the sensor measures (docs/wire.md, "Depth")."""
THERMAL_UNIT_K: Final = 0.01
"""Default thermal quantum: 0.01 K, below the ~0.05 K NETD of microbolometers."""
RASTER_CODEC: Final = "delta16-zlib"
"""The raster codec of version 1 (see :func:`encode_depth`)."""
RASTER_ZLIB_LEVEL: Final = 1
"""zlib level of :data:`RASTER_CODEC`; level 3 saves ~1 % for ~30 % more encode time."""
_UNIT_RANGE: Final = (1e-6, 1.0)

PoseSource: TypeAlias = Literal[
    "init", "rgb", "relocalised", "thermal", "depth", "odometry", "motion_model", "none"
]
"""What produced a keyframe's pose; the same values as ``wardmap.edge.tracker.PoseSource``."""
AckStatus: TypeAlias = Literal["stored", "duplicate", "rejected", "retry"]
"""``retry``: the server could not store the keyframe now (its own storage failed); keep it and
resend. Added within version 1: an older robot reads it as a bad ack and keeps the item too."""
POSE_SOURCES: Final[tuple[str, ...]] = get_args(PoseSource)
ACK_STATUSES: Final[tuple[str, ...]] = get_args(AckStatus)

_ID_RE: Final = re.compile(r"[A-Za-z0-9_.\-]{1,64}")
_CALIB_REF_RE: Final = re.compile(r"[A-Za-z0-9_.:\-]{1,128}")
_UINT63: Final = 2**63
_DTYPES: Final[Mapping[str, np.dtype[Any]]] = MappingProxyType({
    name: np.dtype(name).newbyteorder("<") for name in ("float32", "int8", "int16", "int32", "uint8")
})
"""Array dtypes allowed on the wire (little-endian)."""
_UNPACK_LIMITS: Final = {
    "max_str_len": 4 * MAX_TEXT_LEN,  # bytes: room for MAX_TEXT_LEN characters of UTF-8
    "max_array_len": 64,
    "max_map_len": 2 * MAX_STATS,
    "max_ext_len": 0,
}


# --------------------------------------------------------------------------- small checks


def _fail(field: str, message: str) -> WireError:
    return WireError(field, message)


def _check_id(value: object, field: str) -> str:
    if not isinstance(value, str):
        raise _fail(field, f"expected a string, got {type(value).__name__}")
    if not _ID_RE.fullmatch(value):
        raise _fail(field, f"expected 1-64 characters [A-Za-z0-9_.-], got {value[:80]!r}")
    return value


def _check_int(value: object, field: str, lo: int, hi: int) -> int:
    """``value`` as an int in ``[lo, hi)``; bools are not ints here."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise _fail(field, f"expected an integer, got {type(value).__name__}")
    v = int(value)
    if not lo <= v < hi:
        raise _fail(field, f"expected an integer in [{lo}, {hi}), got {v}")
    return v


def _check_float(value: object, field: str, *, positive: bool = False) -> float:
    """``value`` as a finite float (ints accepted, bools not); ``positive``: also > 0."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise _fail(field, f"expected a number, got {type(value).__name__}")
    try:
        v = float(value)
    except OverflowError as exc:
        raise _fail(field, "number out of range") from exc
    if not math.isfinite(v):
        raise _fail(field, f"expected a finite number, got {v}")
    if positive and v <= 0:
        raise _fail(field, f"expected a positive number, got {v}")
    return v


def _check_text(value: object, field: str, max_len: int = MAX_TEXT_LEN) -> str:
    if not isinstance(value, str):
        raise _fail(field, f"expected a string, got {type(value).__name__}")
    if len(value) > max_len:
        raise _fail(field, f"string longer than {max_len} characters ({len(value)})")
    return value


def _check_bytes(value: object, field: str) -> bytes:
    if not isinstance(value, bytes | bytearray | memoryview):
        raise _fail(field, f"expected bytes, got {type(value).__name__}")
    return bytes(value)


def _shape_text(shape: tuple[int | None, ...]) -> str:
    """``(N, 2)`` for ``(None, 2)``: N is any length."""
    parts = ["N" if s is None else str(s) for s in shape]
    return "(" + ", ".join(parts) + ("," if len(parts) == 1 else "") + ")"


def _check_array(value: object, field: str, dtypes: tuple[str, ...], shape: tuple[int | None, ...]) -> Any:
    """Check an in-memory array: exact dtype, shape (None = any length), finite if float.

    Returns a read-only C-contiguous copy, so a frozen message cannot change under its reader.
    """
    if not isinstance(value, np.ndarray):
        raise _fail(field, f"expected a numpy array, got {type(value).__name__}")
    if value.dtype.name not in dtypes:
        raise _fail(field, f"expected dtype {' or '.join(dtypes)}, got {value.dtype.name}")
    if value.ndim != len(shape) or any(
        s is not None and s != g for s, g in zip(shape, value.shape, strict=True)
    ):
        raise _fail(field, f"expected shape {_shape_text(shape)}, got {tuple(value.shape)}")
    if value.dtype.kind == "f" and not np.all(np.isfinite(value)):
        raise _fail(field, "contains non-finite values")
    out = np.array(value, dtype=value.dtype.newbyteorder("="), order="C", copy=True)
    out.flags.writeable = False
    return out


def _check_pose(T: object, field: str) -> F64:
    try:
        M = check_transform(np.asarray(T, dtype=np.float64), field)
    except (GeometryError, TypeError, ValueError) as exc:
        raise _fail(field, f"not a rigid 4x4 transform: {exc}") from exc
    out = M.copy()
    out.flags.writeable = False
    return out


# --------------------------------------------------------------------------- JPEG header

_SOF_MARKERS: Final = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_STANDALONE_MARKERS: Final = frozenset({0x01, *range(0xD0, 0xD8)})


def jpeg_size(data: bytes, field: str = "rgb_jpeg") -> tuple[int, int, int]:
    """``(width, height, components)`` from a JPEG's start-of-frame header.

    Walks the marker segments (ITU T.81 Annex B) up to the first SOFn without decoding the
    entropy-coded data, so it costs microseconds instead of the ~3 ms of a full decode.

    Raises:
        WireError: no SOI magic ``FF D8``, a malformed or truncated segment, or no SOF
            before the scan.
    """
    if data[:2] != b"\xff\xd8":
        raise _fail(field, f"not a JPEG: expected magic FF D8, got {data[:2].hex(' ').upper() or 'nothing'}")
    i, n = 2, len(data)
    while True:
        if i >= n or data[i] != 0xFF:
            raise _fail(field, f"malformed JPEG: expected a marker at byte {i}")
        while i < n and data[i] == 0xFF:  # fill bytes (B.1.1.2)
            i += 1
        if i >= n:
            raise _fail(field, "truncated JPEG header")
        marker = data[i]
        i += 1
        if marker in _STANDALONE_MARKERS:
            continue
        if marker in (0xD9, 0xDA, 0x00):
            raise _fail(field, "malformed JPEG: no start-of-frame header before the scan")
        if i + 2 > n:
            raise _fail(field, "truncated JPEG header")
        (length,) = struct.unpack_from(">H", data, i)
        if length < 2 or i + length > n:
            raise _fail(field, f"malformed JPEG: segment length {length} at byte {i}")
        if marker in _SOF_MARKERS:
            if length < 8:
                raise _fail(field, "malformed JPEG: short start-of-frame header")
            _, height, width, comps = struct.unpack_from(">BHHB", data, i + 2)
            if width == 0 or height == 0:
                raise _fail(field, f"JPEG has an empty image size {width}x{height}")
            return int(width), int(height), int(comps)
        i += length


# --------------------------------------------------------------------------- rasters


@dataclass(frozen=True)
class RasterMeta:
    """How a quantised uint16 raster (depth or thermal) was packed.

    Attributes:
        width, height: raster size in pixels.
        unit: physical value of one count -- metres for depth, kelvin for thermal.
            Count 0 means "no data".
        codec: packing; version 1 knows only ``"delta16-zlib"`` (:func:`encode_depth`).
    """

    width: int
    height: int
    unit: float
    codec: str = RASTER_CODEC

    def __post_init__(self) -> None:
        _check_int(self.width, "width", 1, MAX_IMAGE_SIDE + 1)
        _check_int(self.height, "height", 1, MAX_IMAGE_SIDE + 1)
        unit = _check_float(self.unit, "unit", positive=True)
        if not _UNIT_RANGE[0] <= unit <= _UNIT_RANGE[1]:
            raise _fail("unit", f"expected a value in [{_UNIT_RANGE[0]}, {_UNIT_RANGE[1]}], got {unit}")
        if self.codec != RASTER_CODEC:
            raise _fail("codec", f"unknown raster codec {self.codec!r}; version 1 knows {RASTER_CODEC!r}")


@dataclass(frozen=True)
class PackedRaster:
    """A compressed depth or thermal raster as carried in a :class:`KeyframeMsg`.

    Build one with ``PackedRaster(*encode_depth(depth_m))``; read it with
    :func:`decode_depth` / :func:`decode_thermal` (or :meth:`counts`).

    Attributes:
        data: the compressed stream (see :func:`encode_depth`).
        meta: size, unit and codec.
    """

    data: bytes
    meta: RasterMeta

    def __post_init__(self) -> None:
        if not isinstance(self.meta, RasterMeta):
            raise _fail("meta", f"expected RasterMeta, got {type(self.meta).__name__}")
        object.__setattr__(self, "data", _check_bytes(self.data, "data"))

    def counts(self) -> U16:
        """The uint16 (height, width) counts; raises WireError if the stream is corrupt."""
        return _unpack_counts(self.data, self.meta.width, self.meta.height)


def _quantise(values: ArrayLike, unit: float, field: str) -> U16:
    """``round(values / unit)`` as uint16; non-finite and non-positive values become 0."""
    v = np.asarray(values)
    if v.ndim != 2 or v.dtype.kind != "f":
        raise _fail(field, f"expected a float (H, W) array, got {v.dtype.name} {v.shape}")
    if not (0 < v.shape[0] <= MAX_IMAGE_SIDE and 0 < v.shape[1] <= MAX_IMAGE_SIDE):
        raise _fail(field, f"image size {v.shape[1]}x{v.shape[0]} out of range")
    with np.errstate(invalid="ignore", over="ignore"):
        scaled = np.where(np.isfinite(v) & (v > 0), v.astype(np.float64) / unit, 0.0)
    counts = np.rint(scaled)
    top = float(counts.max())
    if top > 65535:
        raise _fail(field, f"value {top * unit:.6g} exceeds the range {65535 * unit:.6g} of unit {unit}")
    return counts.astype(np.uint16)


def _pack_counts(counts: U16) -> bytes:
    """Codec ``delta16-zlib``: vertical delta, zigzag, byte planes, zlib.

    Each pixel is predicted by the pixel above (row 0 by zero); the residual is taken
    modulo 2**16, zigzag-mapped so small signed residuals become small unsigned ones,
    split into a low-byte plane followed by a high-byte plane (the high plane is nearly all
    zeros), and the 2*H*W bytes are zlib-compressed. Decoding is a cumulative sum, so the
    round trip is exact for every uint16 raster.
    """
    res = np.diff(counts, axis=0, prepend=np.zeros((1, counts.shape[1]), np.uint16))
    s = res.view(np.int16).astype(np.int32)
    zz = ((s << 1) ^ (s >> 15)).astype(np.uint16)
    planes = np.stack([(zz & 0xFF).astype(np.uint8), (zz >> 8).astype(np.uint8)])
    return zlib.compress(planes.tobytes(), RASTER_ZLIB_LEVEL)


def _unpack_counts(data: bytes, width: int, height: int, field: str = "data") -> U16:
    """Inverse of :func:`_pack_counts`; inflates at most ``2 * width * height`` bytes."""
    want = 2 * width * height
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(data, want)
    except zlib.error as exc:
        raise _fail(field, f"corrupt compressed raster: {exc}") from exc
    if len(raw) != want or not inflater.eof or inflater.unconsumed_tail or inflater.unused_data:
        raise _fail(field, f"compressed raster does not hold exactly {width}x{height} uint16 values")
    planes = np.frombuffer(raw, np.uint8).reshape(2, height, width)
    zz = planes[0].astype(np.uint16) | (planes[1].astype(np.uint16) << 8)
    s = (zz >> 1).astype(np.int32) ^ -(zz & 1).astype(np.int32)
    res = s.astype(np.int16).view(np.uint16)
    return np.cumsum(res, axis=0, dtype=np.uint16)


def _check_packed(data: bytes, width: int, height: int, field: str) -> None:
    """Raise as :func:`_unpack_counts` would, without keeping the raster: the stream is inflated
    :data:`_INFLATE_CHUNK` bytes at a time and each chunk dropped (memory stays at a chunk)."""
    want = 2 * width * height
    inflater = zlib.decompressobj()
    got, tail = 0, data
    try:
        while not inflater.eof and got <= want:
            chunk = inflater.decompress(tail, min(_INFLATE_CHUNK, want - got + 1))
            got += len(chunk)
            tail = inflater.unconsumed_tail
            if not chunk and not tail:
                break
    except zlib.error as exc:
        raise _fail(field, f"corrupt compressed raster: {exc}") from exc
    if got != want or not inflater.eof or inflater.unconsumed_tail or inflater.unused_data:
        raise _fail(field, f"compressed raster does not hold exactly {width}x{height} uint16 values")


def encode_depth(depth_m: ArrayLike, *, unit_m: float = DEPTH_UNIT_M) -> tuple[bytes, RasterMeta]:
    """Quantise a depth image to ``unit_m`` and compress it losslessly.

    Args:
        depth_m: float (H, W) depth along the camera's z axis in metres; 0, negative and
            non-finite values mean "no data" and are sent as 0.
        unit_m: quantum in metres (default 1 mm; the range is then 0-65.535 m).

    Returns:
        ``(data, meta)``; ``decode_depth(data, meta)`` gives back ``round(depth_m / unit_m) *
        unit_m`` as float32 exactly.

    Raises:
        WireError: not a 2-D float array, or a depth beyond ``65535 * unit_m``.
    """
    meta_unit = _check_float(unit_m, "depth.unit", positive=True)
    counts = _quantise(depth_m, meta_unit, "depth")
    meta = RasterMeta(width=counts.shape[1], height=counts.shape[0], unit=meta_unit)
    return _pack_counts(counts), meta


def decode_depth(data: bytes, meta: RasterMeta) -> F32:
    """Float32 (height, width) depth in metres from :func:`encode_depth`'s output; 0 = no data."""
    counts = _unpack_counts(data, meta.width, meta.height, "depth.data")
    return (counts.astype(np.float64) * meta.unit).astype(np.float32)


def encode_thermal(thermal_k: ArrayLike, *, unit_k: float = THERMAL_UNIT_K) -> tuple[bytes, RasterMeta]:
    """As :func:`encode_depth` for a thermal image: float (h, w) kelvin, 0 = no data,
    quantised to ``unit_k`` (default 0.01 K; range 0-655.35 K)."""
    meta_unit = _check_float(unit_k, "thermal.unit", positive=True)
    counts = _quantise(thermal_k, meta_unit, "thermal")
    meta = RasterMeta(width=counts.shape[1], height=counts.shape[0], unit=meta_unit)
    return _pack_counts(counts), meta


def decode_thermal(data: bytes, meta: RasterMeta) -> F32:
    """Float32 (height, width) temperature in kelvin from :func:`encode_thermal`; 0 = no data."""
    counts = _unpack_counts(data, meta.width, meta.height, "thermal.data")
    return (counts.astype(np.float64) * meta.unit).astype(np.float32)


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True)
class Intrinsics:
    """The colour camera's calibration, sent when the server has no ``calib_ref`` for it.

    Attributes:
        width, height: image size in pixels.
        fx, fy: focal lengths in pixels; cx, cy: principal point in pixels (centre of the
            top-left pixel at (0, 0)).
        distortion: ``(k1, k2, p1, p2, k3)``, OpenCV's model; zeros for none.
        depth_scale: the depth sensor's native units per metre (``calibration.toml``'s
            ``depth_scale``, e.g. 5000). Informational: the transmitted depth raster carries
            its own quantum (:attr:`RasterMeta.unit`).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float]
    depth_scale: float

    def __post_init__(self) -> None:
        _check_int(self.width, "intrinsics.width", 1, MAX_IMAGE_SIDE + 1)
        _check_int(self.height, "intrinsics.height", 1, MAX_IMAGE_SIDE + 1)
        for name in ("fx", "fy", "depth_scale"):
            value = _check_float(getattr(self, name), f"intrinsics.{name}", positive=True)
            object.__setattr__(self, name, value)
        for name in ("cx", "cy"):
            object.__setattr__(self, name, _check_float(getattr(self, name), f"intrinsics.{name}"))
        dist = self.distortion
        if not isinstance(dist, tuple | list) or len(dist) != 5:
            raise _fail("intrinsics.distortion", "expected 5 numbers (k1 k2 p1 p2 k3)")
        values = tuple(_check_float(d, f"intrinsics.distortion[{i}]") for i, d in enumerate(dist))
        object.__setattr__(self, "distortion", values)

    @staticmethod
    def from_camera(camera: PinholeCamera, depth_scale: float) -> Intrinsics:
        """Intrinsics of ``camera`` with the depth sensor's ``depth_scale`` (units per metre)."""
        return Intrinsics(camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy,
                          camera.distortion, depth_scale)

    def to_camera(self) -> PinholeCamera:
        """The :class:`~wardmap.shared.camera.PinholeCamera` these intrinsics describe."""
        return PinholeCamera(self.width, self.height, self.fx, self.fy, self.cx, self.cy, self.distortion)


@dataclass(frozen=True, eq=False)
class Keypoints:
    """The keyframe's 2-D features, one row per keypoint (N <= :data:`MAX_KEYPOINTS`).

    Arrays are stored read-only; dtypes are exact (cast before building).

    Attributes:
        uv: float32 (N, 2) pixel coordinates (u along columns, v along rows) in the colour image.
        octave: int8 or int16 (N,) pyramid level (0 = full resolution, -1 = upsampled), in [-1, 31].
        angle_deg: float32 (N,) orientation in degrees, [0, 360].
        depth_m: float32 (N,) depth along the camera's z axis in metres, 0 = none.
        descriptors: uint8 (N, 32) binary descriptors (ORB, 256 bits).
        point_id: int32 (N,) the tracker's map point each keypoint observed or made, -1 =
            none, else in [0, 2**31): the robot numbers its points modulo 2**31, so an id names
            one point among the keyframes of a session fewer than :data:`POINT_ID_SPAN` apart
            (keypoints of two such keyframes with one id saw the same point); None when the
            robot does not send them.
    """

    uv: F32
    octave: NDArray[np.int8] | NDArray[np.int16]
    angle_deg: F32
    depth_m: F32
    descriptors: NDArray[np.uint8]
    point_id: NDArray[np.int32] | None = None

    def __post_init__(self) -> None:
        uv = _check_array(self.uv, "keypoints.uv", ("float32",), (None, 2))
        n = uv.shape[0]
        if n > MAX_KEYPOINTS:
            raise _fail("keypoints.uv", f"{n} keypoints, at most {MAX_KEYPOINTS} allowed")
        checked = {
            "uv": uv,
            "octave": _check_array(self.octave, "keypoints.octave", ("int8", "int16"), (n,)),
            "angle_deg": _check_array(self.angle_deg, "keypoints.angle_deg", ("float32",), (n,)),
            "depth_m": _check_array(self.depth_m, "keypoints.depth_m", ("float32",), (n,)),
            "descriptors": _check_array(self.descriptors, "keypoints.descriptors", ("uint8",), (n, 32)),
        }
        if n and (checked["octave"].min() < -1 or checked["octave"].max() > 31):
            raise _fail("keypoints.octave", "expected values in [-1, 31]")
        if n and (checked["angle_deg"].min() < 0 or checked["angle_deg"].max() > 360):
            raise _fail("keypoints.angle_deg", "expected values in [0, 360]")
        if n and checked["depth_m"].min() < 0:
            raise _fail("keypoints.depth_m", "expected values >= 0 (0 = no depth)")
        if self.point_id is not None:
            checked["point_id"] = _check_array(self.point_id, "keypoints.point_id", ("int32",), (n,))
            if n and checked["point_id"].min() < -1:
                raise _fail("keypoints.point_id", "expected values >= -1 (-1 = no map point)")
        for name, arr in checked.items():
            object.__setattr__(self, name, arr)

    def __len__(self) -> int:
        return int(self.uv.shape[0])


@dataclass(frozen=True, eq=False)
class KeyframeMsg:
    """One keyframe from a robot (schema ``wardmap.keyframe``).

    Exactly one of ``intrinsics`` and ``calib_ref`` is set.

    Attributes:
        robot_id: the robot, 1-64 characters ``[A-Za-z0-9_.-]``.
        session_id: the robot's mapping session (its ``odom`` frame), same rule.
        seq: keyframe number within the session, 0 <= seq < 2**63; with robot_id and
            session_id it identifies the keyframe (the server acks duplicates).
        stamp: capture time of the colour image, seconds since the Unix epoch (> 0).
        T_odom_camera: (4, 4) float64 pose of the colour camera in the session's odom frame.
        pose_source: what produced ``T_odom_camera`` (the tracker's ``TrackResult.source``).
        keypoints: the features the tracker used, in colour-image pixels.
        rgb_jpeg: the colour image as a 3-channel JPEG.
        depth: depth registered to the colour camera, metres (:func:`encode_depth`); its size
            is the colour image's divided by 1, 2 or 4 (pixel (i, j) covers colour pixel
            (s*i, s*j)).
        intrinsics: the colour camera's calibration, or None when ``calib_ref`` names it.
        calib_ref: reference to a calibration the server already has (e.g. the sha256 of
            ``calibration.toml``), 1-128 characters ``[A-Za-z0-9_.:-]``, or None.
        T_odom_base: (4, 4) wheel-odometry pose of the robot base at ``stamp``, or None.
        thermal: thermal image in kelvin (:func:`encode_thermal`), own size, or None.
        T_map_odom: (4, 4) the session's odom frame in the shared map frame, when the robot
            was started at a known map pose (e.g. its docking station; ``wardmap edge
            --map-pose``); None when unknown (the server then keeps the session in its own
            frame until loop closure aligns it).
    """

    robot_id: str
    session_id: str
    seq: int
    stamp: float
    T_odom_camera: F64
    pose_source: PoseSource
    keypoints: Keypoints
    rgb_jpeg: bytes
    depth: PackedRaster
    intrinsics: Intrinsics | None = None
    calib_ref: str | None = None
    T_odom_base: F64 | None = None
    thermal: PackedRaster | None = None
    T_map_odom: F64 | None = None

    def __post_init__(self) -> None:
        _check_id(self.robot_id, "robot_id")
        _check_id(self.session_id, "session_id")
        _check_int(self.seq, "seq", 0, _UINT63)
        if self.T_map_odom is not None:
            object.__setattr__(self, "T_map_odom", _check_pose(self.T_map_odom, "T_map_odom"))
        object.__setattr__(self, "stamp", _check_float(self.stamp, "stamp", positive=True))
        object.__setattr__(self, "T_odom_camera", _check_pose(self.T_odom_camera, "T_odom_camera"))
        if self.T_odom_base is not None:
            object.__setattr__(self, "T_odom_base", _check_pose(self.T_odom_base, "T_odom_base"))
        if self.pose_source not in POSE_SOURCES:
            raise _fail("pose_source", f"unknown pose source {self.pose_source!r:.40}; "
                                       f"expected one of {POSE_SOURCES}")
        if not isinstance(self.keypoints, Keypoints):
            raise _fail("keypoints", f"expected Keypoints, got {type(self.keypoints).__name__}")
        if (self.intrinsics is None) == (self.calib_ref is None):
            raise _fail("intrinsics", "exactly one of intrinsics and calib_ref must be given")
        if self.intrinsics is not None and not isinstance(self.intrinsics, Intrinsics):
            raise _fail("intrinsics", f"expected Intrinsics, got {type(self.intrinsics).__name__}")
        if self.calib_ref is not None and not (
            isinstance(self.calib_ref, str) and _CALIB_REF_RE.fullmatch(self.calib_ref)
        ):
            raise _fail("calib_ref", "expected 1-128 characters [A-Za-z0-9_.:-]")
        rgb = _check_bytes(self.rgb_jpeg, "rgb_jpeg")
        object.__setattr__(self, "rgb_jpeg", rgb)
        width, height, comps = jpeg_size(rgb)
        if comps != 3:
            raise _fail("rgb_jpeg", f"expected a 3-channel colour JPEG, got {comps} channel(s)")
        if self.intrinsics is not None and (width, height) != (self.intrinsics.width, self.intrinsics.height):
            raise _fail("rgb_jpeg", f"JPEG is {width}x{height}, intrinsics say "
                                    f"{self.intrinsics.width}x{self.intrinsics.height}")
        for raster, name in ((self.depth, "depth"), (self.thermal, "thermal")):
            if raster is not None and not isinstance(raster, PackedRaster):
                raise _fail(name, f"expected PackedRaster, got {type(raster).__name__}")
        dm = self.depth.meta
        if not any((dm.width * s, dm.height * s) == (width, height) for s in (1, 2, 4)):
            raise _fail("depth", f"depth is {dm.width}x{dm.height}, expected the colour size "
                                 f"{width}x{height} divided by 1, 2 or 4")
        # The decoded size from the headers alone, before anything is inflated.
        decoded = 3 * width * height
        for raster, name in ((None, "rgb_jpeg"), (self.depth, "depth"), (self.thermal, "thermal")):
            if raster is not None:
                decoded += 2 * raster.meta.width * raster.meta.height
            if decoded > MAX_DECODED_BYTES:
                raise _fail(name, f"the images would decode to {decoded} bytes or more, "
                                  f"more than {MAX_DECODED_BYTES=}")
        _check_packed(self.depth.data, dm.width, dm.height, "depth.data")
        if self.thermal is not None:
            tm = self.thermal.meta
            _check_packed(self.thermal.data, tm.width, tm.height, "thermal.data")
        if len(self.keypoints):
            uv = self.keypoints.uv
            if uv.min() < -1 or np.any(uv.max(axis=0) > np.array([width, height]) + 1):
                raise _fail("keypoints.uv", f"keypoints outside the {width}x{height} image")

    @property
    def camera(self) -> PinholeCamera | None:
        """The colour camera when ``intrinsics`` were sent, else None (look up ``calib_ref``)."""
        return None if self.intrinsics is None else self.intrinsics.to_camera()


@dataclass(frozen=True)
class AckMsg:
    """The server's answer to one keyframe (schema ``wardmap.ack``).

    Attributes:
        robot_id, session_id, seq: the keyframe acknowledged.
        status: ``stored`` (new, committed), ``duplicate`` (already stored; the robot may drop
            it), ``rejected`` (invalid: will never be stored; ``reason`` says why) or ``retry``
            (valid, but the server's storage failed: disk full, locked, damaged; the robot keeps
            it and resends after its normal resend delay).
        reason: human-readable detail, at most 1024 characters; may be empty.
    """

    robot_id: str
    session_id: str
    seq: int
    status: AckStatus
    reason: str = ""

    def __post_init__(self) -> None:
        _check_id(self.robot_id, "robot_id")
        _check_id(self.session_id, "session_id")
        _check_int(self.seq, "seq", 0, _UINT63)
        if self.status not in ACK_STATUSES:
            raise _fail("status", f"unknown status {self.status!r}; expected one of {ACK_STATUSES}")
        _check_text(self.reason, "reason")


@dataclass(frozen=True)
class HeartbeatMsg:
    """A robot's periodic sign of life with flat numeric statistics (schema ``wardmap.heartbeat``).

    Attributes:
        robot_id, session_id: as in :class:`KeyframeMsg`.
        stamp: send time, seconds since the Unix epoch (> 0).
        stats: at most 64 entries; keys 1-64 characters, values finite ints or floats
            (bools are not numbers here). Names carry units (``queue_len``, ``track_ms``).
            Stored read-only.
    """

    robot_id: str
    session_id: str
    stamp: float
    stats: Mapping[str, float | int]

    def __post_init__(self) -> None:
        _check_id(self.robot_id, "robot_id")
        _check_id(self.session_id, "session_id")
        object.__setattr__(self, "stamp", _check_float(self.stamp, "stamp", positive=True))
        if not isinstance(self.stats, Mapping):
            raise _fail("stats", f"expected a map, got {type(self.stats).__name__}")
        if len(self.stats) > MAX_STATS:
            raise _fail("stats", f"{len(self.stats)} entries, at most {MAX_STATS} allowed")
        clean: dict[str, float | int] = {}
        for key, value in self.stats.items():
            if not isinstance(key, str) or not 1 <= len(key) <= MAX_STAT_KEY_LEN:
                raise _fail("stats", f"keys must be strings of 1-{MAX_STAT_KEY_LEN} characters, "
                                     f"got {key!r:.80}")
            if isinstance(value, int | np.integer) and not isinstance(value, bool):
                clean[key] = _check_int(value, f"stats.{key}", -_UINT63, 2**64)
            else:
                clean[key] = _check_float(value, f"stats.{key}")
        object.__setattr__(self, "stats", MappingProxyType(clean))


Message: TypeAlias = KeyframeMsg | AckMsg | HeartbeatMsg


# --------------------------------------------------------------------------- encode


def _array_to_wire(a: NDArray[Any]) -> dict[str, Any]:
    data = np.ascontiguousarray(a, dtype=a.dtype.newbyteorder("<")).tobytes()
    return {"dtype": a.dtype.name, "shape": list(a.shape), "data": data}


def _pose_to_wire(T: F64) -> dict[str, Any]:
    return {"t": [float(x) for x in T[:3, 3]], "q_xyzw": [float(x) for x in rotation_to_quat(T[:3, :3])]}


def _raster_to_wire(r: PackedRaster) -> dict[str, Any]:
    m = r.meta
    return {"codec": m.codec, "width": m.width, "height": m.height, "unit": m.unit, "data": r.data}


def _to_wire(msg: Message) -> dict[str, Any]:
    if isinstance(msg, KeyframeMsg):
        kp = msg.keypoints
        d: dict[str, Any] = {
            "schema": SCHEMA_KEYFRAME, "version": SCHEMA_VERSION,
            "robot_id": msg.robot_id, "session_id": msg.session_id, "seq": msg.seq, "stamp": msg.stamp,
            "T_odom_camera": _pose_to_wire(msg.T_odom_camera), "pose_source": msg.pose_source,
            "keypoints": {name: _array_to_wire(getattr(kp, name)) for name in _KEYPOINT_FIELDS
                          if getattr(kp, name) is not None},
            "rgb_jpeg": msg.rgb_jpeg, "depth": _raster_to_wire(msg.depth),
        }
        if msg.intrinsics is not None:
            i = msg.intrinsics
            d["intrinsics"] = {"width": i.width, "height": i.height, "fx": i.fx, "fy": i.fy, "cx": i.cx,
                               "cy": i.cy, "distortion": list(i.distortion), "depth_scale": i.depth_scale}
        if msg.calib_ref is not None:
            d["calib_ref"] = msg.calib_ref
        if msg.T_odom_base is not None:
            d["T_odom_base"] = _pose_to_wire(msg.T_odom_base)
        if msg.thermal is not None:
            d["thermal"] = _raster_to_wire(msg.thermal)
        if msg.T_map_odom is not None:
            d["T_map_odom"] = _pose_to_wire(msg.T_map_odom)
        return d
    if isinstance(msg, AckMsg):
        return {"schema": SCHEMA_ACK, "version": SCHEMA_VERSION, "robot_id": msg.robot_id,
                "session_id": msg.session_id, "seq": msg.seq, "status": msg.status, "reason": msg.reason}
    if isinstance(msg, HeartbeatMsg):
        return {"schema": SCHEMA_HEARTBEAT, "version": SCHEMA_VERSION, "robot_id": msg.robot_id,
                "session_id": msg.session_id, "stamp": msg.stamp, "stats": dict(msg.stats)}
    raise WireError("", f"cannot encode {type(msg).__name__}: not a wire message")


def encode(msg: Message) -> bytes:
    """Serialise a message to msgpack bytes (schema ``version`` 1).

    Raises:
        WireError: ``msg`` is not a message type, or the payload would exceed
            :data:`MAX_MESSAGE_BYTES` (the server would reject it).
    """
    payload: bytes = msgpack.packb(_to_wire(msg), use_bin_type=True)
    if len(payload) > MAX_MESSAGE_BYTES:
        raise WireError("", f"message is {len(payload)} bytes, more than {MAX_MESSAGE_BYTES=}")
    return payload


# --------------------------------------------------------------------------- decode

_KEYPOINT_FIELDS: Final = ("uv", "octave", "angle_deg", "depth_m", "descriptors", "point_id")
_OPTIONAL_KEYPOINT_FIELDS: Final = frozenset({"point_id"})
_KEYPOINT_LAYOUT: Final[Mapping[str, tuple[tuple[str, ...], tuple[int | None, ...]]]] = MappingProxyType({
    "uv": (("float32",), (None, 2)),
    "octave": (("int8", "int16"), (None,)),
    "angle_deg": (("float32",), (None,)),
    "depth_m": (("float32",), (None,)),
    "descriptors": (("uint8",), (None, 32)),
    "point_id": (("int32",), (None,)),
})
"""Wire dtypes and shapes (None = the keypoint count N) of the keypoint arrays."""


class _Fields:
    """Read a wire map once: every key must be consumed, unknown keys are an error."""

    def __init__(self, value: object, path: str) -> None:
        if not isinstance(value, dict):
            raise _fail(path, f"expected a map, got {type(value).__name__}")
        self._d: dict[str, Any] = value
        self._path = path
        self._seen: set[str] = set()

    def name(self, key: str) -> str:
        return f"{self._path}.{key}" if self._path else key

    def get(self, key: str) -> Any:
        self._seen.add(key)
        if key not in self._d:
            raise _fail(self.name(key), "missing")
        return self._d[key]

    def optional(self, key: str) -> Any:
        self._seen.add(key)
        return self._d.get(key)

    def done(self) -> None:
        extra = sorted(set(self._d) - self._seen)
        if extra:
            raise _fail(self.name(extra[0]), "unknown field")


def _list_of_floats(value: object, field: str, n: int) -> list[float]:
    if not isinstance(value, list) or len(value) != n:
        raise _fail(field, f"expected a list of {n} numbers")
    return [_check_float(v, f"{field}[{i}]") for i, v in enumerate(value)]


def _pose_from_wire(value: object, field: str) -> F64:
    f = _Fields(value, field)
    t = _list_of_floats(f.get("t"), f.name("t"), 3)
    q = np.array(_list_of_floats(f.get("q_xyzw"), f.name("q_xyzw"), 4))
    f.done()
    with np.errstate(over="ignore"):  # a huge component gives norm inf, refused below
        norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise _fail(f.name("q_xyzw"), f"quaternion norm {norm:.6g} is not within {QUAT_NORM_TOL} of 1")
    return make_transform(quat_to_rotation(q / norm), t)


def _array_from_wire(value: object, field: str, dtypes: tuple[str, ...], shape: tuple[int | None, ...],
                     ) -> Any:
    f = _Fields(value, field)
    dtype_name = f.get("dtype")
    raw_shape = f.get("shape")
    data = _check_bytes(f.get("data"), f.name("data"))
    f.done()
    if not isinstance(dtype_name, str) or dtype_name not in _DTYPES:
        raise _fail(f.name("dtype"), f"dtype {dtype_name!r:.40} not allowed; allowed: {sorted(_DTYPES)}")
    if dtype_name not in dtypes:
        raise _fail(f.name("dtype"), f"expected {' or '.join(dtypes)}, got {dtype_name}")
    if not isinstance(raw_shape, list) or len(raw_shape) != len(shape):
        raise _fail(f.name("shape"), f"expected a list of {len(shape)} sizes")
    dims = tuple(_check_int(s, f.name("shape"), 0, MAX_KEYPOINTS + 1) for s in raw_shape)
    for want, got in zip(shape, dims, strict=True):
        if want is not None and want != got:
            raise _fail(field, f"expected shape {_shape_text(shape)}, got {dims}")
    dt = _DTYPES[dtype_name]
    if math.prod(dims) * dt.itemsize != len(data):
        raise _fail(f.name("data"), f"{len(data)} bytes do not hold a {dtype_name} array of shape {dims}")
    return np.frombuffer(data, dtype=dt).reshape(dims).astype(dt.newbyteorder("="))


def array_to_wire(a: NDArray[Any]) -> dict[str, Any]:
    """An array as the wire's ``{"dtype": name, "shape": [...], "data": little-endian bytes}`` map."""
    return _array_to_wire(a)


def _raster_from_wire(value: object, field: str) -> PackedRaster:
    f = _Fields(value, field)
    codec = f.get("codec")
    if codec != RASTER_CODEC:
        raise _fail(f.name("codec"), f"unknown raster codec {codec!r:.40}; version 1 knows {RASTER_CODEC!r}")
    width = _check_int(f.get("width"), f.name("width"), 1, MAX_IMAGE_SIDE + 1)
    height = _check_int(f.get("height"), f.name("height"), 1, MAX_IMAGE_SIDE + 1)
    unit = _check_float(f.get("unit"), f.name("unit"), positive=True)
    data = _check_bytes(f.get("data"), f.name("data"))
    f.done()
    try:
        meta = RasterMeta(width, height, unit, codec)
    except WireError as exc:
        raise _fail(f.name(exc.field), str(exc).split(": ", 1)[-1]) from exc
    return PackedRaster(data, meta)


def _intrinsics_from_wire(value: object) -> Intrinsics:
    f = _Fields(value, "intrinsics")
    args = {k: f.get(k) for k in ("width", "height", "fx", "fy", "cx", "cy", "depth_scale")}
    dist = _list_of_floats(f.get("distortion"), "intrinsics.distortion", 5)
    f.done()
    return Intrinsics(distortion=tuple(dist), **args)  # type: ignore[arg-type]  # checked in __post_init__


def _keyframe_from_wire(f: _Fields) -> KeyframeMsg:
    robot_id = _check_id(f.get("robot_id"), "robot_id")
    session_id = _check_id(f.get("session_id"), "session_id")
    seq = _check_int(f.get("seq"), "seq", 0, _UINT63)
    stamp = _check_float(f.get("stamp"), "stamp", positive=True)
    T_odom_camera = _pose_from_wire(f.get("T_odom_camera"), "T_odom_camera")
    source = f.get("pose_source")
    if not isinstance(source, str) or source not in POSE_SOURCES:
        raise _fail("pose_source", f"unknown pose source {source!r:.40}; expected one of {POSE_SOURCES}")
    base = f.optional("T_odom_base")
    T_odom_base = None if base is None else _pose_from_wire(base, "T_odom_base")
    raw_intr = f.optional("intrinsics")
    intrinsics = None if raw_intr is None else _intrinsics_from_wire(raw_intr)
    calib_ref = f.optional("calib_ref")
    if calib_ref is not None and not isinstance(calib_ref, str):
        raise _fail("calib_ref", f"expected a string, got {type(calib_ref).__name__}")
    kf = _Fields(f.get("keypoints"), "keypoints")
    kp_arrays: dict[str, Any] = {}
    for name in _KEYPOINT_FIELDS:
        dtypes, shape = _KEYPOINT_LAYOUT[name]
        raw = kf.optional(name) if name in _OPTIONAL_KEYPOINT_FIELDS else kf.get(name)
        if raw is not None:
            kp_arrays[name] = _array_from_wire(raw, kf.name(name), dtypes, shape)
    kf.done()
    counts = {name: a.shape[0] for name, a in kp_arrays.items()}
    if len(set(counts.values())) > 1:
        bad = next(name for name, c in counts.items() if c != counts["uv"])
        raise _fail(f"keypoints.{bad}",
                    f"declares {counts[bad]} keypoints, keypoints.uv declares {counts['uv']}")
    keypoints = Keypoints(**kp_arrays)
    rgb_jpeg = _check_bytes(f.get("rgb_jpeg"), "rgb_jpeg")
    depth = _raster_from_wire(f.get("depth"), "depth")
    raw_th = f.optional("thermal")
    thermal = None if raw_th is None else _raster_from_wire(raw_th, "thermal")
    raw_map = f.optional("T_map_odom")
    T_map_odom = None if raw_map is None else _pose_from_wire(raw_map, "T_map_odom")
    f.done()
    return KeyframeMsg(
        robot_id=robot_id, session_id=session_id, seq=seq, stamp=stamp, T_odom_camera=T_odom_camera,
        pose_source=source, keypoints=keypoints, rgb_jpeg=rgb_jpeg, depth=depth,  # type: ignore[arg-type]
        intrinsics=intrinsics, calib_ref=calib_ref, T_odom_base=T_odom_base, thermal=thermal,
        T_map_odom=T_map_odom,
    )


def _ack_from_wire(f: _Fields) -> AckMsg:
    status = f.get("status")
    if not isinstance(status, str) or status not in ACK_STATUSES:
        raise _fail("status", f"unknown status {status!r:.40}; expected one of {ACK_STATUSES}")
    msg = AckMsg(
        robot_id=_check_id(f.get("robot_id"), "robot_id"),
        session_id=_check_id(f.get("session_id"), "session_id"),
        seq=_check_int(f.get("seq"), "seq", 0, _UINT63),
        status=status,  # type: ignore[arg-type]  # checked above
        reason=_check_text(f.get("reason"), "reason"),
    )
    f.done()
    return msg


def _heartbeat_from_wire(f: _Fields) -> HeartbeatMsg:
    stats = f.get("stats")
    if not isinstance(stats, dict):
        raise _fail("stats", f"expected a map, got {type(stats).__name__}")
    msg = HeartbeatMsg(
        robot_id=_check_id(f.get("robot_id"), "robot_id"),
        session_id=_check_id(f.get("session_id"), "session_id"),
        stamp=_check_float(f.get("stamp"), "stamp", positive=True),
        stats=stats,
    )
    f.done()
    return msg


_READERS: Final[Mapping[str, Callable[[_Fields], Message]]] = MappingProxyType({
    SCHEMA_KEYFRAME: _keyframe_from_wire, SCHEMA_ACK: _ack_from_wire, SCHEMA_HEARTBEAT: _heartbeat_from_wire,
})


def decode(payload: bytes, *, max_bytes: int = MAX_MESSAGE_BYTES) -> Message:
    """Parse and validate one message from untrusted bytes.

    Args:
        payload: msgpack bytes as produced by :func:`encode`.
        max_bytes: reject larger payloads before unpacking anything.

    Raises:
        WireError: for any malformed input -- oversize, truncated or non-msgpack bytes,
            unknown ``schema`` or ``version``, a missing, unknown, mistyped or out-of-range
            field. ``.field`` names the field (dotted wire path; ``""`` for the whole payload).
    """
    f = _Fields(unpack_payload(payload, max_bytes=max_bytes), "")
    schema = f.get("schema")
    if not isinstance(schema, str) or schema not in _READERS:
        raise WireError("schema", f"unknown schema {schema!r:.60}; expected one of {sorted(_READERS)}")
    version = f.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version != SCHEMA_VERSION:
        raise WireError("version", f"unsupported version {version!r:.40} of {schema}; this build reads "
                                   f"{SCHEMA_VERSION}")
    try:
        return _READERS[schema](f)
    except WireError:
        raise
    except (ValueError, TypeError, KeyError, IndexError, OverflowError, ArithmeticError,
            GeometryError, zlib.error) as exc:  # safety net: validators raise WireError themselves
        raise WireError("", f"malformed {schema}: {type(exc).__name__}: {exc}"[:300]) from exc


_M = TypeVar("_M", KeyframeMsg, AckMsg, HeartbeatMsg)


def _decode_as(payload: bytes, kind: type[_M], schema: str, max_bytes: int) -> _M:
    msg = decode(payload, max_bytes=max_bytes)
    if not isinstance(msg, kind):
        got = {KeyframeMsg: SCHEMA_KEYFRAME, AckMsg: SCHEMA_ACK, HeartbeatMsg: SCHEMA_HEARTBEAT}[type(msg)]
        raise WireError("schema", f"expected {schema}, got {got}")
    return msg


def decode_keyframe(payload: bytes, *, max_bytes: int = MAX_MESSAGE_BYTES) -> KeyframeMsg:
    """:func:`decode` that also requires schema ``wardmap.keyframe``."""
    return _decode_as(payload, KeyframeMsg, SCHEMA_KEYFRAME, max_bytes)


def decode_ack(payload: bytes, *, max_bytes: int = MAX_MESSAGE_BYTES) -> AckMsg:
    """:func:`decode` that also requires schema ``wardmap.ack``."""
    return _decode_as(payload, AckMsg, SCHEMA_ACK, max_bytes)


def decode_heartbeat(payload: bytes, *, max_bytes: int = MAX_MESSAGE_BYTES) -> HeartbeatMsg:
    """:func:`decode` that also requires schema ``wardmap.heartbeat``."""
    return _decode_as(payload, HeartbeatMsg, SCHEMA_HEARTBEAT, max_bytes)


# --------------------------------------------------------------------------- for other schemas
# This schema's readers and checks, public for the other message schemas of ``shared/``
# (``robotwire.py``), so that every wardmap message is unpacked, validated and refused alike.

Fields = _Fields
"""Read a wire map once: :meth:`~_Fields.get` / :meth:`~_Fields.optional` each key, then
:meth:`~_Fields.done` raises :class:`WireError` on any key left unread (unknown field)."""
check_id = _check_id
"""``check_id(value, field) -> str``: 1-64 characters ``[A-Za-z0-9_.-]`` (robot and session ids)."""
check_int = _check_int
"""``check_int(value, field, lo, hi) -> int``: an int in ``[lo, hi)``; bools are refused."""
check_float = _check_float
"""``check_float(value, field, *, positive=False) -> float``: finite; bools are refused."""
check_text = _check_text
"""``check_text(value, field, max_len=MAX_TEXT_LEN) -> str``."""
check_pose = _check_pose
"""``check_pose(T, field) -> F64``: a read-only copy of a rigid (4, 4) transform."""
pose_to_wire = _pose_to_wire
"""``pose_to_wire(T) -> {"t": [x, y, z], "q_xyzw": [x, y, z, w]}``, the wire's pose form."""
pose_from_wire = _pose_from_wire
"""``pose_from_wire(value, field) -> F64``: the pose form read back (quaternion norm within
:data:`QUAT_NORM_TOL` of 1, then renormalised)."""


def unpack_payload(payload: object, *, max_bytes: int) -> object:
    """Unpack untrusted msgpack bytes with this schema's limits (docs/wire.md, "Validation").

    Payloads over ``max_bytes`` are refused before unpacking; strings, arrays, maps and binaries
    are bounded and ext types refused, so hostile input cannot allocate much.

    Raises:
        WireError: (field ``""``) not bytes, oversize, truncated or not msgpack.
    """
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise WireError("", f"expected bytes, got {type(payload).__name__}")
    if len(payload) > max_bytes:
        raise WireError("", f"payload of {len(payload)} bytes exceeds the limit of {max_bytes}")
    try:
        return msgpack.unpackb(payload, raw=False, strict_map_key=True, use_list=True,
                               max_bin_len=max_bytes, **_UNPACK_LIMITS)
    except (msgpack.UnpackException, ValueError, TypeError, OverflowError, RecursionError) as exc:
        raise WireError("", f"not a valid msgpack payload: {type(exc).__name__}: {exc}"[:300]) from exc

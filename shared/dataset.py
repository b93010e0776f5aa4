"""Data-set folders: the TUM RGB-D layout, extended with thermal, odometry and ground truth.

The layout, units and frames of every file are described in ``docs/dataset.md``. In short:
``rgb.txt`` + ``rgb/`` (8-bit colour PNG), ``depth.txt`` + ``depth/`` (uint16 PNG,
``depth_scale`` units per metre, 0 = no data), ``groundtruth.txt`` (TUM poses
``T_world_rgbcamera``), optionally ``thermal.txt`` + ``thermal/`` (uint16 PNG,
kelvin * ``thermal_scale``), ``odometry.txt`` (TUM poses ``T_odom_base``),
``encoders.txt``, ``calibration.toml``, and from the simulator ``labels.txt`` + ``labels/``
(uint16 instance ids) and ``objects.json``. Real TUM folders open unchanged: without a
``calibration.toml`` the camera is chosen from the folder name (freiburg1/2/3).

:class:`DatasetReader` validates a folder eagerly (list files, calibration, that every
referenced image exists) and loads images lazily, one :class:`Frame` at a time.
:class:`DatasetWriter` writes a folder deterministically: the same input gives
byte-identical files. Every problem raises :class:`~wardmap.shared.errors.DatasetError`
naming the file (and line or key) at fault. This module reads and writes only the files
it is asked to.
"""

from __future__ import annotations

import json
import logging
import math
import operator
import os
import re
import shutil
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from types import MappingProxyType, TracebackType
from typing import Any, Final, NamedTuple, Protocol

import cv2
import numpy as np
import tomli_w
from numpy.typing import ArrayLike, NDArray

from wardmap.shared.camera import PinholeCamera
from wardmap.shared.config import load_toml
from wardmap.shared.errors import ConfigError, DatasetError, GeometryError
from wardmap.shared.se3 import (
    check_transform,
    interpolate_transform,
    transform_from_tum,
    transform_to_tum,
)
from wardmap.shared.sensors import SENSORS, TUM_SENSOR, ReadoutModel, readout_model

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
U16 = NDArray[np.uint16]
U8 = NDArray[np.uint8]

DEFAULT_DEPTH_SCALE: Final = 5000.0
"""Depth PNG units per metre (TUM's value)."""
MAX_READOUT_S: Final = 0.1
"""Largest rolling-shutter readout time accepted (a 10 Hz frame period), seconds."""
DEFAULT_THERMAL_SCALE: Final = 100.0
"""Thermal PNG units per kelvin (centikelvin)."""
MAX_DEPTH_DT_S: Final = 0.02
"""Largest |rgb stamp - depth stamp| for an rgb/depth pair (TUM associate.py's default)."""
MAX_THERMAL_DT_S: Final = 0.04
"""Largest |rgb stamp - thermal stamp|: half the period of a 12.5 Hz thermal camera."""
GT_MAX_BRACKET_S: Final = 0.1
"""Ground truth is interpolated when both bracketing rows are at most this far away."""
GT_MAX_NEAREST_S: Final = 0.02
"""Without a usable bracket, the nearest ground-truth row is used up to this far away."""
LABEL_STAMP_TOL_S: Final = 5e-7
"""Label stamps equal rgb stamps; files store microseconds, so half a microsecond."""
UINT16_MAX: Final = 65535
PNG_COMPRESSION: Final = 1
"""zlib level for written PNGs; fixed so output bytes never depend on library defaults."""

TUM_CAMERAS: Final[Mapping[str, PinholeCamera]] = MappingProxyType({
    # Published by the TUM RGB-D benchmark ("file formats" page, calibrated colour camera).
    "freiburg1": PinholeCamera(
        640, 480, 517.3, 516.5, 318.6, 255.3, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)
    ),
    "freiburg2": PinholeCamera(
        640, 480, 520.9, 521.0, 325.1, 249.7, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)
    ),
    "freiburg3": PinholeCamera(640, 480, 535.4, 539.2, 320.1, 247.6),
})
"""Colour cameras of the TUM RGB-D sequences, keyed by the name used in their folders."""

_TUM_NAME = re.compile(r"(?<![a-z0-9])(?:freiburg|fr)([123])(?![0-9])")

_RGB_HEADER: Final = "# color images\n# timestamp filename\n"
_DEPTH_HEADER: Final = "# depth maps (uint16 PNG, depth_scale units per metre)\n# timestamp filename\n"
_THERMAL_HEADER: Final = (
    "# thermal images (uint16 PNG, kelvin * thermal_scale)\n# timestamp filename\n"
)
_LABELS_HEADER: Final = "# instance labels (uint16 PNG, 0 = none)\n# timestamp filename\n"
_GT_HEADER: Final = "# ground truth trajectory T_world_rgbcamera\n# timestamp tx ty tz qx qy qz qw\n"
_ODOM_HEADER: Final = "# wheel odometry T_odom_base\n# timestamp tx ty tz qx qy qz qw\n"
_ENCODERS_HEADER: Final = (
    "# wheel encoders (cumulative ticks) and yaw gyro\n"
    "# timestamp left_ticks right_ticks gyro_z_rad_s\n"
)

ASSOCIATION_FILES: Final = ("associations.txt", "rgbd_assoc.txt", "assoc.txt")
"""rgb/depth association files read when present, in this order (TUM associate.py's output under
the names TUM users give it)."""

_LAYOUT_FILES: Final = (
    "rgb.txt", "depth.txt", "thermal.txt", "labels.txt", *ASSOCIATION_FILES,
    "groundtruth.txt", "odometry.txt", "encoders.txt", "calibration.toml", "objects.json",
)
_LAYOUT_DIRS: Final = ("rgb", "depth", "thermal", "labels")


# --------------------------------------------------------------------------- calibration


def _readonly(a: ArrayLike) -> F64:
    out = np.array(a, dtype=np.float64)
    out.flags.writeable = False
    return out


def _positive_finite(value: float, name: str) -> None:
    if not (math.isfinite(value) and value > 0):
        raise DatasetError(f"{name} must be a positive finite number, got {value!r}")


@dataclass(frozen=True, eq=False)
class Calibration:
    """Sensor calibration of one data set (``calibration.toml``).

    Attributes:
        rgb: the colour camera; depth images are registered to it (same size, same pixels).
        depth_scale: depth PNG units per metre (TUM: 5000, i.e. 0.2 mm per unit).
        thermal: the thermal camera, or None when the rig has none.
        T_rgb_thermal: (4, 4) pose of the thermal camera in the rgb camera frame (maps
            thermal-camera points to rgb-camera points); required iff ``thermal`` is given.
        thermal_scale: thermal PNG units per kelvin (100: centikelvin). Not stored in
            ``calibration.toml`` when there is no thermal camera.
        T_base_rgb: (4, 4) pose of the rgb camera in the robot base frame, or None.
        wheel_radius_m, wheel_base_m, ticks_per_mm: differential-drive geometry for
            ``encoders.txt`` (wheel radius, distance between wheels, encoder ticks per mm of
            wheel travel); they need ``T_base_rgb`` (they live in the ``[base]`` table).
        rgb_readout_s: rolling-shutter readout time of the colour camera, seconds from the
            first row to the last (``[rgb] readout_s``); 0 = global shutter (the simulator);
            None = not given (then ``rgb_sensor``'s default, see :attr:`readout`).
            ``wardmap calibrate-readout`` estimates it from a recording.
        rgb_sensor: the colour camera's model (``[rgb] sensor``, a
            :data:`wardmap.shared.sensors.SENSORS` key; TUM folders: ``kinect_v1``), "" = not
            named.

    Matrices are stored as read-only float64 copies. Equality compares every field exactly.
    """

    rgb: PinholeCamera
    depth_scale: float = DEFAULT_DEPTH_SCALE
    thermal: PinholeCamera | None = None
    T_rgb_thermal: F64 | None = None
    thermal_scale: float = DEFAULT_THERMAL_SCALE
    T_base_rgb: F64 | None = None
    wheel_radius_m: float | None = None
    wheel_base_m: float | None = None
    ticks_per_mm: float | None = None
    rgb_readout_s: float | None = None
    rgb_sensor: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.rgb, PinholeCamera):
            raise DatasetError(f"Calibration.rgb must be a PinholeCamera, got {type(self.rgb)}")
        if self.thermal is not None and not isinstance(self.thermal, PinholeCamera):
            raise DatasetError(
                f"Calibration.thermal must be a PinholeCamera or None, got {type(self.thermal)}"
            )
        _positive_finite(self.depth_scale, "Calibration.depth_scale")
        _positive_finite(self.thermal_scale, "Calibration.thermal_scale")
        if self.rgb_sensor and self.rgb_sensor not in SENSORS:
            raise DatasetError(
                f"Calibration.rgb_sensor ([rgb] sensor) {self.rgb_sensor!r} is not a known sensor; "
                f"known: {', '.join(SENSORS)} (or give [rgb] readout_s)"
            )
        if self.rgb_readout_s is not None and not (
            math.isfinite(self.rgb_readout_s) and 0.0 <= self.rgb_readout_s <= MAX_READOUT_S
        ):
            raise DatasetError(
                f"Calibration.rgb_readout_s ([rgb] readout_s) must be in [0, {MAX_READOUT_S}] seconds, "
                f"got {self.rgb_readout_s!r}"
            )
        if (self.thermal is None) != (self.T_rgb_thermal is None):
            raise DatasetError("Calibration: thermal and T_rgb_thermal must be given together")
        for name in ("T_rgb_thermal", "T_base_rgb"):
            value = getattr(self, name)
            if value is not None:
                try:
                    T = check_transform(value, f"Calibration.{name}")
                except GeometryError as exc:
                    raise DatasetError(str(exc)) from exc
                object.__setattr__(self, name, _readonly(T))
        wheel = {"wheel_radius_m": self.wheel_radius_m, "wheel_base_m": self.wheel_base_m,
                 "ticks_per_mm": self.ticks_per_mm}
        for name, value in wheel.items():
            if value is not None:
                _positive_finite(value, f"Calibration.{name}")
        if self.T_base_rgb is None and any(v is not None for v in wheel.values()):
            raise DatasetError("Calibration: wheel parameters need T_base_rgb (the [base] table)")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Calibration):
            return NotImplemented
        for name in ("T_rgb_thermal", "T_base_rgb"):
            a, b = getattr(self, name), getattr(other, name)
            if (a is None) != (b is None) or (a is not None and not np.array_equal(a, b)):
                return False
        return (self.rgb, self.depth_scale, self.thermal, self.thermal_scale,
                self.wheel_radius_m, self.wheel_base_m, self.ticks_per_mm, self.rgb_readout_s,
                self.rgb_sensor) == (
                other.rgb, other.depth_scale, other.thermal, other.thermal_scale,
                other.wheel_radius_m, other.wheel_base_m, other.ticks_per_mm, other.rgb_readout_s,
                other.rgb_sensor)

    __hash__ = None  # type: ignore[assignment]  # holds arrays: equality is by value

    @property
    def readout(self) -> ReadoutModel:
        """The readout time tracking uses and where it comes from
        (:func:`wardmap.shared.sensors.readout_model`)."""
        return readout_model(self.rgb_readout_s, self.rgb_sensor)

    def to_toml_dict(self) -> dict[str, Any]:
        """The ``calibration.toml`` tables as plain Python values (None fields left out)."""
        out: dict[str, Any] = {"rgb": {**_camera_dict(self.rgb), "depth_scale": self.depth_scale}}
        if self.rgb_readout_s is not None:
            out["rgb"]["readout_s"] = self.rgb_readout_s
        if self.rgb_sensor:
            out["rgb"]["sensor"] = self.rgb_sensor
        if self.thermal is not None and self.T_rgb_thermal is not None:
            out["thermal"] = {
                **_camera_dict(self.thermal),
                "T_rgb_thermal": self.T_rgb_thermal.tolist(),
                "thermal_scale": self.thermal_scale,
            }
        if self.T_base_rgb is not None:
            base: dict[str, Any] = {"T_base_rgb": self.T_base_rgb.tolist()}
            for name in ("wheel_radius_m", "wheel_base_m", "ticks_per_mm"):
                if getattr(self, name) is not None:
                    base[name] = getattr(self, name)
            out["base"] = base
        return out

    @staticmethod
    def from_toml_dict(d: Mapping[str, Any], source: str) -> Calibration:
        """Build a calibration from parsed ``calibration.toml`` tables, validating every key.

        Args:
            d: the parsed TOML document.
            source: where it came from (a file name), used in error messages.

        Raises:
            DatasetError: unknown or missing table or key, a value of the wrong type, a
                camera that is not valid, or a matrix that is not a rigid transform. The
                message names ``source`` and the ``[table] key``.
        """
        if not isinstance(d, Mapping):
            raise DatasetError(f"{source}: expected a TOML document (tables), got {type(d)}")
        _check_keys(d, source, "", required=("rgb",), optional=("thermal", "base"))
        rgb_t = _table(d, "rgb", source)
        _check_keys(rgb_t, source, "rgb", required=_CAMERA_KEYS,
                    optional=("depth_scale", "readout_s", "sensor"))
        kwargs: dict[str, Any] = {
            "rgb": _camera_from(rgb_t, source, "rgb"),
            "depth_scale": _number(rgb_t, "depth_scale", source, "rgb", DEFAULT_DEPTH_SCALE),
            "rgb_readout_s": _number(rgb_t, "readout_s", source, "rgb") if "readout_s" in rgb_t else None,
        }
        if "sensor" in rgb_t:
            if not isinstance(rgb_t["sensor"], str):
                raise DatasetError(f"{source}: {_where('rgb', 'sensor')}: expected a string, "
                                   f"got {rgb_t['sensor']!r}")
            kwargs["rgb_sensor"] = rgb_t["sensor"]
        if "thermal" in d:
            th_t = _table(d, "thermal", source)
            _check_keys(th_t, source, "thermal", required=(*_CAMERA_KEYS, "T_rgb_thermal"),
                        optional=("thermal_scale",))
            kwargs["thermal"] = _camera_from(th_t, source, "thermal")
            kwargs["T_rgb_thermal"] = _transform(th_t, "T_rgb_thermal", source, "thermal")
            kwargs["thermal_scale"] = _number(th_t, "thermal_scale", source, "thermal",
                                              DEFAULT_THERMAL_SCALE)
        if "base" in d:
            base_t = _table(d, "base", source)
            _check_keys(base_t, source, "base", required=("T_base_rgb",),
                        optional=("wheel_radius_m", "wheel_base_m", "ticks_per_mm"))
            kwargs["T_base_rgb"] = _transform(base_t, "T_base_rgb", source, "base")
            for name in ("wheel_radius_m", "wheel_base_m", "ticks_per_mm"):
                if name in base_t:
                    kwargs[name] = _number(base_t, name, source, "base")
        try:
            return Calibration(**kwargs)
        except DatasetError as exc:
            raise DatasetError(f"{source}: {exc}") from exc


_CAMERA_KEYS: Final = ("width", "height", "fx", "fy", "cx", "cy", "distortion")


def _camera_dict(cam: PinholeCamera) -> dict[str, Any]:
    return {"width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy,
            "cx": cam.cx, "cy": cam.cy, "distortion": list(cam.distortion)}


def _where(table: str, key: str) -> str:
    return f"[{table}] {key}" if table else key


def _check_keys(t: Mapping[str, Any], source: str, table: str, *,
                required: tuple[str, ...], optional: tuple[str, ...]) -> None:
    what = f"[{table}]" if table else "top level"
    unknown = sorted(set(t) - set(required) - set(optional))
    if unknown:
        raise DatasetError(f"{source}: {what}: unknown key(s) {', '.join(unknown)}; "
                           f"known: {', '.join((*required, *optional))}")
    missing = [k for k in required if k not in t]
    if missing:
        kind = "table" if not table else "key"
        raise DatasetError(f"{source}: {what}: missing {kind}(s) {', '.join(missing)}")


def _table(d: Mapping[str, Any], name: str, source: str) -> Mapping[str, Any]:
    t = d[name]
    if not isinstance(t, Mapping):
        raise DatasetError(f"{source}: [{name}] must be a table, got {type(t).__name__}")
    return t


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _number(t: Mapping[str, Any], key: str, source: str, table: str,
            default: float | None = None) -> float:
    if key not in t:
        if default is None:
            raise DatasetError(f"{source}: {_where(table, key)}: missing")
        return default
    v = t[key]
    if not _is_number(v) or not math.isfinite(v):
        raise DatasetError(f"{source}: {_where(table, key)}: expected a finite number, got {v!r}")
    return float(v)


def _integer(t: Mapping[str, Any], key: str, source: str, table: str) -> int:
    v = t[key]
    if isinstance(v, bool) or not isinstance(v, int):
        raise DatasetError(f"{source}: {_where(table, key)}: expected an integer, got {v!r}")
    return v


def _vector(t: Mapping[str, Any], key: str, n: int, source: str, table: str) -> list[float]:
    v = t[key]
    if not isinstance(v, list) or len(v) != n or not all(_is_number(x) for x in v):
        raise DatasetError(
            f"{source}: {_where(table, key)}: expected an array of {n} numbers, got {v!r}"
        )
    return [float(x) for x in v]


def _transform(t: Mapping[str, Any], key: str, source: str, table: str) -> F64:
    v = t[key]
    ok = (isinstance(v, list) and len(v) == 4
          and all(isinstance(r, list) and len(r) == 4 and all(_is_number(x) for x in r)
                  for r in v))
    if not ok:
        raise DatasetError(f"{source}: {_where(table, key)}: expected a 4x4 matrix as a list "
                           f"of 4 rows of 4 numbers, got {v!r}")
    try:
        return check_transform(v, key)
    except GeometryError as exc:
        raise DatasetError(f"{source}: {_where(table, key)}: not a rigid transform: {exc}") from exc


def _camera_from(t: Mapping[str, Any], source: str, table: str) -> PinholeCamera:
    width = _integer(t, "width", source, table)
    height = _integer(t, "height", source, table)
    fx, fy, cx, cy = (_number(t, k, source, table) for k in ("fx", "fy", "cx", "cy"))
    k1, k2, p1, p2, k3 = _vector(t, "distortion", 5, source, table)
    try:
        return PinholeCamera(width, height, fx, fy, cx, cy, (k1, k2, p1, p2, k3))
    except GeometryError as exc:
        raise DatasetError(f"{source}: [{table}]: {exc}") from exc


def calibration_to_toml(calib: Calibration) -> str:
    """The text of ``calibration.toml`` for ``calib`` (deterministic; floats written exactly)."""
    return "# wardmap sensor calibration; keys and units: docs/dataset.md\n\n" + tomli_w.dumps(
        calib.to_toml_dict()
    )


def load_calibration(path: str | Path) -> Calibration:
    """Read and validate a ``calibration.toml``.

    Raises:
        DatasetError: the file is missing, not TOML, or fails validation.
    """
    p = Path(path)
    try:
        doc = load_toml(p)
    except ConfigError as exc:
        raise DatasetError(str(exc)) from exc
    return Calibration.from_toml_dict(doc, str(p))


def save_calibration(path: str | Path, calib: Calibration) -> None:
    """Write ``calib`` as TOML to ``path`` (see :func:`calibration_to_toml`)."""
    _write_text(Path(path), calibration_to_toml(calib))


def tum_camera_for_folder(name: str) -> PinholeCamera | None:
    """The TUM colour camera named in a folder name (``freiburg1``..``3`` or ``fr1``..``3``).

    Returns None when the name names none, or names more than one.
    """
    found = {m.group(1) for m in _TUM_NAME.finditer(name.lower())}
    if len(found) != 1:
        return None
    return TUM_CAMERAS[f"freiburg{found.pop()}"]


# --------------------------------------------------------------------------- encodings


def encode_scaled_uint16(values: ArrayLike, scale: float) -> U16:
    """Quantise values (depth in metres, temperature in kelvin) to uint16 PNG units.

    ``round(values * scale)`` clipped to 65535; NaN, infinite and negative values become 0
    (no data), as do positive values below half a unit.
    """
    v = np.asarray(values, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        scaled = v * float(scale)
        bad = ~np.isfinite(scaled) | (scaled < 0)
    scaled = np.where(bad, 0.0, scaled)
    return np.clip(np.rint(scaled), 0, UINT16_MAX).astype(np.uint16)


def decode_scaled_uint16(raw: ArrayLike, scale: float) -> F32:
    """Inverse of :func:`encode_scaled_uint16`: uint16 units to float32 values (0 stays 0)."""
    return (np.asarray(raw, dtype=np.float64) / float(scale)).astype(np.float32)


def encode_png(image: NDArray[Any], path: Path) -> bytes:
    """PNG bytes of an 8-bit colour (H, W, 3, **RGB order**) or uint16 (H, W) image."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
    if not ok:
        raise DatasetError(f"{path}: PNG encoding failed")
    return bytes(np.asarray(buf).tobytes())


def read_png(path: Path) -> NDArray[Any]:
    """Decode a PNG as stored (colour comes back in **BGR** order, 16-bit stays 16-bit).

    Raises:
        DatasetError: the file cannot be read or is not a decodable image.
    """
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read image: {exc.strerror or exc}") from exc
    img: NDArray[Any] | None
    try:
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    if img is None:
        raise DatasetError(f"{path}: not a readable image (corrupt, truncated or empty file)")
    return img


# --------------------------------------------------------------------------- time


def associate_stamps(first: ArrayLike, second: ArrayLike, max_dt_s: float) -> list[tuple[int, int]]:
    """Pair stamps of two streams the way TUM's ``associate.py`` does.

    Candidate pairs with ``|a - b| < max_dt_s`` are taken closest first; each stamp is used
    at most once. Ties are broken by index, so the result is deterministic.

    Returns:
        ``(i, j)`` index pairs into ``first`` and ``second``, sorted by ``i``.
    """
    a = np.asarray(first, dtype=np.float64).reshape(-1)
    b = np.asarray(second, dtype=np.float64).reshape(-1)
    order = np.argsort(b, kind="stable")
    b_sorted = b[order]
    lo = np.searchsorted(b_sorted, a - max_dt_s, side="left")
    hi = np.searchsorted(b_sorted, a + max_dt_s, side="right")
    candidates: list[tuple[float, int, int]] = []
    for i in range(a.shape[0]):
        for k in range(int(lo[i]), int(hi[i])):
            dt = abs(float(a[i]) - float(b_sorted[k]))
            if dt < max_dt_s:
                candidates.append((dt, i, int(order[k])))
    candidates.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs: list[tuple[int, int]] = []
    for _, i, j in candidates:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    pairs.sort()
    return pairs


def pose_at(stamps: ArrayLike, T: ArrayLike, t: float, *, max_bracket_s: float = GT_MAX_BRACKET_S,
            max_nearest_s: float = GT_MAX_NEAREST_S) -> F64 | None:
    """Pose of a trajectory at time ``t``, or None when the trajectory does not cover ``t``.

    Args:
        stamps: (M,) strictly increasing stamps in seconds.
        T: (M, 4, 4) poses ``T_a_b`` at those stamps.
        t: query stamp in seconds.
        max_bracket_s: interpolate (linear translation, slerp rotation) between the rows
            just before and just after ``t`` when both are at most this far from ``t``.
        max_nearest_s: otherwise use the nearest row if it is at most this far away.

    Returns:
        A new (4, 4) float64 pose, or None.
    """
    s = np.asarray(stamps, dtype=np.float64)
    P = np.asarray(T, dtype=np.float64)
    m = s.shape[0]
    if m == 0:
        return None
    k = int(np.searchsorted(s, t, side="left"))  # s[k-1] < t <= s[k]
    if k < m and s[k] == t:
        return P[k].copy()
    if 0 < k < m and t - s[k - 1] <= max_bracket_s and s[k] - t <= max_bracket_s:
        return interpolate_transform(P[k - 1], P[k], (t - s[k - 1]) / (s[k] - s[k - 1]))
    near = [j for j in (k - 1, k) if 0 <= j < m]
    j = min(near, key=lambda j: abs(s[j] - t))
    if abs(s[j] - t) <= max_nearest_s:
        return P[j].copy()
    return None


# --------------------------------------------------------------------------- text files


class _Row(NamedTuple):
    line: int
    fields: list[str]


def odom_at(odo: tuple[F64, F64] | None, stamp: float) -> F64 | None:
    """Wheel-odometry pose ``T_odom_base`` at ``stamp`` from :meth:`DatasetReader.odometry`, or
    None (no odometry, or none within 0.1 s bracket / 0.05 s nearest: :func:`pose_at`)."""
    if odo is None:
        return None
    return pose_at(odo[0], odo[1], stamp, max_bracket_s=0.1, max_nearest_s=0.05)


def _match_equal(sorted_stamps: F64, query: F64, tol: float) -> list[int | None]:
    """For each query stamp, the index of the equal (within ``tol``) sorted stamp, or None."""
    m = sorted_stamps.shape[0]
    first = np.searchsorted(sorted_stamps, query - tol, side="left")
    return [int(k) if k < m and abs(sorted_stamps[k] - q) <= tol else None
            for q, k in zip(query, first, strict=True)]


def _read_rows(path: Path) -> list[_Row]:
    """Non-comment rows of a TUM text file, split like associate.py (spaces, tabs, commas)."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path}: not a UTF-8 text file ({exc.reason})") from exc
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    rows = []
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        rows.append(_Row(n, line.replace(",", " ").replace("\t", " ").split()))
    return rows


def _float(path: Path, row: _Row, col: int, what: str) -> float:
    try:
        v = float(row.fields[col])
    except ValueError:
        raise DatasetError(
            f"{path}:{row.line}: {what} is not a number: {row.fields[col]!r}"
        ) from None
    if not math.isfinite(v):
        raise DatasetError(f"{path}:{row.line}: {what} is not finite: {row.fields[col]!r}")
    return v


def _check_columns(path: Path, row: _Row, names: tuple[str, ...]) -> None:
    if len(row.fields) != len(names):
        raise DatasetError(
            f"{path}:{row.line}: expected {len(names)} columns ({' '.join(names)}), "
            f"got {len(row.fields)}: {' '.join(row.fields)!r}"
        )


def _check_increasing(path: Path, rows: list[_Row], stamps: list[float]) -> None:
    for k in range(1, len(stamps)):
        if stamps[k] <= stamps[k - 1]:
            raise DatasetError(
                f"{path}:{rows[k].line}: stamp {rows[k].fields[0]} is not after the previous "
                f"row's {rows[k - 1].fields[0]} (rows must be sorted by strictly increasing stamp)"
            )


def _relative(path: Path, row: _Row, col: int) -> str:
    rel = row.fields[col]
    p = PurePosixPath(rel)
    if p.is_absolute() or ".." in p.parts or re.match(r"^[A-Za-z]:", rel):
        raise DatasetError(
            f"{path}:{row.line}: image path {rel!r} must be relative to the data-set folder"
        )
    return rel


class _ListFile(NamedTuple):
    """A parsed ``stamp path`` list (rgb.txt, depth.txt, thermal.txt, labels.txt)."""

    path: Path
    stamps: F64
    files: tuple[str, ...]
    lines: tuple[int, ...]


def _read_list(path: Path) -> _ListFile:
    rows = _read_rows(path)
    stamps, files = [], []
    for row in rows:
        _check_columns(path, row, ("timestamp", "filename"))
        stamps.append(_float(path, row, 0, "timestamp"))
        files.append(_relative(path, row, 1))
    _check_increasing(path, rows, stamps)
    return _ListFile(path, _readonly(stamps), tuple(files), tuple(r.line for r in rows))


def _read_associations(path: Path) -> tuple[_ListFile, _ListFile]:
    rows = _read_rows(path)
    names = ("rgb_timestamp", "rgb_filename", "depth_timestamp", "depth_filename")
    rgb_s, rgb_f, depth_s, depth_f = [], [], [], []
    for row in rows:
        _check_columns(path, row, names)
        rgb_s.append(_float(path, row, 0, "rgb timestamp"))
        rgb_f.append(_relative(path, row, 1))
        depth_s.append(_float(path, row, 2, "depth timestamp"))
        depth_f.append(_relative(path, row, 3))
    _check_increasing(path, rows, rgb_s)
    lines = tuple(r.line for r in rows)
    return (_ListFile(path, _readonly(rgb_s), tuple(rgb_f), lines),
            _ListFile(path, _readonly(depth_s), tuple(depth_f), lines))


def read_tum_trajectory(path: str | Path) -> tuple[F64, F64]:
    """Read a TUM trajectory file: stamps (N,) seconds and poses (N, 4, 4).

    Raises:
        DatasetError: missing file, malformed row (with its line number), bad quaternion,
            stamps not increasing, or no pose at all.
    """
    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"trajectory file not found: {p}")
    return _read_trajectory(p)


def _read_trajectory(path: Path) -> tuple[F64, F64]:
    rows = _read_rows(path)
    names = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
    stamps: list[float] = []
    poses = np.empty((len(rows), 4, 4))
    for k, row in enumerate(rows):
        _check_columns(path, row, names)
        values = [_float(path, row, c, names[c]) for c in range(8)]
        stamps.append(values[0])
        try:
            poses[k] = transform_from_tum(values[1:])
        except GeometryError as exc:
            raise DatasetError(f"{path}:{row.line}: bad pose: {exc}") from exc
    _check_increasing(path, rows, stamps)
    if not rows:
        raise DatasetError(f"{path}: holds no poses")
    return _readonly(stamps), _readonly(poses)


def _read_encoders(path: Path) -> F64:
    rows = _read_rows(path)
    names = ("timestamp", "left_ticks", "right_ticks", "gyro_z_rad_s")
    out = np.empty((len(rows), 4))
    for k, row in enumerate(rows):
        _check_columns(path, row, names)
        out[k] = [_float(path, row, c, names[c]) for c in range(4)]
    _check_increasing(path, rows, list(out[:, 0]))
    if not rows:
        raise DatasetError(f"{path}: holds no rows")
    return _readonly(out)


def _write_text(path: Path, text: str) -> None:
    try:
        with path.open("w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot write: {exc.strerror or exc}") from exc


def _write_bytes(path: Path, data: bytes) -> None:
    try:
        path.write_bytes(data)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot write: {exc.strerror or exc}") from exc


def _fmt_stamp(stamp: float, what: str) -> str:
    s = float(stamp)
    if not math.isfinite(s):
        raise DatasetError(f"{what}: stamp must be finite, got {stamp!r}")
    return f"{s:.6f}"


def _pose_row(stamp: str, T: F64) -> str:
    return stamp + "".join(f" {v:.9f}" for v in transform_to_tum(T)) + "\n"


# --------------------------------------------------------------------------- reader


@dataclass(frozen=True, eq=False)
class Frame:
    """One associated frame of a data set.

    Attributes:
        index: position in the reader (0..N-1).
        stamp: rgb stamp in seconds.
        rgb: uint8 (H, W, 3), RGB channel order.
        depth_m: float32 (H, W) depth along the rgb camera's z axis in metres; 0 = no data.
        thermal_k: float32 (h, w) temperature in kelvin (0 = no data), or None when the
            frame has no thermal image.
        labels: uint16 (H, W) instance id per rgb pixel (0 = none), or None.
        T_world_camera: (4, 4) ground-truth pose of the rgb camera at ``stamp``, or None
            (see :func:`pose_at` for the interpolation rule).
        depth_stamp: stamp of the depth image in seconds.
        thermal_stamp: stamp of the thermal image in seconds, or None.
    """

    index: int
    stamp: float
    rgb: U8
    depth_m: F32
    thermal_k: F32 | None
    labels: U16 | None
    T_world_camera: F64 | None
    depth_stamp: float | None = None
    thermal_stamp: float | None = None


class FrameSource(Protocol):
    """What consumers of frames need: :class:`DatasetReader` and the simulator's live runs.

    Attributes:
        root: the folder, or a display name for sources without one.
        calibration: the sensor calibration.
        stamps: (N,) colour stamps in seconds.
    """

    root: Path
    calibration: Calibration
    stamps: F64

    def __len__(self) -> int: ...

    def frame(self, i: int) -> Frame:
        """Frame ``i``; raises IndexError out of range, DatasetError on unreadable data."""
        ...

    def odometry(self) -> tuple[F64, F64] | None:
        """Wheel odometry ``(stamps (M,), T_odom_base (M, 4, 4))``, or None."""
        ...

    def groundtruth(self) -> tuple[F64, F64] | None:
        """Ground-truth ``(stamps (K,), T_world_camera (K, 4, 4))``, or None."""
        ...

    def objects(self) -> dict[str, Any] | None:
        """The ``objects.json`` document, or None."""
        ...

    @property
    def has_labels(self) -> bool: ...


class DatasetReader:
    """Read a data-set folder (extended TUM RGB-D layout, docs/dataset.md).

    The folder is validated when the reader is made: list files parse, stamps increase,
    every referenced image file exists, ``calibration.toml`` is valid (or the folder name
    names a TUM camera). Images are loaded on demand by :meth:`frame`.

    Frames are rgb images paired with a depth image: from the association file
    ``associations`` when given, else the first of :data:`ASSOCIATION_FILES` in the folder,
    otherwise by nearest stamp within ``max_depth_dt_s`` (TUM associate.py rule). An
    association file may list depth before rgb (``associate.py depth.txt rgb.txt``): the
    columns are swapped when its rgb column names depth.txt's files.
    Thermal images pair with frames the same way within ``max_thermal_dt_s``; labels by
    equal stamp.

    Attributes:
        root: the folder.
        calibration: the sensor calibration.
        stamps: (N,) rgb stamps in seconds of the associated frames (read-only).
        associations: the association file read, or None (paired by nearest stamps).
    """

    def __init__(self, root: str | Path, *, max_depth_dt_s: float = MAX_DEPTH_DT_S,
                 max_thermal_dt_s: float = MAX_THERMAL_DT_S,
                 associations: str | Path | None = None) -> None:
        self.root = Path(root)
        if not self.root.exists():
            raise DatasetError(f"data-set folder not found: {self.root}")
        if not self.root.is_dir():
            raise DatasetError(f"data-set path is not a folder: {self.root}")
        for name in ("rgb.txt", "depth.txt"):
            if not (self.root / name).is_file():
                raise DatasetError(f"{self.root}: missing {name} (a data set needs rgb.txt, "
                                   "depth.txt and their image folders; see docs/dataset.md)")
        self.calibration = self._load_calibration()
        rgb = _read_list(self.root / "rgb.txt")
        depth = _read_list(self.root / "depth.txt")
        listed = [rgb, depth]

        assoc_file = self._association_file(associations)
        self.associations: Path | None = assoc_file
        if assoc_file is not None:
            rgb_f, depth_f = _read_associations(assoc_file)
            if set(rgb_f.files) <= set(depth.files) and not set(rgb_f.files) <= set(rgb.files):
                rgb_f, depth_f = depth_f, rgb_f  # written as "depth rgb"
            listed.append(rgb_f)
            listed.append(depth_f)
            how = str(assoc_file)
        else:
            pairs = associate_stamps(rgb.stamps, depth.stamps, max_depth_dt_s)
            ri = [i for i, _ in pairs]
            di = [j for _, j in pairs]
            rgb_f = _ListFile(rgb.path, _readonly(rgb.stamps[ri]), tuple(rgb.files[i] for i in ri),
                              tuple(rgb.lines[i] for i in ri))
            depth_f = _ListFile(depth.path, _readonly(depth.stamps[di]),
                                tuple(depth.files[j] for j in di), tuple(depth.lines[j] for j in di))
            how = f"nearest stamps within {max_depth_dt_s} s"
        if len(rgb_f.stamps) == 0:
            raise DatasetError(f"{self.root}: no rgb image has a depth image ({how}); check the "
                               "stamps in rgb.txt and depth.txt")
        self._rgb = rgb_f
        self._depth = depth_f
        self.stamps: F64 = rgb_f.stamps
        n = len(self.stamps)

        self._thermal_file: _ListFile | None = None
        self._thermal_of: list[int | None] = [None] * n
        if (self.root / "thermal.txt").is_file():
            if self.calibration.thermal is None:
                raise DatasetError(f"{self.root}: thermal.txt is present but the calibration has "
                                   "no [thermal] table")
            th = _read_list(self.root / "thermal.txt")
            listed.append(th)
            for i, j in associate_stamps(self.stamps, th.stamps, max_thermal_dt_s):
                self._thermal_of[i] = j
            self._thermal_file = th

        self._labels_file: _ListFile | None = None
        self._labels_of: list[int | None] = [None] * n
        if (self.root / "labels.txt").is_file():
            lab = _read_list(self.root / "labels.txt")
            listed.append(lab)
            in_rgb = _match_equal(rgb.stamps, lab.stamps, LABEL_STAMP_TOL_S)
            for k, match in enumerate(in_rgb):
                if match is None:
                    raise DatasetError(f"{lab.path}:{lab.lines[k]}: stamp {lab.stamps[k]:.6f} is "
                                       "not an rgb.txt stamp (labels use the rgb stamps)")
            self._labels_of = _match_equal(lab.stamps, self.stamps, LABEL_STAMP_TOL_S)
            self._labels_file = lab

        self._check_files_exist(listed)
        self._gt = self._optional_trajectory("groundtruth.txt")
        self._odom = self._optional_trajectory("odometry.txt")
        enc = self.root / "encoders.txt"
        self._encoders = _read_encoders(enc) if enc.is_file() else None
        log.debug("%s: %d frames (%s), thermal %s, labels %s, ground truth %s", self.root, n,
                  how, self.has_thermal, self.has_labels, self._gt is not None)

    def _association_file(self, given: str | Path | None) -> Path | None:
        if given is not None:
            path = Path(given)
            if not path.is_absolute() and not path.exists() and (self.root / path).exists():
                path = self.root / path  # a name inside the folder
            if not path.is_file():
                raise DatasetError(f"association file not found: {given}")
            return path
        found = [self.root / n for n in ASSOCIATION_FILES if (self.root / n).is_file()]
        if len(found) > 1:
            log.info("%s: %d association files; reading %s", self.root, len(found), found[0].name)
        return found[0] if found else None

    def _load_calibration(self) -> Calibration:
        path = self.root / "calibration.toml"
        if path.is_file():
            return load_calibration(path)
        # The folder's own name (a link named after its sequence says which camera), then the
        # name of the folder a link points to.
        own = Path(os.path.abspath(self.root)).name
        target = self.root.resolve().name
        for name in dict.fromkeys((own, target)):
            tum = tum_camera_for_folder(name)
            if tum is not None:
                return Calibration(rgb=tum, depth_scale=DEFAULT_DEPTH_SCALE, rgb_sensor=TUM_SENSOR)
        names = repr(own) if own == target else f"{own!r} (a link to {target!r})"
        raise DatasetError(
            f"{self.root}: no calibration.toml, and the folder name {names} does not say "
            "which TUM camera took it; add a calibration.toml (docs/dataset.md) or, for a "
            "TUM RGB-D sequence, keep 'freiburg1', 'freiburg2' or 'freiburg3' (or 'fr1', "
            "'fr2', 'fr3') in the folder name"
        )

    def _check_files_exist(self, lists: list[_ListFile]) -> None:
        missing: list[str] = []
        seen: set[str] = set()
        for lf in lists:
            for rel, line in zip(lf.files, lf.lines, strict=True):
                if rel in seen:
                    continue
                seen.add(rel)
                if not (self.root / rel).is_file():
                    missing.append(f"{lf.path}:{line}: {rel}")
        if missing:
            more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
            raise DatasetError(f"referenced image file does not exist: {missing[0]}{more}")

    def _optional_trajectory(self, name: str) -> tuple[F64, F64] | None:
        path = self.root / name
        return _read_trajectory(path) if path.is_file() else None

    def __len__(self) -> int:
        return len(self.stamps)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self.frame(i)

    def __repr__(self) -> str:
        return f"DatasetReader({str(self.root)!r}, {len(self)} frames)"

    @property
    def has_thermal(self) -> bool:
        """True when the folder has ``thermal.txt``."""
        return self._thermal_file is not None

    @property
    def has_labels(self) -> bool:
        """True when the folder has ``labels.txt``."""
        return self._labels_file is not None

    @property
    def has_groundtruth(self) -> bool:
        """True when the folder has ``groundtruth.txt``."""
        return self._gt is not None

    def frame(self, i: int) -> Frame:
        """Load frame ``i`` (negative indices count from the end).

        Raises:
            IndexError: ``i`` out of range.
            DatasetError: an image is missing, corrupt, or has the wrong type or size.
        """
        i = operator.index(i)
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for {n} frames")
        i = i % n
        cam = self.calibration.rgb
        rgb_path = self.root / self._rgb.files[i]
        bgr = read_png(rgb_path)
        if bgr.dtype != np.uint8 or bgr.ndim != 3 or bgr.shape[2] != 3:
            raise DatasetError(f"{rgb_path}: expected an 8-bit colour image (H, W, 3), got "
                               f"{bgr.dtype} {bgr.shape}")
        _check_size(rgb_path, bgr.shape[:2], (cam.height, cam.width), "the rgb calibration")
        rgb = np.asarray(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), dtype=np.uint8)

        depth_path = self.root / self._depth.files[i]
        depth_m = decode_scaled_uint16(_read_uint16(depth_path, bgr.shape[:2], "the rgb image"),
                                       self.calibration.depth_scale)

        thermal_k: F32 | None = None
        thermal_stamp: float | None = None
        j = self._thermal_of[i]
        th_cam = self.calibration.thermal
        if j is not None and self._thermal_file is not None and th_cam is not None:
            th_path = self.root / self._thermal_file.files[j]
            raw = _read_uint16(th_path, (th_cam.height, th_cam.width), "the thermal calibration")
            thermal_k = decode_scaled_uint16(raw, self.calibration.thermal_scale)
            thermal_stamp = float(self._thermal_file.stamps[j])

        labels: U16 | None = None
        k = self._labels_of[i]
        if k is not None and self._labels_file is not None:
            labels = _read_uint16(self.root / self._labels_file.files[k], bgr.shape[:2],
                                  "the rgb image")

        stamp = float(self.stamps[i])
        T = pose_at(self._gt[0], self._gt[1], stamp) if self._gt is not None else None
        return Frame(index=i, stamp=stamp, rgb=rgb, depth_m=depth_m, thermal_k=thermal_k,
                     labels=labels, T_world_camera=T, depth_stamp=float(self._depth.stamps[i]),
                     thermal_stamp=thermal_stamp)

    def groundtruth(self) -> tuple[F64, F64] | None:
        """``(stamps (M,), T_world_rgbcamera (M, 4, 4))`` from groundtruth.txt, or None."""
        return None if self._gt is None else (self._gt[0].copy(), self._gt[1].copy())

    def odometry(self) -> tuple[F64, F64] | None:
        """``(stamps (M,), T_odom_base (M, 4, 4))`` from odometry.txt, or None."""
        return None if self._odom is None else (self._odom[0].copy(), self._odom[1].copy())

    def encoders(self) -> F64 | None:
        """(K, 4) rows ``stamp, left_ticks, right_ticks, gyro_z_rad_s``, or None."""
        return None if self._encoders is None else self._encoders.copy()

    def objects(self) -> dict[str, Any] | None:
        """The parsed ``objects.json`` (a new dict per call), or None when absent.

        Raises:
            DatasetError: the file is not JSON or not a JSON object.
        """
        path = self.root / "objects.json"
        if not path.is_file():
            return None
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise DatasetError(f"{path}:{exc.lineno}: not valid JSON: {exc.msg}") from exc
        except (OSError, UnicodeDecodeError) as exc:
            raise DatasetError(f"{path}: cannot read: {exc}") from exc
        if not isinstance(doc, dict):
            raise DatasetError(f"{path}: expected a JSON object at the top, got "
                               f"{type(doc).__name__}")
        return doc


def _check_size(path: Path, got: tuple[int, ...], want: tuple[int, int], what: str) -> None:
    if tuple(got) != want:
        raise DatasetError(f"{path}: image is {got[1]}x{got[0]} but {what} says "
                           f"{want[1]}x{want[0]} (width x height)")


def _read_uint16(path: Path, shape: tuple[int, ...], what: str) -> U16:
    img = read_png(path)
    if img.dtype != np.uint16 or img.ndim != 2:
        raise DatasetError(f"{path}: expected a 16-bit single-channel image, got {img.dtype} "
                           f"{img.shape}")
    _check_size(path, img.shape, (int(shape[0]), int(shape[1])), what)
    return np.asarray(img, dtype=np.uint16)


# --------------------------------------------------------------------------- writer


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


class DatasetWriter:
    """Write a data-set folder (extended TUM RGB-D layout, docs/dataset.md).

    Use as a context manager: ``with DatasetWriter(root, calibration) as w: ...``. Images
    are written by :meth:`write_frame` as it is called; the list files and
    ``groundtruth.txt`` by :meth:`close` (also on leaving the ``with`` block, even on an
    exception, so the frames written so far form a valid data set). Output is
    deterministic: the same calls give byte-identical files.

    Stamps are stored with 6 decimals (microseconds) and must increase frame to frame.
    """

    def __init__(self, root: str | Path, calibration: Calibration, *, overwrite: bool = False,
                 max_thermal_dt_s: float = MAX_THERMAL_DT_S) -> None:
        """Create ``root`` (and ``rgb/``, ``depth/``) and write ``calibration.toml``.

        Args:
            root: the data-set folder; created with its parents if missing.
            calibration: written to ``calibration.toml``; image sizes are checked against it.
            overwrite: allow a non-empty ``root``; the data-set files and folders in it
                (``rgb/``, ``depth/``, ``thermal/``, ``labels/``, the list files,
                ``calibration.toml``, ``objects.json``) are deleted first, other files kept.
            max_thermal_dt_s: largest allowed ``|thermal_stamp - stamp|``; the reader pairs
                thermal images with frames within this distance.

        Raises:
            DatasetError: ``root`` is not empty (without ``overwrite``), is a file, or
                cannot be created or written.
        """
        if not isinstance(calibration, Calibration):
            raise DatasetError(f"DatasetWriter: calibration must be a Calibration, got "
                               f"{type(calibration)}")
        self.root = Path(root)
        self.calibration = calibration
        self._max_thermal_dt_s = max_thermal_dt_s
        self._prepare(overwrite)
        save_calibration(self.root / "calibration.toml", calibration)
        self._rgb_rows: list[str] = []
        self._depth_rows: list[str] = []
        self._thermal_rows: list[str] = []
        self._labels_rows: list[str] = []
        self._gt_rows: list[str] = []
        self._last_stamp: float | None = None
        self._last_thermal_stamp: float | None = None
        self._written: set[str] = set()
        self._closed = False

    def _prepare(self, overwrite: bool) -> None:
        root = self.root
        try:
            if root.exists() and not root.is_dir():
                raise DatasetError(f"cannot write a data set to {root}: it is a file")
            if root.is_dir() and any(root.iterdir()):
                if not overwrite:
                    raise DatasetError(f"data-set folder {root} is not empty; choose an empty or "
                                       "new folder, or pass overwrite=True")
                for name in _LAYOUT_DIRS + _LAYOUT_FILES:
                    p = root / name
                    if p.is_dir() and not p.is_symlink():
                        shutil.rmtree(p)
                    elif p.exists() or p.is_symlink():
                        p.unlink()
                log.info("%s: overwriting an existing data set", root)
            root.mkdir(parents=True, exist_ok=True)
            for name in ("rgb", "depth"):
                (root / name).mkdir(exist_ok=True)
        except OSError as exc:
            raise DatasetError(f"cannot create data-set folder {root}: "
                               f"{exc.strerror or exc}") from exc

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def _check_open(self, what: str) -> None:
        if self._closed:
            raise DatasetError(f"{what}: the writer for {self.root} is closed")

    def _mkdir(self, name: str) -> None:
        try:
            (self.root / name).mkdir(exist_ok=True)
        except OSError as exc:
            raise DatasetError(f"cannot create {self.root / name}: {exc.strerror or exc}") from exc

    def write_frame(self, stamp: float, rgb: ArrayLike, depth_m: ArrayLike, *,
                    thermal_k: ArrayLike | None = None, thermal_stamp: float | None = None,
                    labels: ArrayLike | None = None, T_world_camera: ArrayLike | None = None) -> None:
        """Write one frame's images; list rows are kept for :meth:`close`.

        Args:
            stamp: rgb (and depth, labels, ground-truth) stamp in seconds; stored to the
                microsecond and must be after the previous frame's.
            rgb: uint8 (H, W, 3) in RGB order, H x W the rgb calibration's size.
            depth_m: (H, W) depth in metres registered to the rgb camera; 0, NaN, inf and
                negative values mean no data (see :func:`encode_scaled_uint16`).
            thermal_k: (h, w) temperature in kelvin at the thermal calibration's size; needs
                a thermal camera in the calibration.
            thermal_stamp: stamp of the thermal image (default ``stamp``); within
                ``max_thermal_dt_s`` of ``stamp`` and after the previous thermal stamp.
            labels: (H, W) non-negative integer instance ids below 65536 (0 = none).
            T_world_camera: (4, 4) ground-truth pose of the rgb camera, written to
                ``groundtruth.txt``.

        Raises:
            DatasetError: a bad argument (nothing is written then) or a write failure.
        """
        self._check_open("write_frame")
        cal = self.calibration
        stamp_s = _fmt_stamp(stamp, "write_frame")
        if self._last_stamp is not None and float(stamp_s) <= self._last_stamp:
            raise DatasetError(f"write_frame: stamp {stamp_s} is not after the previous frame's "
                               f"{self._last_stamp:.6f} (stamps are stored to the microsecond)")
        H, W = cal.rgb.height, cal.rgb.width
        rgb_a = np.asarray(rgb)
        if rgb_a.dtype != np.uint8 or rgb_a.shape != (H, W, 3):
            raise DatasetError(f"write_frame: rgb must be uint8 ({H}, {W}, 3), got "
                               f"{rgb_a.dtype} {rgb_a.shape}")
        depth_a = np.asarray(depth_m)
        if depth_a.shape != (H, W) or not np.issubdtype(depth_a.dtype, np.number):
            raise DatasetError(f"write_frame: depth_m must be numeric ({H}, {W}), got "
                               f"{depth_a.dtype} {depth_a.shape}")
        images: list[tuple[str, NDArray[Any]]] = [
            (f"rgb/{stamp_s}.png", rgb_a),
            (f"depth/{stamp_s}.png", encode_scaled_uint16(depth_a, cal.depth_scale)),
        ]

        th_stamp_s: str | None = None
        if thermal_k is not None:
            if cal.thermal is None:
                raise DatasetError("write_frame: thermal_k given but the calibration has no "
                                   "thermal camera")
            th_a = np.asarray(thermal_k)
            h, w = cal.thermal.height, cal.thermal.width
            if th_a.shape != (h, w) or not np.issubdtype(th_a.dtype, np.number):
                raise DatasetError(f"write_frame: thermal_k must be numeric ({h}, {w}), got "
                                   f"{th_a.dtype} {th_a.shape}")
            th_stamp_s = _fmt_stamp(stamp if thermal_stamp is None else thermal_stamp,
                                    "write_frame thermal")
            if abs(float(th_stamp_s) - float(stamp_s)) >= self._max_thermal_dt_s:
                raise DatasetError(f"write_frame: thermal_stamp {th_stamp_s} is not within "
                                   f"{self._max_thermal_dt_s} s of the frame stamp {stamp_s}")
            last = self._last_thermal_stamp
            if last is not None and float(th_stamp_s) <= last:
                raise DatasetError(f"write_frame: thermal_stamp {th_stamp_s} is not after the "
                                   f"previous thermal stamp {last:.6f}")
            images.append((f"thermal/{th_stamp_s}.png",
                           encode_scaled_uint16(th_a, cal.thermal_scale)))
        elif thermal_stamp is not None:
            raise DatasetError("write_frame: thermal_stamp given without thermal_k")

        if labels is not None:
            lab = np.asarray(labels)
            if lab.shape != (H, W) or not np.issubdtype(lab.dtype, np.integer):
                raise DatasetError(f"write_frame: labels must be integer ({H}, {W}), got "
                                   f"{lab.dtype} {lab.shape}")
            if lab.size and (int(lab.min()) < 0 or int(lab.max()) > UINT16_MAX):
                raise DatasetError(f"write_frame: labels must lie in 0..{UINT16_MAX}, got "
                                   f"{int(lab.min())}..{int(lab.max())}")
            images.append((f"labels/{stamp_s}.png", lab.astype(np.uint16)))

        gt_row: str | None = None
        if T_world_camera is not None:
            try:
                T = check_transform(T_world_camera, "T_world_camera")
            except GeometryError as exc:
                raise DatasetError(f"write_frame: {exc}") from exc
            gt_row = _pose_row(stamp_s, T)

        for rel, image in images:
            folder = rel.split("/", 1)[0]
            if folder not in self._written:
                self._mkdir(folder)
                self._written.add(folder)
            _write_bytes(self.root / rel, encode_png(image, self.root / rel))
        self._rgb_rows.append(f"{stamp_s} rgb/{stamp_s}.png\n")
        self._depth_rows.append(f"{stamp_s} depth/{stamp_s}.png\n")
        if th_stamp_s is not None:
            self._thermal_rows.append(f"{th_stamp_s} thermal/{th_stamp_s}.png\n")
            self._last_thermal_stamp = float(th_stamp_s)
        if labels is not None:
            self._labels_rows.append(f"{stamp_s} labels/{stamp_s}.png\n")
        if gt_row is not None:
            self._gt_rows.append(gt_row)
        self._last_stamp = float(stamp_s)

    def write_odometry(self, stamps: ArrayLike, T_odom_base: ArrayLike) -> None:
        """Write ``odometry.txt``: wheel-odometry poses of the base in its odom frame.

        Args:
            stamps: (N,) strictly increasing stamps in seconds (stored to the microsecond).
            T_odom_base: (N, 4, 4) rigid transforms.
        """
        self._check_open("write_odometry")
        s = np.asarray(stamps, dtype=np.float64)
        T = np.asarray(T_odom_base, dtype=np.float64)
        if s.ndim != 1 or T.shape != (s.shape[0], 4, 4):
            raise DatasetError(f"write_odometry: expected stamps (N,) and T_odom_base (N, 4, 4), "
                               f"got {s.shape} and {T.shape}")
        stamp_strs = self._stamp_column(s, "write_odometry")
        rows = []
        for k in range(s.shape[0]):
            try:
                Tk = check_transform(T[k], f"T_odom_base[{k}]")
            except GeometryError as exc:
                raise DatasetError(f"write_odometry: {exc}") from exc
            rows.append(_pose_row(stamp_strs[k], Tk))
        _write_text(self.root / "odometry.txt", _ODOM_HEADER + "".join(rows))

    def write_encoders(self, encoders: ArrayLike) -> None:
        """Write ``encoders.txt`` from (K, 4) rows ``stamp, left_ticks, right_ticks, gyro_z_rad_s``.

        Ticks are cumulative integer counts (they may be held as floats); the gyro rate is
        in rad/s, stored with 9 decimals.
        """
        self._check_open("write_encoders")
        E = np.asarray(encoders, dtype=np.float64)
        if E.ndim != 2 or E.shape[1] != 4:
            raise DatasetError(f"write_encoders: expected (K, 4), got {E.shape}")
        if not np.all(np.isfinite(E)):
            raise DatasetError("write_encoders: contains non-finite values")
        ticks = E[:, 1:3]
        if not np.array_equal(ticks, np.round(ticks)) or np.any(np.abs(ticks) >= 2.0**53):
            raise DatasetError("write_encoders: tick columns must hold integer counts")
        stamp_strs = self._stamp_column(E[:, 0], "write_encoders")
        rows = [f"{stamp_strs[k]} {int(E[k, 1])} {int(E[k, 2])} {E[k, 3]:.9f}\n"
                for k in range(E.shape[0])]
        _write_text(self.root / "encoders.txt", _ENCODERS_HEADER + "".join(rows))

    def write_objects(self, objects: Mapping[str, Any]) -> None:
        """Write ``objects.json`` as given (key order kept, 2-space indent).

        numpy arrays and scalars are written as JSON lists and numbers (they read back as
        lists and numbers). NaN and infinity are refused (not JSON).
        """
        self._check_open("write_objects")
        if not isinstance(objects, Mapping):
            raise DatasetError(f"write_objects: expected a dict, got {type(objects).__name__}")
        try:
            text = json.dumps(objects, indent=2, ensure_ascii=False, allow_nan=False,
                              default=_json_default)
        except (TypeError, ValueError) as exc:
            raise DatasetError(f"write_objects: cannot encode as JSON: {exc}") from exc
        _write_text(self.root / "objects.json", text + "\n")

    @staticmethod
    def _stamp_column(stamps: F64, what: str) -> list[str]:
        out = [_fmt_stamp(float(v), what) for v in stamps]
        values = [float(v) for v in out]
        for k in range(1, len(values)):
            if values[k] <= values[k - 1]:
                raise DatasetError(f"{what}: stamps must increase (to the microsecond); row {k} "
                                   f"{out[k]} is not after {out[k - 1]}")
        return out

    def close(self) -> None:
        """Write the list files and ``groundtruth.txt``; calling it again does nothing."""
        if self._closed:
            return
        self._closed = True
        _write_text(self.root / "rgb.txt", _RGB_HEADER + "".join(self._rgb_rows))
        _write_text(self.root / "depth.txt", _DEPTH_HEADER + "".join(self._depth_rows))
        if self._thermal_rows:
            _write_text(self.root / "thermal.txt", _THERMAL_HEADER + "".join(self._thermal_rows))
        if self._labels_rows:
            _write_text(self.root / "labels.txt", _LABELS_HEADER + "".join(self._labels_rows))
        if self._gt_rows:
            _write_text(self.root / "groundtruth.txt", _GT_HEADER + "".join(self._gt_rows))
        log.info("%s: wrote %d frames", self.root, len(self._rgb_rows))

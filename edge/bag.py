"""ROS recordings as a frame source (``--source bag:PATH``), read with the ``rosbags`` library.

Reads ROS 1 bags (``.bag``), ROS 2 bags (a folder with ``metadata.yaml``; sqlite3 or MCAP
storage) and bare ``.mcap`` files, without a ROS installation. Topics and what is taken from
them (:class:`BagSourceConfig`, the ``[source]`` table of a config file):

- colour: ``sensor_msgs/Image`` (``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``mono8``) or
  ``sensor_msgs/CompressedImage`` (JPEG or PNG);
- depth registered to the colour camera (same size, same pixels): ``sensor_msgs/Image``
  ``16UC1``/``mono16`` (units of ``depth_unit_m``, ROS: millimetres) or ``32FC1`` (metres;
  NaN, inf, <= 0 = no data). Compressed depth is not read;
- intrinsics: the first ``sensor_msgs/CameraInfo`` of the colour camera (plumb_bob or
  rational_polynomial distortion; its first five coefficients are OpenCV's k1 k2 p1 p2 k3);
- extrinsics ``T_base_rgb``: ``/tf_static`` (``tf2_msgs/TFMessage``), the chain from the
  base frame to the colour image's frame;
- wheel odometry: ``nav_msgs/Odometry`` (``pose.pose`` is ``T_odom_base``), or, in a recording
  without it, the ``/tf`` transforms from the odometry frame to the base frame.

A ``calibration.toml`` (``calibration`` key) replaces the CameraInfo and tf calibration. Colour
and depth images pair by header stamp (nearest within ``max_depth_dt_s``, the data-set rule);
stamps are header stamps rounded to the microsecond (the data-set files' resolution); messages
are read in the recording's order (its log time), so frames reach the stream as a robot would
have delivered them: a depth image may come after later colour images (a colour image without a
partner waits until depth :data:`REORDER_S` past its window has come). Colour images without
a depth partner are counted (``unpaired``).
"""

from __future__ import annotations

import bisect
import logging
import math
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.edge.stream import FrameProblem, OdometrySample, SourceEvent
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import MAX_DEPTH_DT_S, Calibration, Frame, FrameSource, load_calibration
from wardmap.shared.errors import ConfigError, DatasetError
from wardmap.shared.se3 import transform_from_tum

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
F32 = NDArray[np.float32]
U8 = NDArray[np.uint8]

SOURCE_PREFIX: Final = "bag:"
INSTALL_HINT: Final = "reading ROS recordings needs the rosbags package: pip install 'wardmap[ros]'"
MAX_PENDING: Final = 64
"""Colour or depth images waiting for their partner at most (the oldest is dropped beyond)."""
REORDER_S: Final = 0.1
"""A colour image without a depth partner waits until depth this much past its window came."""

IMAGE: Final = "sensor_msgs/msg/Image"
COMPRESSED: Final = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO: Final = "sensor_msgs/msg/CameraInfo"
ODOMETRY: Final = "nav_msgs/msg/Odometry"
TF: Final = "tf2_msgs/msg/TFMessage"
TF_STATIC_TOPIC: Final = "/tf_static"
TF_TOPIC: Final = "/tf"
TF_SCAN_MESSAGES: Final = 1000
"""``/tf`` messages searched at most for the odometry transform when the source opens."""


@dataclass(frozen=True)
class BagSourceConfig:
    """Topics and conversions of a ROS recording (``[source]`` table; CLI flags override).

    Attributes:
        rgb_topic: colour images (``Image`` or ``CompressedImage``).
        depth_topic: depth images registered to the colour camera (``Image``).
        camera_info_topic: the colour camera's ``CameraInfo``.
        odom_topic: ``nav_msgs/Odometry``, or ``/tf`` (odometry as the transforms
            ``odom_frame`` -> ``base_frame``); None: ``/odom`` when the recording has it, else
            ``/tf`` when it holds that transform; ``""``: none.
        odom_frame: the odometry frame in ``/tf``.
        base_frame: the robot base's tf frame; None: the odometry's ``child_frame_id``
            (``base_link`` without ``nav_msgs/Odometry``).
        calibration: a ``calibration.toml`` replacing CameraInfo and tf (``""``: none).
        depth_unit_m: metres per unit of ``16UC1`` depth (ROS: 0.001).
        max_depth_dt_s: largest |colour stamp - depth stamp| of a pair, seconds.
        ros_domain_id: live ``ros2:`` topics: the ROS domain (None: ``ROS_DOMAIN_ID``, else 0).
        ros_key_format: live ``ros2:`` topics: ``rmw_zenoh`` keys, or ``ros2dds``
            (zenoh-bridge-ros2dds); see :mod:`wardmap.edge.ros2live`.
        ros_stall_s: live ``ros2:`` topics: no colour image for this long (seconds) = lost.
    """

    rgb_topic: str = "/camera/color/image_raw"
    depth_topic: str = "/camera/aligned_depth_to_color/image_raw"
    camera_info_topic: str = "/camera/color/camera_info"
    odom_topic: str | None = None
    odom_frame: str = "odom"
    base_frame: str | None = None
    calibration: str = ""
    depth_unit_m: float = 0.001
    max_depth_dt_s: float = MAX_DEPTH_DT_S
    ros_domain_id: int | None = None
    ros_key_format: str = "rmw_zenoh"
    ros_stall_s: float = 5.0

    def __post_init__(self) -> None:
        for name in ("rgb_topic", "depth_topic"):
            if not getattr(self, name):
                raise ConfigError(f"source.{name} must name a topic")
        if not (math.isfinite(self.depth_unit_m) and self.depth_unit_m > 0):
            raise ConfigError(f"source.depth_unit_m must be > 0, got {self.depth_unit_m}")
        if not (math.isfinite(self.max_depth_dt_s) and self.max_depth_dt_s > 0):
            raise ConfigError(f"source.max_depth_dt_s must be > 0, got {self.max_depth_dt_s}")


def is_bag_source(spec: str | Path) -> bool:
    """True when ``spec`` names a ROS recording (``bag:PATH``)."""
    return isinstance(spec, str) and spec.startswith(SOURCE_PREFIX)


def import_rosbags() -> Any:
    """The rosbags modules the reader needs, or a ConfigError with the install hint."""
    try:
        from rosbags import highlevel, typesys
    except ImportError as exc:
        raise ConfigError(INSTALL_HINT) from exc
    return highlevel, typesys


def _msgtype(name: str) -> str:
    """``pkg/Type`` (ROS 1) or ``pkg/msg/Type`` -> ``pkg/msg/Type``."""
    pkg, _, rest = name.partition("/")
    return name if rest.startswith("msg/") else f"{pkg}/msg/{rest}"


def stamp_of(header: Any) -> float:
    """A ROS header's stamp in seconds, rounded to the microsecond."""
    return round(int(header.stamp.sec) + int(header.stamp.nanosec) * 1e-9, 6)


def _frame_id(name: str) -> str:
    return name.lstrip("/")


def _pose_matrix(position: Any, orientation: Any) -> F64:
    return transform_from_tum([position.x, position.y, position.z,
                               orientation.x, orientation.y, orientation.z, orientation.w])


# --------------------------------------------------------------------------- decoding


def _image_array(msg: Any, dtype: type, channels: int, what: str) -> NDArray[Any]:
    """The pixels of a ``sensor_msgs/Image`` as (H, W[, C]), honouring ``step`` and byte order."""
    h, w = int(msg.height), int(msg.width)
    item = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    row = w * channels * item.itemsize
    data = np.asarray(msg.data, np.uint8)
    if int(msg.step) < row or data.size < int(msg.step) * h:
        raise DatasetError(f"{what}: {msg.encoding} image {w}x{h} has step {msg.step} and "
                           f"{data.size} bytes; expected at least {row} per row")
    rows = data[: int(msg.step) * h].reshape(h, int(msg.step))[:, :row]
    out = np.ascontiguousarray(rows).view(item).reshape((h, w, channels) if channels > 1 else (h, w))
    return out.astype(np.dtype(dtype).newbyteorder("="), copy=False)


def decode_colour(msg: Any, msgtype: str, what: str) -> U8:
    """A colour ``Image`` or ``CompressedImage`` -> uint8 (H, W, 3) in RGB order.

    Raises:
        DatasetError: an encoding or format that is not colour (named in the message).
    """
    if msgtype == COMPRESSED:
        buf = np.asarray(msg.data, np.uint8)
        img = cv2.imdecode(buf, cv2.IMREAD_COLOR) if buf.size else None
        if img is None:
            raise DatasetError(f"{what}: cannot decode compressed image (format {msg.format!r})")
        return np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), np.uint8)
    enc = str(msg.encoding).lower()
    if enc in ("rgb8", "bgr8"):
        img = _image_array(msg, np.uint8, 3, what)
        return np.ascontiguousarray(img if enc == "rgb8" else img[:, :, ::-1])
    if enc in ("rgba8", "bgra8"):
        img = _image_array(msg, np.uint8, 4, what)[:, :, :3]
        return np.ascontiguousarray(img if enc == "rgba8" else img[:, :, ::-1])
    if enc == "mono8":
        return np.ascontiguousarray(np.repeat(_image_array(msg, np.uint8, 1, what)[:, :, None], 3, axis=2))
    raise DatasetError(f"{what}: colour encoding {msg.encoding!r} is not supported "
                       "(rgb8, bgr8, rgba8, bgra8, mono8, or a JPEG/PNG CompressedImage)")


def decode_depth(msg: Any, msgtype: str, depth_unit_m: float, what: str) -> F32:
    """A depth ``Image`` -> float32 (H, W) metres, 0 = no data.

    ``16UC1``/``mono16``: units of ``depth_unit_m`` (0 = no data); ``32FC1``: metres (NaN,
    inf and values <= 0 = no data).

    Raises:
        DatasetError: a compressed image or another encoding.
    """
    if msgtype != IMAGE:
        raise DatasetError(f"{what}: depth must be a raw sensor_msgs/Image (16UC1 or 32FC1), "
                           f"got {msgtype}")
    enc = str(msg.encoding).upper()
    if enc in ("16UC1", "MONO16"):
        raw = _image_array(msg, np.uint16, 1, what)
        return (raw.astype(np.float64) * depth_unit_m).astype(np.float32)
    if enc == "32FC1":
        d = _image_array(msg, np.float32, 1, what)
        return np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
    raise DatasetError(f"{what}: depth encoding {msg.encoding!r} is not supported (16UC1 or 32FC1)")


def camera_from_info(msg: Any, what: str) -> PinholeCamera:
    """A ``CameraInfo`` -> :class:`PinholeCamera` (``K`` and the first five of ``D``).

    Raises:
        DatasetError: no focal length, or a distortion model OpenCV's five terms cannot hold.
    """
    ros1 = hasattr(msg, "K")  # ROS 1 names the fields K and D
    k = [float(v) for v in (msg.K if ros1 else msg.k)]
    d = [float(v) for v in (msg.D if ros1 else msg.d)]
    model = str(msg.distortion_model)
    if model not in ("plumb_bob", "rational_polynomial", "") and any(d):
        raise DatasetError(f"{what}: distortion model {model!r} is not supported (plumb_bob, "
                           "rational_polynomial); give a calibration.toml instead")
    if model == "rational_polynomial" and any(d[5:]):
        log.warning("%s: rational_polynomial terms k4..k6 are ignored", what)
    d5 = (d + [0.0] * 5)[:5]
    try:
        return PinholeCamera(int(msg.width), int(msg.height), k[0], k[4], k[2], k[5],
                             (d5[0], d5[1], d5[2], d5[3], d5[4]))
    except Exception as exc:  # the camera's own validation (GeometryError, ValueError)
        raise DatasetError(f"{what}: not a usable camera: {exc}") from exc


def tf_chain(transforms: dict[str, tuple[str, F64]], parent: str, child: str) -> F64 | None:
    """``T_parent_child`` (4, 4) through a tf tree given as child -> (parent, T_parent_child), or None."""
    T = np.eye(4)
    frame = child
    for _ in range(len(transforms) + 1):
        if frame == parent:
            return T
        if frame not in transforms:
            return None
        up, T_up_frame = transforms[frame]
        T = T_up_frame @ T
        frame = up
    return None


# --------------------------------------------------------------------------- source


class BagSource:
    """A ROS recording as a :class:`~wardmap.edge.stream.StreamSource` (module docstring).

    Opening checks that the topics exist with the right types and reads the calibration
    (CameraInfo and tf, or the ``calibration.toml``); :meth:`events` reads the recording.

    Attributes:
        skipped: frames left out by reason (``unpaired``: no depth image near its stamp).
    """

    live = False

    def __init__(self, path: str | Path, config: BagSourceConfig | None = None) -> None:
        """Raises:
            DatasetError: the recording is missing or unreadable, a topic does not exist or
                has the wrong type, or there is no CameraInfo and no calibration.toml.
            ConfigError: rosbags is not installed.
        """
        self.path = Path(path)
        self.cfg = config or BagSourceConfig()
        self.name = f"{SOURCE_PREFIX}{self.path}"
        self.dataset: FrameSource | None = None
        self.frame_count: int | None = None
        self.skipped: Counter[str] = Counter()
        highlevel, typesys = import_rosbags()
        self._highlevel = highlevel
        self._typestore = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
        if not self.path.exists():
            raise DatasetError(f"recording not found: {self.path}")
        reader = self._open()
        try:
            topics = {c.topic: _msgtype(c.msgtype) for c in reader.connections}
            self._check_topic(topics, "rgb_topic", self.cfg.rgb_topic, (IMAGE, COMPRESSED))
            self._check_topic(topics, "depth_topic", self.cfg.depth_topic, (IMAGE,))
            odom = self.cfg.odom_topic
            if odom is None:
                tf_odom = TF_TOPIC if topics.get(TF_TOPIC) == TF else ""
                odom = "/odom" if topics.get("/odom") == ODOMETRY else tf_odom
            if odom:
                self._check_topic(topics, "odom_topic", odom, (ODOMETRY, TF))
            self._odom_is_tf = bool(odom) and topics[odom] == TF
            self.base_frame = self._base_frame(reader, odom)
            if self._odom_is_tf and not self._tf_has_odometry(reader, odom):
                if self.cfg.odom_topic is not None:
                    raise DatasetError(f"{self.path}: {odom} has no transform {self.cfg.odom_frame!r} -> "
                                       f"{self.base_frame!r} (odometry) in its first {TF_SCAN_MESSAGES} "
                                       "messages; set odom_frame / base_frame")
                odom = ""  # /tf without odometry: none
                self._odom_is_tf = False
            self._odom_topic = odom
            self.has_odometry = bool(odom)
            self.frame_count = sum(c.msgcount for c in reader.connections if c.topic == self.cfg.rgb_topic)
            self.calibration = self._calibration(reader, topics)
        finally:
            reader.close()

    def _open(self) -> Any:
        try:
            reader = self._highlevel.AnyReader([self.path], default_typestore=self._typestore)
            reader.open()
        except Exception as exc:  # rosbags raises its own error per format
            raise DatasetError(f"cannot read recording {self.path}: {exc}") from exc
        return reader

    def _check_topic(self, topics: dict[str, str], key: str, topic: str, types: Sequence[str]) -> None:
        if topic not in topics:
            listing = ", ".join(f"{t} ({m})" for t, m in sorted(topics.items())) or "none"
            raise DatasetError(f"{self.path} has no topic {topic!r} ({key}); its topics: {listing}")
        if topics[topic] not in types:
            raise DatasetError(f"{self.path}: topic {topic!r} ({key}) carries {topics[topic]}, "
                               f"expected {' or '.join(types)}")

    def _base_frame(self, reader: Any, odom_topic: str) -> str:
        if self.cfg.base_frame is not None:
            return _frame_id(self.cfg.base_frame)
        odo = self._first(reader, odom_topic) if odom_topic and not self._odom_is_tf else None
        return _frame_id(odo.child_frame_id) if odo is not None and odo.child_frame_id else "base_link"

    def _tf_has_odometry(self, reader: Any, topic: str) -> bool:
        conns = [c for c in reader.connections if c.topic == topic]
        for k, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
            if any(self._is_odometry(tr) for tr in reader.deserialize(raw, conn.msgtype).transforms):
                return True
            if k + 1 >= TF_SCAN_MESSAGES:
                break
        return False

    def _is_odometry(self, tr: Any) -> bool:
        """True for a tf transform odometry frame -> base frame."""
        return bool(_frame_id(tr.header.frame_id) == _frame_id(self.cfg.odom_frame)
                    and _frame_id(tr.child_frame_id) == self.base_frame)

    def _first(self, reader: Any, topic: str) -> Any | None:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:  # rosbags reads every topic when given none
            return None
        for conn, _, raw in reader.messages(connections=conns):
            return reader.deserialize(raw, conn.msgtype)
        return None

    def _calibration(self, reader: Any, topics: dict[str, str]) -> Calibration:
        if self.cfg.calibration:
            return load_calibration(self.cfg.calibration)
        info_topic = self.cfg.camera_info_topic
        info = self._first(reader, info_topic) if topics.get(info_topic) == CAMERA_INFO else None
        if info is None:
            raise DatasetError(
                f"{self.path} has no sensor_msgs/CameraInfo on {info_topic!r}, so the colour camera's "
                "intrinsics are unknown; name the topic (--camera-info-topic) or give a "
                "calibration.toml (--calibration)")
        camera = camera_from_info(info, f"{self.path} {info_topic}")
        cam_frame = _frame_id(info.header.frame_id)
        base = self.base_frame
        statics: dict[str, tuple[str, F64]] = {}
        conns = [c for c in reader.connections if c.topic == TF_STATIC_TOPIC and _msgtype(c.msgtype) == TF]
        for conn, _, raw in reader.messages(connections=conns) if conns else ():
            for tr in reader.deserialize(raw, conn.msgtype).transforms:
                T_parent_child = _pose_matrix(tr.transform.translation, tr.transform.rotation)
                statics[_frame_id(tr.child_frame_id)] = (_frame_id(tr.header.frame_id), T_parent_child)
        T_base_rgb = tf_chain(statics, base, cam_frame)
        if T_base_rgb is None and self.has_odometry:
            log.warning("%s: no %s transform from %r to the camera frame %r: wheel odometry cannot "
                        "be used (give a calibration.toml with [base] T_base_rgb)",
                        self.path, TF_STATIC_TOPIC, base, cam_frame)
        return Calibration(rgb=camera, T_base_rgb=T_base_rgb)

    @property
    def dropped_frames(self) -> int:
        """Colour images left out because no depth image paired with them."""
        return self.skipped["unpaired"]

    def events(self) -> Iterator[SourceEvent]:
        """Frames (colour paired with depth) and odometry, in the recording's order."""
        cfg = self.cfg
        topics = {cfg.rgb_topic, cfg.depth_topic} | ({self._odom_topic} if self._odom_topic else set())
        pairer = FramePairer(cfg, self.calibration, str(self.path))
        self.skipped = pairer.skipped
        reader = self._open()
        try:
            conns = [c for c in reader.connections if c.topic in topics]
            for conn, _, raw in reader.messages(connections=conns):
                msgtype = _msgtype(conn.msgtype)
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic == self._odom_topic and self._odom_is_tf:
                    for tr in msg.transforms:
                        if self._is_odometry(tr):
                            yield OdometrySample(stamp_of(tr.header), _pose_matrix(tr.transform.translation,
                                                                                   tr.transform.rotation))
                    continue
                if conn.topic == self._odom_topic:
                    yield odometry_sample(msg)
                    continue
                yield from pairer.add(conn.topic == cfg.rgb_topic, msg, msgtype)
            yield from pairer.finish()
        finally:
            reader.close()
        if self.skipped:
            log.warning("%s: frames left out: %s", self.name, dict(self.skipped))


def odometry_sample(msg: Any) -> OdometrySample:
    """A ``nav_msgs/Odometry`` -> its ``pose.pose`` as ``T_odom_base`` at its header stamp."""
    pose = msg.pose.pose
    return OdometrySample(stamp_of(msg.header), _pose_matrix(pose.position, pose.orientation))


class FramePairer:
    """Pairs colour and depth images by header stamp into :class:`Frame`\\ s (the rule of the
    module docstring: nearest depth within ``max_depth_dt_s``; a colour image without a partner
    waits until depth :data:`REORDER_S` past its window came, then is counted ``unpaired``).
    Used by the recording reader and the live ROS 2 source; one thread owns it.

    Attributes:
        skipped: frames left out by reason (``unpaired``).
    """

    def __init__(self, config: BagSourceConfig, calibration: Calibration, where: str) -> None:
        self.cfg = config
        self.calibration = calibration
        self.where = where
        self.skipped: Counter[str] = Counter()
        self._colour: list[tuple[float, Any, str]] = []  # (stamp, message, msgtype), sorted by stamp
        self._depth: list[tuple[float, Any, str]] = []
        self._index = 0

    def add(self, is_colour: bool, msg: Any, msgtype: str) -> Iterator[Frame | FrameProblem]:
        """Take one colour (or depth) message; yield the frames it settles."""
        pending = self._colour if is_colour else self._depth
        bisect.insort(pending, (stamp_of(msg.header), msg, msgtype), key=lambda e: e[0])
        if len(pending) > MAX_PENDING:
            pending.pop(0)
            self.skipped["unpaired"] += pending is self._colour
        yield from self._pairs(final=False)

    def finish(self) -> Iterator[Frame | FrameProblem]:
        """The source ended: pair what is left."""
        yield from self._pairs(final=True)

    def _pairs(self, *, final: bool) -> Iterator[Frame | FrameProblem]:
        """Pair the oldest colour images whose depth partner is settled (consumes both lists)."""
        colour, depth = self._colour, self._depth
        tol = self.cfg.max_depth_dt_s
        while colour:
            c_stamp = colour[0][0]
            near = [k for k, d in enumerate(depth) if abs(d[0] - c_stamp) <= tol]
            newest = depth[-1][0] if depth else -math.inf
            # settled: a partner at or after the colour stamp came (depth comes in stamp order, so
            # none nearer will: a camera's aligned depth, stamped like its colour, pairs at once),
            # or a depth image past the pairing window came, or, without a partner yet, one past
            # the window plus REORDER_S (a late partner may still come)
            at_or_after = any(depth[k][0] >= c_stamp for k in near)
            if not final and not at_or_after and newest <= c_stamp + tol + (0.0 if near else REORDER_S):
                return
            _, c_msg, c_type = colour.pop(0)
            if not near:
                self.skipped["unpaired"] += 1
                continue
            best = min(near, key=lambda k: (abs(depth[k][0] - c_stamp), k))
            _, d_msg, d_type = depth[best]
            del depth[: best + 1]
            yield self._frame(self._index, c_stamp, c_msg, c_type, d_msg, d_type)
            self._index += 1

    def _frame(self, index: int, stamp: float, c_msg: Any, c_type: str, d_msg: Any,
               d_type: str) -> Frame | FrameProblem:
        where = f"{self.where} at {stamp:.6f}"
        try:
            rgb = decode_colour(c_msg, c_type, f"{where} {self.cfg.rgb_topic}")
            depth_m = decode_depth(d_msg, d_type, self.cfg.depth_unit_m, f"{where} {self.cfg.depth_topic}")
        except DatasetError as exc:
            log.warning("%s", exc)
            return FrameProblem(stamp, str(exc))
        cam = self.calibration.rgb
        if rgb.shape[:2] != (cam.height, cam.width):
            raise DatasetError(f"{where}: colour image is {rgb.shape[1]}x{rgb.shape[0]} but the camera "
                               f"calibration says {cam.width}x{cam.height}")
        if depth_m.shape != rgb.shape[:2]:
            raise DatasetError(f"{where}: depth image is {depth_m.shape[1]}x{depth_m.shape[0]} but colour "
                               f"is {rgb.shape[1]}x{rgb.shape[0]}; the depth topic must be registered "
                               "to the colour camera (e.g. /camera/aligned_depth_to_color/image_raw)")
        return Frame(index=index, stamp=stamp, rgb=rgb, depth_m=depth_m, thermal_k=None, labels=None,
                     T_world_camera=None, depth_stamp=stamp_of(d_msg.header))

"""Convert between data-set folders and ROS recordings (``wardmap dataset to-bag / from-bag``).

:class:`BagWriter` writes colour, registered depth, the colour ``CameraInfo``, wheel odometry
(``nav_msgs/Odometry``) and the camera's mount (``/tf_static``) with the ``rosbags`` library,
on the topics :class:`~wardmap.edge.bag.BagSourceConfig` reads by default, so ``--source
bag:PATH`` reads what it wrote without options. The output kind follows the name: ``*.bag`` a
ROS 1 bag, ``*.mcap`` one MCAP file, anything else a ROS 2 bag folder (``storage`` sqlite3 or
mcap). :func:`bag_to_dataset` reads a recording with :class:`~wardmap.edge.bag.BagSource` and
writes our data-set layout (docs/dataset.md).
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Any, Final, Literal

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.edge.bag import INSTALL_HINT, BagSource, BagSourceConfig
from wardmap.edge.stream import FrameProblem, OdometrySample
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import DatasetReader, DatasetWriter, Frame
from wardmap.shared.errors import ConfigError, DatasetError
from wardmap.shared.se3 import transform_to_tum

log = logging.getLogger(__name__)

RgbFormat = Literal["raw", "png", "jpeg"]
DepthEncoding = Literal["32FC1", "16UC1"]
Storage = Literal["sqlite3", "mcap"]
CAMERA_FRAME: Final = "camera_color_optical_frame"
ODOM_FRAME: Final = "odom"
BASE_FRAME: Final = "base_link"


def _ns(stamp: float) -> int:
    """Seconds -> integer nanoseconds, exact for stamps given to the microsecond."""
    return round(stamp * 1e6) * 1000


class BagWriter:
    """Write a ROS recording (use as a context manager; see the module docstring).

    Messages are written with log time = their stamp unless ``log_stamp`` says otherwise (the
    tests record messages out of order that way).
    """

    def __init__(
        self, out: str | Path, *, topics: BagSourceConfig | None = None, rgb_format: RgbFormat = "raw",
        depth_encoding: DepthEncoding = "32FC1", storage: Storage = "sqlite3", overwrite: bool = False,
    ) -> None:
        """Raises:
            DatasetError: ``out`` exists (without ``overwrite``) or its folder does not.
            ConfigError: rosbags is not installed, or a bad format name.
        """
        try:
            from rosbags import rosbag1, rosbag2, typesys
        except ImportError as exc:
            raise ConfigError(INSTALL_HINT) from exc
        if rgb_format not in ("raw", "png", "jpeg"):
            raise ConfigError(f"rgb format must be raw, png or jpeg, got {rgb_format!r}")
        if depth_encoding not in ("32FC1", "16UC1"):
            raise ConfigError(f"depth encoding must be 32FC1 or 16UC1, got {depth_encoding!r}")
        if storage not in ("sqlite3", "mcap"):
            raise ConfigError(f"storage must be sqlite3 or mcap, got {storage!r}")
        self.out = Path(out)
        self.topics = topics or BagSourceConfig()
        self.rgb_format = rgb_format
        self.depth_encoding = depth_encoding
        if self.out.exists():
            if not overwrite:
                raise DatasetError(f"{self.out} exists; choose another name or remove it")
            shutil.rmtree(self.out) if self.out.is_dir() else self.out.unlink()
        if not self.out.parent.is_dir():
            raise DatasetError(f"folder {self.out.parent} does not exist")
        self._ros1 = self.out.suffix == ".bag"
        self._mcap_file = self.out.suffix == ".mcap"
        self._tmp: Path | None = None
        if self._ros1:
            self._ts = typesys.get_typestore(typesys.Stores.ROS1_NOETIC)
            # rosbags' ROS 1 store lacks tf2_msgs; its definition is one line
            self._ts.register(typesys.get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                         "tf2_msgs/msg/TFMessage"))
            self._writer: Any = rosbag1.Writer(self.out)
        else:
            self._ts = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
            mcap = storage == "mcap" or self._mcap_file
            plugin = rosbag2.StoragePlugin.MCAP if mcap else rosbag2.StoragePlugin.SQLITE3
            target = self.out
            if self._mcap_file:  # rosbags writes a bag folder; its one .mcap file is kept
                self._tmp = Path(tempfile.mkdtemp(prefix=".to-bag-", dir=self.out.parent))
                target = self._tmp / "bag"
            self._writer = rosbag2.Writer(target, version=9, storage_plugin=plugin)
        self._writer.open()
        self._conns: dict[str, Any] = {}

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Finish the recording (an ``.mcap`` output is moved into place)."""
        self._writer.close()
        if self._tmp is not None:
            files = sorted((self._tmp / "bag").glob("*.mcap"))
            if len(files) != 1:
                raise DatasetError(f"expected one .mcap file from rosbags, got {len(files)}")
            files[0].replace(self.out)
            shutil.rmtree(self._tmp)
            self._tmp = None

    # ------------------------------------------------------------------ messages

    def _t(self, name: str) -> Any:
        return self._ts.types[name]

    def _header(self, stamp: float, frame_id: str) -> Any:
        ns = _ns(stamp)
        time = self._t("builtin_interfaces/msg/Time")(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        if self._ros1:
            return self._t("std_msgs/msg/Header")(seq=0, stamp=time, frame_id=frame_id)
        return self._t("std_msgs/msg/Header")(stamp=time, frame_id=frame_id)

    def _write(self, topic: str, msg: Any, log_stamp: float) -> None:
        msgtype = msg.__msgtype__
        if topic not in self._conns:
            self._conns[topic] = self._writer.add_connection(topic, msgtype, typestore=self._ts)
        data = self._ts.serialize_ros1(msg, msgtype) if self._ros1 else self._ts.serialize_cdr(msg, msgtype)
        self._writer.write(self._conns[topic], _ns(log_stamp), data)

    def _image(self, stamp: float, pixels: NDArray[Any], encoding: str) -> Any:
        h, w = pixels.shape[:2]
        data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
        return self._t("sensor_msgs/msg/Image")(
            header=self._header(stamp, CAMERA_FRAME), height=h, width=w, encoding=encoding,
            is_bigendian=0, step=data.size // h, data=data)

    def write_camera_info(self, stamp: float, camera: PinholeCamera) -> None:
        """The colour camera's intrinsics (plumb_bob: OpenCV's k1 k2 p1 p2 k3)."""
        K = np.array([camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1], np.float64)
        P = np.array([camera.fx, 0, camera.cx, 0, 0, camera.fy, camera.cy, 0, 0, 0, 1, 0], np.float64)
        fields = {"D": np.array(camera.distortion, np.float64), "K": K, "R": np.eye(3).reshape(-1), "P": P}
        if not self._ros1:
            fields = {k.lower(): v for k, v in fields.items()}
        roi = self._t("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0,
                                                          do_rectify=False)
        msg = self._t("sensor_msgs/msg/CameraInfo")(
            header=self._header(stamp, CAMERA_FRAME), height=camera.height, width=camera.width,
            distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi, **fields)
        self._write(self.topics.camera_info_topic, msg, stamp)

    def write_frame(self, stamp: float, rgb: ArrayLike, depth_m: ArrayLike, *,
                    depth_stamp: float | None = None, log_stamp: float | None = None) -> None:
        """One colour image (uint8 (H, W, 3) RGB) and its registered depth ((H, W) metres, 0 = none)."""
        rgb_a = np.asarray(rgb, np.uint8)
        depth = np.asarray(depth_m, np.float32)
        log_t = stamp if log_stamp is None else log_stamp
        if self.rgb_format == "raw":
            colour = self._image(stamp, rgb_a, "rgb8")
        else:
            ext = ".png" if self.rgb_format == "png" else ".jpg"
            ok, buf = cv2.imencode(ext, cv2.cvtColor(rgb_a, cv2.COLOR_RGB2BGR))
            if not ok:
                raise DatasetError(f"cannot encode the colour image at {stamp:.6f} as {self.rgb_format}")
            colour = self._t("sensor_msgs/msg/CompressedImage")(
                header=self._header(stamp, CAMERA_FRAME), format=self.rgb_format,
                data=np.asarray(buf, np.uint8).reshape(-1))
        self._write(self.topics.rgb_topic, colour, log_t)
        d_stamp = stamp if depth_stamp is None else depth_stamp
        if self.depth_encoding == "32FC1":
            dmsg = self._image(d_stamp, depth, "32FC1")
        else:
            units = np.round(np.where(np.isfinite(depth) & (depth > 0), depth, 0) / self.topics.depth_unit_m)
            dmsg = self._image(d_stamp, np.clip(units, 0, 65535).astype(np.uint16), "16UC1")
        self._write(self.topics.depth_topic, dmsg, log_t)

    def write_odometry(self, stamp: float, T_odom_base: ArrayLike, *, log_stamp: float | None = None) -> None:
        """One wheel-odometry pose ``T_odom_base`` (4, 4) on the odometry topic."""
        t = self._t
        v = transform_to_tum(T_odom_base)
        pose = t("geometry_msgs/msg/Pose")(
            position=t("geometry_msgs/msg/Point")(x=v[0], y=v[1], z=v[2]),
            orientation=t("geometry_msgs/msg/Quaternion")(x=v[3], y=v[4], z=v[5], w=v[6]))
        zero = t("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.0)
        msg = t("nav_msgs/msg/Odometry")(
            header=self._header(stamp, ODOM_FRAME), child_frame_id=BASE_FRAME,
            pose=t("geometry_msgs/msg/PoseWithCovariance")(pose=pose, covariance=np.zeros(36)),
            twist=t("geometry_msgs/msg/TwistWithCovariance")(
                twist=t("geometry_msgs/msg/Twist")(linear=zero, angular=zero), covariance=np.zeros(36)))
        self._write(self.topics.odom_topic or "/odom", msg, stamp if log_stamp is None else log_stamp)

    def _tf(self, stamp: float, parent: str, child: str, T_parent_child: ArrayLike) -> Any:
        t = self._t
        v = transform_to_tum(T_parent_child)
        tr = t("geometry_msgs/msg/TransformStamped")(
            header=self._header(stamp, parent), child_frame_id=child,
            transform=t("geometry_msgs/msg/Transform")(
                translation=t("geometry_msgs/msg/Vector3")(x=v[0], y=v[1], z=v[2]),
                rotation=t("geometry_msgs/msg/Quaternion")(x=v[3], y=v[4], z=v[5], w=v[6])))
        return t("tf2_msgs/msg/TFMessage")(transforms=[tr])

    def write_tf_static(self, stamp: float, T_base_rgb: ArrayLike) -> None:
        """The colour camera's mount on the base (``base_link`` -> the camera frame)."""
        self._write("/tf_static", self._tf(stamp, BASE_FRAME, CAMERA_FRAME, T_base_rgb), stamp)

    def write_tf_odometry(self, stamp: float, T_odom_base: ArrayLike, *,
                          log_stamp: float | None = None) -> None:
        """One wheel-odometry pose as a ``/tf`` transform ``odom`` -> ``base_link``."""
        self._write("/tf", self._tf(stamp, ODOM_FRAME, BASE_FRAME, T_odom_base),
                    stamp if log_stamp is None else log_stamp)


def dataset_to_bag(dataset: str | Path, out: str | Path, *, rgb_format: RgbFormat = "raw",
                   depth_encoding: DepthEncoding = "32FC1", storage: Storage = "sqlite3",
                   max_frames: int | None = None, overwrite: bool = False,
                   progress: Callable[[int, int], None] | None = None) -> dict[str, Any]:
    """Write the frames (colour + depth pairs), odometry, intrinsics and mount of a data-set folder
    to a ROS recording; return a summary. Thermal images, labels and ground truth are not written.
    """
    reader = DatasetReader(dataset)
    n = len(reader) if max_frames is None else min(max_frames, len(reader))
    if n <= 0:
        raise DatasetError(f"--max-frames must be positive, got {max_frames}")
    calib = reader.calibration
    if calib.readout.readout_s > 0 or calib.thermal is not None:
        log.info("%s: readout time and thermal camera are not written to the recording", dataset)
    odo = reader.odometry()
    last = float(reader.stamps[n - 1])
    n_odo = 0
    with BagWriter(out, rgb_format=rgb_format, depth_encoding=depth_encoding, storage=storage,
                   overwrite=overwrite) as w:
        first = float(reader.stamps[0])
        w.write_camera_info(first, calib.rgb)
        if calib.T_base_rgb is not None:
            w.write_tf_static(first, calib.T_base_rgb)
        events: list[tuple[float, int, int]] = [(float(s), 1, i) for i, s in enumerate(reader.stamps[:n])]
        if odo is not None:
            # odometry up to one sample past the last frame (its pose is interpolated)
            past = np.flatnonzero(odo[0] > last)
            end = int(past[0]) + 1 if past.size else len(odo[0])
            events += [(float(s), 0, k) for k, s in enumerate(odo[0][:end])]
        for stamp, kind, i in sorted(events):
            if kind == 0 and odo is not None:
                w.write_odometry(stamp, odo[1][i])
                n_odo += 1
                continue
            frame: Frame = reader.frame(i)
            w.write_frame(frame.stamp, frame.rgb, frame.depth_m, depth_stamp=frame.depth_stamp)
            if progress is not None:
                progress(i + 1, n)
    return {"out": str(out), "frames": n, "odometry": n_odo, "rgb": rgb_format, "depth": depth_encoding,
            "tf_static": calib.T_base_rgb is not None}


def bag_to_dataset(
    bag: str | Path, out: str | Path, *, config: BagSourceConfig | None = None, overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Read a ROS recording and write our data-set layout to ``out``; return a summary.

    Frames come in the recording's order; one older than the frame before it is left out and
    counted (``late``), as are unusable ones (``bad``) and colour images without depth
    (``unpaired``). Odometry is written sorted by stamp (``odometry.txt``).
    """
    source = BagSource(bag, config)
    odo: dict[float, NDArray[np.float64]] = {}
    late = bad = written = 0
    last: float | None = None
    total = source.frame_count or 0
    with DatasetWriter(out, source.calibration, overwrite=overwrite) as w:
        for ev in source.events():
            if isinstance(ev, OdometrySample):
                odo[round(ev.stamp, 6)] = ev.T_odom_base
                continue
            if isinstance(ev, FrameProblem):
                bad += 1
                continue
            if last is not None and round(ev.stamp, 6) <= last:
                late += 1
                log.warning("frame %.6f comes after %.6f: left out", ev.stamp, last)
                continue
            w.write_frame(ev.stamp, ev.rgb, ev.depth_m)
            last = round(ev.stamp, 6)
            written += 1
            if progress is not None:
                progress(written, total)
        if odo:
            stamps = sorted(odo)
            w.write_odometry(np.array(stamps), np.stack([odo[s] for s in stamps]))
    if written == 0:
        raise DatasetError(f"{bag}: no frame could be read (colour and depth never paired)")
    return {"out": str(out), "frames": written, "odometry": len(odo), "late": late, "bad": bad,
            **{k: v for k, v in source.skipped.items()}}

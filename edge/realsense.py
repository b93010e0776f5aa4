"""Intel RealSense cameras as a live source (``--source realsense[:SERIAL]``), with pyrealsense2.

pyrealsense2 is the optional extra ``realsense`` (``pip install 'wardmap[realsense]'``),
imported only when this source is chosen. What the source takes from the SDK:

- colour ``rgb8`` and depth ``z16`` at ``width`` x ``height`` and ``fps`` (default 640x480 at
  30 Hz), depth aligned to the colour camera with ``rs.align`` (same size, same pixels as the
  colour image: the registration the tracker needs);
- intrinsics of the colour stream (after alignment the depth has them too): ``fx fy ppx ppy``
  and, for the Brown-Conrady model, OpenCV's ``k1 k2 p1 p2 k3`` (other models with non-zero
  coefficients: a warning, the coefficients are dropped);
- the depth scale (metres per ``z16`` unit) from the depth sensor's ``depth_units``;
- stamps: each frame's timestamp (milliseconds -> seconds) in the domain the device gives:
  ``global_time`` (the camera's hardware clock mapped to the host clock; librealsense's default
  on D400 cameras, comparable with odometry stamped on the host) or ``hardware_clock`` /
  ``system_time`` (logged once at connect when not global time).

A frame set without both images is skipped and counted (``incomplete``). No frame for
:data:`STALL_S` seconds, or an SDK error while waiting, is :class:`~wardmap.edge.live.SourceLostError`:
the daemon reconnects (:class:`~wardmap.edge.live.ReconnectingSource`). The camera has no
odometry; the robot mount ``T_base_rgb`` comes from a ``calibration.toml`` ``[base]`` table when
given (its ``[rgb]`` table is replaced by the device's intrinsics).

:class:`RealSenseSource` turns any SDK frame-set poller into frames: a real camera's
``rs.pipeline`` (:func:`realsense_connector`), or in tests the SDK's own ``rs.software_device``
behind an ``rs.syncer``.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any, Final

import numpy as np

from wardmap.edge.live import Connector, PolledCamera, SourceLostError
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import Calibration, Frame
from wardmap.shared.errors import ConfigError, DatasetError

log = logging.getLogger(__name__)

SOURCE_PREFIX: Final = "realsense"
INSTALL_HINT: Final = "--source realsense needs pyrealsense2: pip install 'wardmap[realsense]'"
STALL_S: Final = 3.0
"""No frame set for this long (seconds) means the camera is gone."""
POLL_MS: Final = 200
"""Longest single wait for a frame set, milliseconds (a stop request is seen this soon)."""

Poll = Callable[[int], tuple[bool, Any]]
"""``poll(timeout_ms) -> (ok, frameset)``: ``rs.pipeline.try_wait_for_frames`` or ``rs.syncer``'s."""


def import_pyrealsense2() -> Any:
    """The ``pyrealsense2`` module, or a ConfigError with the install hint."""
    try:
        import pyrealsense2
    except ImportError as exc:
        raise ConfigError(INSTALL_HINT) from exc
    return pyrealsense2


def camera_from_intrinsics(rs: Any, intr: Any) -> PinholeCamera:
    """An ``rs.intrinsics`` -> :class:`PinholeCamera` (Brown-Conrady coefficients kept)."""
    coeffs = [float(c) for c in intr.coeffs][:5]
    if intr.model != rs.distortion.brown_conrady and any(coeffs):
        log.warning("RealSense colour distortion %s is not OpenCV's model: its coefficients are "
                    "ignored", intr.model)
        coeffs = [0.0] * 5
    c = (coeffs + [0.0] * 5)[:5]
    return PinholeCamera(int(intr.width), int(intr.height), float(intr.fx), float(intr.fy),
                         float(intr.ppx), float(intr.ppy), (c[0], c[1], c[2], c[3], c[4]))


class RealSenseSource(PolledCamera):
    """One connection to a RealSense device (or software device): a live
    :class:`~wardmap.edge.stream.StreamSource` whose events end when ``stop`` is set.

    Attributes:
        skipped: frame sets not turned into frames, by reason (``incomplete``).
    """

    def __init__(self, name: str, poll: Poll, calibration: Calibration, depth_units_m: float,
                 stop: threading.Event, *, close: Callable[[], None] | None = None,
                 stall_s: float = STALL_S) -> None:
        """Args:
            poll: gives the device's frame sets (see :data:`Poll`).
            calibration: its ``rgb`` camera is the colour stream's intrinsics.
            depth_units_m: metres per ``z16`` unit.
            close: releases the device (``pipeline.stop``); called when the events end.
        """
        super().__init__(name, calibration, stop, close=close, stall_s=stall_s)
        self._rs = import_pyrealsense2()
        self.depth_units_m = float(depth_units_m)
        self._poll = poll
        self._align = self._rs.align(self._rs.stream.color)

    def poll(self) -> Any:
        ok, frames = self._poll(POLL_MS)  # RuntimeError: the SDK's error for a device that went away
        return frames if ok else None

    def frame(self, frames: Any) -> Frame | None:
        """One SDK frame set -> a :class:`Frame` (depth aligned to colour), or None when it lacks
        an image (counted in ``skipped``)."""
        aligned = self._align.process(frames.as_frameset())
        colour, depth = aligned.get_color_frame(), aligned.get_depth_frame()
        if not colour or not depth:
            self.skipped["incomplete"] += 1
            return None
        rgb = np.array(np.asanyarray(colour.get_data()), np.uint8)  # a copy: the SDK reuses its buffer
        if colour.profile.format() == self._rs.format.bgr8:
            rgb = np.ascontiguousarray(rgb[:, :, ::-1])
        depth_m = (np.asanyarray(depth.get_data()).astype(np.float32) * np.float32(self.depth_units_m))
        cam = self.calibration.rgb
        if rgb.shape != (cam.height, cam.width, 3) or depth_m.shape != (cam.height, cam.width):
            raise DatasetError(f"{self.name}: frame {rgb.shape[1]}x{rgb.shape[0]} (depth "
                               f"{depth_m.shape[1]}x{depth_m.shape[0]}) but the colour stream is "
                               f"{cam.width}x{cam.height}")
        if self._index == 0 and colour.get_frame_timestamp_domain() != self._rs.timestamp_domain.global_time:
            log.warning("%s: frame stamps are in %s, not global_time: odometry stamped on the host "
                        "may not line up with them", self.name, colour.get_frame_timestamp_domain())
        out = Frame(index=self._index, stamp=round(colour.get_timestamp() * 1e-3, 6), rgb=rgb,
                    depth_m=depth_m, thermal_k=None, labels=None, T_world_camera=None,
                    depth_stamp=round(depth.get_timestamp() * 1e-3, 6))
        self._index += 1
        return out


def parse_spec(spec: str) -> str | None:
    """``realsense`` -> None (the first camera); ``realsense:SERIAL`` -> the serial number."""
    serial = spec.removeprefix(SOURCE_PREFIX).removeprefix(":")
    return serial or None


def realsense_connector(serial: str | None, *, width: int = 640, height: int = 480, fps: int = 30,
                        calibration: Calibration | None = None) -> Connector:
    """A connector (:class:`~wardmap.edge.live.ReconnectingSource`) opening a RealSense camera.

    ``calibration``: its ``T_base_rgb`` (and thermal camera) are kept; the colour intrinsics and
    depth scale always come from the device.
    """
    rs = import_pyrealsense2()

    def connect(stop: threading.Event) -> RealSenseSource:
        ctx = rs.context()
        found = [d.get_info(rs.camera_info.serial_number) for d in ctx.query_devices()]
        if not found:
            raise SourceLostError("no RealSense camera is connected")
        if serial is not None and serial not in found:
            raise SourceLostError(f"RealSense {serial} is not connected (connected: {', '.join(found)})")
        chosen = serial or found[0]
        pipe = rs.pipeline(ctx)
        cfg = rs.config()
        cfg.enable_device(chosen)
        cfg.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
        cfg.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
        try:
            profile = pipe.start(cfg)
        except RuntimeError as exc:
            raise SourceLostError(f"cannot start RealSense {chosen} at {width}x{height} {fps} Hz: "
                                  f"{exc}") from exc
        try:
            depth_units = profile.get_device().first_depth_sensor().get_depth_scale()
            intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
            camera = camera_from_intrinsics(rs, intr)
        except Exception:
            pipe.stop()
            raise
        return RealSenseSource(f"realsense:{chosen}", pipe.try_wait_for_frames,
                               _with_camera(calibration, camera), depth_units, stop, close=pipe.stop)

    return connect


def _with_camera(calibration: Calibration | None, camera: PinholeCamera) -> Calibration:
    """``calibration`` (or none) with its colour camera replaced by the device's."""
    if calibration is None:
        return Calibration(rgb=camera)
    import dataclasses

    return dataclasses.replace(calibration, rgb=camera)

"""Orbbec cameras as a live source (``--source orbbec[:N]``), with Orbbec SDK v2's Python bindings.

The bindings are the ``pyorbbecsdk2`` wheel, which bundles the SDK, installed by hand with
``pip install --no-deps 'pyorbbecsdk2>=2.1'`` (no extra: the wheel declares numpy < 2 and its
examples' packages, which would break this install; the older ``pyorbbecsdk`` 1.x wheel on the
index holds macOS binaries only); imported only when this source is chosen. What the source takes from
the SDK:

- the colour stream at ``width`` x ``height`` and ``fps`` (default 640x480 at 30 Hz) in ``RGB``,
  ``BGR`` or ``MJPG`` (decoded here), the first the camera offers; depth (``Y16``) registered
  to the colour camera by the pipeline's depth-to-colour alignment, in hardware when the camera
  offers a matching depth profile (``get_d2c_depth_profile_list``), else in the SDK's software;
  framesets only with both images (``FULL_FRAME_REQUIRE``), frame sync on;
- intrinsics of the colour profile (``fx fy cx cy``) and, for the Brown-Conrady models, OpenCV's
  ``k1 k2 p1 p2 k3`` (``k4..k6`` of the rational model and other models: a warning, dropped);
- the depth scale of each depth frame (``get_depth_scale``: millimetres per unit);
- stamps: each frame's global timestamp (the device clock mapped to the host's) when the device
  gives one, else the host's time of arrival (``system`` timestamp; logged once): both on the host
  clock, comparable with odometry stamped there. The device's own clock is not used.

A frameset without both images is skipped and counted (``incomplete``). No frameset for
:data:`STALL_S` seconds, or an SDK error while waiting, is :class:`~wardmap.edge.live.SourceLostError`:
the daemon reconnects (:class:`~wardmap.edge.live.ReconnectingSource`). The camera has no
odometry; the robot mount ``T_base_rgb`` comes from a ``calibration.toml`` ``[base]`` table when
given (its ``[rgb]`` table is replaced by the device's intrinsics).

:class:`OrbbecSource` turns any frameset poller into frames: a camera's ``Pipeline``
(:func:`orbbec_connector`), or in tests framesets the SDK builds in software
(``FrameSet.create_video_frame``).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
import threading
from collections.abc import Callable
from typing import Any, Final

import cv2
import numpy as np

from wardmap.edge.live import Connector, PolledCamera, SourceLostError
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import Calibration, Frame
from wardmap.shared.errors import ConfigError, DatasetError

log = logging.getLogger(__name__)

SOURCE_PREFIX: Final = "orbbec"
INSTALL_HINT: Final = ("--source orbbec needs Orbbec SDK v2's bindings: pip install --no-deps "
                       "'pyorbbecsdk2>=2.1' (docs/sources.md)")
STALL_S: Final = 3.0
"""No frameset for this long (seconds) means the camera is gone."""
POLL_MS: Final = 200
"""Longest single wait for a frameset, milliseconds (a stop request is seen this soon)."""
COLOUR_FORMATS: Final = ("RGB", "BGR", "MJPG")
"""Colour formats asked for, in this order."""

Poll = Callable[[int], Any]
"""``poll(timeout_ms) -> FrameSet | None``: ``Pipeline.wait_for_frames``."""


def import_pyorbbecsdk() -> Any:
    """The ``pyorbbecsdk`` module, or a ConfigError with the install hint.

    The SDK prints a banner ("load extensions from ...") on standard output when loaded
    (discarded here: our commands' output and one-line errors stay theirs) and by default writes
    a log folder into the working directory (turned off: its console messages stay)."""
    module: Any = sys.modules.get("pyorbbecsdk")
    if module is None:
        sys.stdout.flush()
        saved, null = os.dup(1), os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(null, 1)
            import pyorbbecsdk

            module = pyorbbecsdk
        except ImportError as exc:
            raise ConfigError(INSTALL_HINT) from exc
        finally:
            os.dup2(saved, 1)
            os.close(saved)
            os.close(null)
    module.Context.set_logger_to_file(module.OBLogLevel.NONE, "")
    return module


def camera_from_profile(ob: Any, intr: Any, dist: Any) -> PinholeCamera:
    """An ``OBCameraIntrinsic`` and ``OBCameraDistortion`` -> :class:`PinholeCamera`."""
    coeffs = [float(dist.k1), float(dist.k2), float(dist.p1), float(dist.p2), float(dist.k3)]
    model = dist.model
    brown = (ob.OBCameraDistortionModel.BROWN_CONRADY, ob.OBCameraDistortionModel.BROWN_CONRADY_K6)
    if model not in brown and any(coeffs):
        log.warning("Orbbec colour distortion %s is not OpenCV's model: its coefficients are ignored", model)
        coeffs = [0.0] * 5
    elif any(float(getattr(dist, k)) for k in ("k4", "k5", "k6")):
        log.warning("Orbbec colour distortion: the rational terms k4..k6 are ignored")
    c = coeffs
    return PinholeCamera(int(intr.width), int(intr.height), float(intr.fx), float(intr.fy),
                         float(intr.cx), float(intr.cy), (c[0], c[1], c[2], c[3], c[4]))


class OrbbecSource(PolledCamera):
    """One connection to an Orbbec camera (or software framesets): a live
    :class:`~wardmap.edge.stream.StreamSource` whose events end when ``stop`` is set.

    Attributes:
        skipped: framesets not turned into frames, by reason (``incomplete``, ``undecodable``).
    """

    def __init__(self, name: str, poll: Poll, calibration: Calibration, stop: threading.Event, *,
                 close: Callable[[], None] | None = None, stall_s: float = STALL_S) -> None:
        """Args:
            poll: gives the camera's framesets (see :data:`Poll`).
            calibration: its ``rgb`` camera is the colour stream's intrinsics.
            close: releases the camera (``Pipeline.stop``); called when the events end.
        """
        super().__init__(name, calibration, stop, close=close, stall_s=stall_s)
        self._ob = import_pyorbbecsdk()
        self._poll = poll
        self.errors = (RuntimeError, self._ob.OBError)
        self._arrival_stamps = False  # said once: the device gives no global timestamps

    def poll(self) -> Any:
        return self._poll(POLL_MS)

    def frame(self, frames: Any) -> Frame | None:
        """One SDK frameset (depth registered to colour) -> a :class:`Frame`, or None when it
        lacks an image or its colour image does not decode (counted in ``skipped``).

        Raises:
            DatasetError: images of another size than the colour stream's intrinsics.
        """
        colour, depth = frames.get_color_frame(), frames.get_depth_frame()
        if colour is None or depth is None:
            self.skipped["incomplete"] += 1
            return None
        rgb = self._rgb(colour)
        if rgb is None:
            self.skipped["undecodable"] += 1
            return None
        h, w = int(depth.get_height()), int(depth.get_width())
        units = np.frombuffer(depth.get_data(), np.uint16, count=w * h).reshape(h, w)
        depth_m = units.astype(np.float32) * np.float32(depth.get_depth_scale() * 1e-3)
        cam = self.calibration.rgb
        if rgb.shape != (cam.height, cam.width, 3) or depth_m.shape != (cam.height, cam.width):
            raise DatasetError(f"{self.name}: frame {rgb.shape[1]}x{rgb.shape[0]} (depth {w}x{h}) but "
                               f"the colour stream is {cam.width}x{cam.height}")
        out = Frame(index=self._index, stamp=self._stamp(colour), rgb=rgb, depth_m=depth_m, thermal_k=None,
                    labels=None, T_world_camera=None, depth_stamp=self._stamp(depth))
        self._index += 1
        return out

    def _rgb(self, colour: Any) -> np.ndarray | None:
        """(H, W, 3) uint8 RGB, a copy (the SDK reuses its buffers); None when MJPG does not decode."""
        fmt, ob = colour.get_format(), self._ob
        data = np.frombuffer(colour.get_data(), np.uint8)
        if fmt == ob.OBFormat.MJPG:
            bgr = cv2.imdecode(data, cv2.IMREAD_COLOR)
            return None if bgr is None else np.ascontiguousarray(bgr[:, :, ::-1])
        h, w = int(colour.get_height()), int(colour.get_width())
        if fmt not in (ob.OBFormat.RGB, ob.OBFormat.BGR) or data.size < w * h * 3:
            raise DatasetError(f"{self.name}: colour format {fmt} ({data.size} bytes for {w}x{h}): "
                               f"expected one of {', '.join(COLOUR_FORMATS)}")
        img = data[: w * h * 3].reshape(h, w, 3)
        return np.ascontiguousarray(img[:, :, ::-1]) if fmt == ob.OBFormat.BGR else img.copy()

    def _stamp(self, frame: Any) -> float:
        """Seconds on the host clock: the global timestamp, else the time of arrival."""
        us = int(frame.get_global_timestamp_us())
        if us <= 0:
            if not self._arrival_stamps:
                self._arrival_stamps = True
                log.warning("%s: no global timestamps: frames are stamped on arrival at the host",
                            self.name)
            us = int(frame.get_system_timestamp_us())
        return round(us * 1e-6, 6)


def parse_spec(spec: str) -> int:
    """``orbbec`` -> 0 (the first camera); ``orbbec:N`` -> N.

    Raises:
        ConfigError: N is not a camera index (an integer >= 0).
    """
    text = spec.removeprefix(SOURCE_PREFIX).removeprefix(":")
    if not text:
        return 0
    if not text.isdigit():
        raise ConfigError(f"--source {spec!r}: expected orbbec or orbbec:N (N a camera index: 0, 1, ...)")
    return int(text)


def orbbec_connector(index: int, *, width: int = 640, height: int = 480, fps: int = 30,
                     calibration: Calibration | None = None) -> Connector:
    """A connector (:class:`~wardmap.edge.live.ReconnectingSource`) opening the ``index``-th
    Orbbec camera.

    ``calibration``: its ``T_base_rgb`` (and thermal camera) are kept; the colour intrinsics always
    come from the camera.
    """
    ob = import_pyorbbecsdk()
    errors = (RuntimeError, ob.OBError)

    def connect(stop: threading.Event) -> OrbbecSource:
        try:
            devices = ob.Context().query_devices()
            n = devices.get_count()
            if index >= n:
                raise SourceLostError("no Orbbec camera is connected" if n == 0 else
                                      f"Orbbec camera {index} is not connected ({n} connected)")
            device = devices.get_device_by_index(index)
            serial = device.get_device_info().get_serial_number()
            pipe = ob.Pipeline(device)
        except errors as exc:
            raise SourceLostError(f"cannot open Orbbec camera {index}: {exc}") from exc
        try:
            config, colour, mode = _configure(ob, pipe, width, height, fps)
            pipe.enable_frame_sync()
            pipe.start(config)
        except errors as exc:
            raise SourceLostError(f"cannot start Orbbec camera {index} ({serial}) at {width}x{height} "
                                  f"{fps} Hz: {exc}") from exc
        try:
            camera = camera_from_profile(ob, colour.get_intrinsic(), colour.get_distortion())
        except Exception:
            pipe.stop()
            raise
        log.info("Orbbec camera %d (%s): colour %s, depth aligned in %s", index, serial,
                 colour.get_format(), mode)
        calib = (Calibration(rgb=camera) if calibration is None
                 else dataclasses.replace(calibration, rgb=camera))
        return OrbbecSource(f"orbbec:{index}", pipe.wait_for_frames, calib, stop, close=pipe.stop)

    return connect


def _configure(ob: Any, pipe: Any, width: int, height: int, fps: int) -> tuple[Any, Any, str]:
    """The pipeline's config (colour + depth registered to it), the colour profile, and where the
    alignment runs (``hardware`` or ``software``)."""
    colours = pipe.get_stream_profile_list(ob.OBSensorType.COLOR_SENSOR)
    colour = None
    for name in COLOUR_FORMATS:
        try:
            colour = colours.get_video_stream_profile(width, height, getattr(ob.OBFormat, name), fps)
            break
        except (RuntimeError, ob.OBError):
            continue
    if colour is None:
        raise RuntimeError(f"no {'/'.join(COLOUR_FORMATS)} colour profile at {width}x{height} {fps} Hz")
    config = ob.Config()
    config.enable_stream(colour)
    hw = pipe.get_d2c_depth_profile_list(colour, ob.OBAlignMode.HW_MODE)
    if hw.get_count() > 0:
        config.enable_stream(hw.get_stream_profile_by_index(0))
        config.set_align_mode(ob.OBAlignMode.HW_MODE)
        mode = "hardware"
    else:
        depths = pipe.get_stream_profile_list(ob.OBSensorType.DEPTH_SENSOR)
        config.enable_stream(depths.get_video_stream_profile(0, 0, ob.OBFormat.Y16, fps))
        config.set_align_mode(ob.OBAlignMode.SW_MODE)
        mode = "software"
    config.set_frame_aggregate_output_mode(ob.OBFrameAggregateOutputMode.FULL_FRAME_REQUIRE)
    return config, colour, mode

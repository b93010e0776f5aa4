"""A UVC thermal camera next to the colour camera (``--thermal INDEX``), read with OpenCV.

Meant for a FLIR Lepton on a PureThermal board (or any UVC camera that sends 16-bit radiometric
``Y16`` frames): OpenCV opens video device ``INDEX`` with FOURCC ``Y16`` and RGB conversion off,
so each frame is the raw (h, w) uint16 image; with the Lepton's TLinear radiometry (PureThermal's
default) a unit is 0.01 K (``unit_k``). The thermal camera's intrinsics and its pose in the
colour camera ``T_rgb_thermal`` come from the ``[thermal]`` table of a ``calibration.toml``
(docs/dataset.md); the tracker uses thermal as its fallback when colour fails
(docs/decisions/0028), and the agent sends thermal rasters with keyframes.

:class:`ThermalCapture` reads frames on its own thread (the capture blocks at the camera's
~9 Hz) and keeps only the newest, stamped with the host clock when read (``time.time()``).
:class:`WithThermal` wraps a colour+depth source and gives each frame the newest thermal image
when it is within :data:`~wardmap.shared.dataset.MAX_THERMAL_DT_S` of the frame's stamp (so the
colour source's stamps must be host time: a RealSense camera's ``global_time``, a ROS header
stamped on the robot's clock); otherwise the frame goes without thermal. A thermal camera that
stops delivering is logged once and the frames go on without it.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.edge.stream import SourceEvent, StreamSource
from wardmap.shared.dataset import MAX_THERMAL_DT_S, Calibration, Frame
from wardmap.shared.errors import DatasetError

log = logging.getLogger(__name__)

F32 = NDArray[np.float32]

DEFAULT_UNIT_K: Final = 0.01
"""Kelvin per raw unit of a radiometric Lepton (TLinear, high gain)."""
READ_FAIL_LIMIT: Final = 10
"""Consecutive failed reads after which the capture is reported lost (logged once)."""

OpenCapture = Callable[[int], Any]
"""Opens a capture like ``cv2.VideoCapture(index, cv2.CAP_V4L2)`` (a fake one in unit tests)."""


def _open_v4l2(index: int) -> Any:
    return cv2.VideoCapture(index, cv2.CAP_V4L2)


class ThermalCapture:
    """The newest thermal image of a UVC camera (module docstring); a context manager whose
    reader thread starts on enter and stops on exit.

    Attributes:
        frames: images read so far.
    """

    def __init__(self, index: int, camera_size: tuple[int, int], *, unit_k: float = DEFAULT_UNIT_K,
                 open_capture: OpenCapture = _open_v4l2) -> None:
        """Args:
            camera_size: (width, height) the calibration's thermal camera has.

        Raises:
            DatasetError: the device cannot be opened or gives frames of another size or type.
        """
        self.index = index
        self.unit_k = unit_k
        self.frames = 0
        self._size = camera_size
        cap = open_capture(index)
        if cap is None or not cap.isOpened():
            raise DatasetError(f"cannot open thermal camera /dev/video{index} (is it plugged in, "
                               "and is the user in the video group?)")
        cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc("Y", "1", "6", " "))
        cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
        self._cap = cap
        self._latest: tuple[float, F32] | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        first = self._read()
        if first is None:
            cap.release()
            raise DatasetError(f"thermal camera /dev/video{index} gives no 16-bit frames of "
                               f"{camera_size[0]}x{camera_size[1]} (calibration [thermal]); is it in "
                               "Y16 mode?")
        self._latest = first

    def _read(self) -> tuple[float, F32] | None:
        if self._cap is None:
            return None
        ok, raw = self._cap.read()
        w, h = self._size
        if not ok or raw is None:
            return None
        raw = np.asarray(raw)
        if raw.dtype != np.uint16 or raw.reshape(-1).size != w * h:
            return None
        self.frames += 1
        return time.time(), (raw.reshape(h, w).astype(np.float32) * np.float32(self.unit_k))

    def __enter__(self) -> ThermalCapture:
        self._thread = threading.Thread(target=self._run, name="thermal-capture", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        self.release()

    def release(self) -> None:
        """Close the device (idempotent; the reader thread must have stopped)."""
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    def _run(self) -> None:
        failures = 0
        while not self._stop.is_set():
            got = self._read()
            if got is None:
                failures += 1
                if failures == READ_FAIL_LIMIT:
                    log.warning("thermal camera /dev/video%d stopped delivering frames", self.index)
                self._stop.wait(0.05)
                continue
            if failures >= READ_FAIL_LIMIT:
                log.warning("thermal camera /dev/video%d is back", self.index)
            failures = 0
            with self._lock:
                self._latest = got

    def latest(self) -> tuple[float, F32] | None:
        """``(stamp, kelvin (h, w))`` of the newest image, or None."""
        with self._lock:
            return self._latest


class WithThermal:
    """``source``'s events, each frame given the capture's newest thermal image when close in
    time (module docstring). Its calibration is the source's with the thermal camera of
    ``thermal_calibration`` (which must have one)."""

    def __init__(self, source: StreamSource, capture: ThermalCapture,
                 thermal_calibration: Calibration) -> None:
        if thermal_calibration.thermal is None:
            raise DatasetError("--thermal needs a calibration.toml with a [thermal] table (the thermal "
                               "camera's intrinsics and T_rgb_thermal)")
        self._source = source
        self._capture = capture
        self.name = f"{source.name}+thermal:{capture.index}"
        self.calibration = dataclasses.replace(
            source.calibration, thermal=thermal_calibration.thermal,
            T_rgb_thermal=thermal_calibration.T_rgb_thermal, thermal_scale=thermal_calibration.thermal_scale)
        self.live = source.live
        self.has_odometry = source.has_odometry
        self.frame_count = source.frame_count
        self.dataset = source.dataset
        self.with_thermal = 0

    def stop(self) -> None:
        """Forward to the inner source's ``stop`` when it has one."""
        stop = getattr(self._source, "stop", None)
        if stop is not None:
            stop()

    def __getattr__(self, name: str) -> object:  # counters of the inner source (reconnects, up)
        return getattr(self._source, name)

    def close(self) -> None:
        """Close the inner source when it can be closed, and release the thermal camera."""
        close = getattr(self._source, "close", None)
        if callable(close):
            close()
        self._capture.release()

    def events(self) -> Iterator[SourceEvent]:
        """See :meth:`StreamSource.events`; the capture runs while they are read."""
        with self._capture:
            for event in self._source.events():
                if isinstance(event, Frame):
                    latest = self._capture.latest()
                    if latest is not None and abs(latest[0] - event.stamp) < MAX_THERMAL_DT_S:
                        event = dataclasses.replace(event, thermal_k=latest[1],
                                                    thermal_stamp=round(latest[0], 6))
                        self.with_thermal += 1
                yield event

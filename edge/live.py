"""Live sources for the daemon: reconnect when the camera goes away, and record what it sees.

:class:`ReconnectingSource` wraps a *connector* (``connect(stop) -> StreamSource``: a camera
driver or a ROS 2 subscription; see :mod:`wardmap.edge.realsense`, :mod:`wardmap.edge.ros2live`)
as one :class:`~wardmap.edge.stream.StreamSource` that never ends on its own. The first connect
happens at construction (the calibration must be known before the stream starts, and a daemon
that cannot see its camera at start says so and exits). When the inner source raises
:class:`SourceLostError` (unplugged, no frames for a while) it logs one warning, retries the connector
with a capped exponential backoff (:data:`BACKOFF_FIRST_S` doubling to :data:`BACKOFF_MAX_S`),
and logs one line when events flow again (connected is not enough: a ROS 2 subscription always
"connects") and counts it in ``reconnects``. A connection that gives nothing before it is lost
is a failed try. Failed retries are logged
at debug level only: one line per state change. A camera that comes back with another
calibration (another camera in the same port) is an error: the tracker's map and the intrinsics
it was built with would disagree.

Threads: :meth:`ReconnectingSource.events` runs on the stream's producer thread and owns the
inner source; :meth:`ReconnectingSource.stop` (any thread) sets the stop event, which the
inner source and the backoff wait both watch. ``reconnects``, ``up`` and the inner source
being streamed are written by the producer thread only (``dropped_frames`` reads them).

:class:`RecordingSource` passes a source's events through unchanged and writes each frame
and odometry sample to a data-set folder (:class:`~wardmap.shared.dataset.DatasetWriter`,
docs/dataset.md), so ``wardmap track DIR`` replays what the robot saw. It writes on the producer
thread: a PNG pair costs it some milliseconds per frame, which a live source absorbs by
dropping (counted) when the tracker is behind.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Final

import numpy as np

from wardmap.edge.stream import FrameProblem, OdometrySample, SourceEvent, StreamSource
from wardmap.shared.dataset import Calibration, DatasetWriter, Frame, FrameSource
from wardmap.shared.errors import DatasetError

log = logging.getLogger(__name__)

BACKOFF_FIRST_S: Final = 0.5
"""First wait before reconnecting, seconds; doubles after each failed try."""
BACKOFF_MAX_S: Final = 8.0
"""Longest wait between reconnect tries, seconds."""

Connector = Callable[[threading.Event], StreamSource]
"""Opens the device or subscription; the source it returns ends its events when the event is set."""


def _close(source: object) -> None:
    """Call ``source.close()`` when it has one."""
    close = getattr(source, "close", None)
    if callable(close):
        close()


class SourceLostError(DatasetError):
    """A live source's device or topics went away (unplugged, no frames); it may come back."""


class PolledCamera:
    """A live camera connection read by polling its SDK for frame sets: the common part of the
    camera sources (``realsense.py``, ``orbbec.py``), a live
    :class:`~wardmap.edge.stream.StreamSource` whose events end when ``stop`` is set. A subclass
    gives :meth:`poll` and :meth:`frame`; ``errors`` are its SDK's exceptions for a camera that
    went away.

    Attributes:
        skipped: frame sets not turned into frames, by reason.
    """

    live = True
    has_odometry = False
    frame_count: int | None = None
    dataset: FrameSource | None = None
    errors: tuple[type[BaseException], ...] = (RuntimeError,)

    def __init__(self, name: str, calibration: Calibration, stop: threading.Event, *,
                 close: Callable[[], None] | None, stall_s: float) -> None:
        """Args:
            calibration: its ``rgb`` camera is the colour stream's intrinsics.
            close: releases the camera; called when the events end.
            stall_s: no frame set for this long (seconds) means the camera is gone.
        """
        self.name = name
        self.calibration = calibration
        self.skipped: Counter[str] = Counter()
        self._stop = stop
        self._close = close
        self._stall_s = stall_s
        self._index = 0

    def poll(self) -> object | None:
        """The SDK's next frame set, or None after a short wait."""
        raise NotImplementedError

    def frame(self, frames: Any) -> Frame | None:
        """A frame set -> a :class:`Frame`, or None when it is skipped (counted in ``skipped``)."""
        raise NotImplementedError

    @property
    def dropped_frames(self) -> int:
        """Frame sets left out (``skipped``)."""
        return sum(self.skipped.values())

    def close(self) -> None:
        """Release the camera (idempotent)."""
        close, self._close = self._close, None
        if close is not None:
            close()

    def events(self) -> Iterator[SourceEvent]:
        """Frames as the camera gives them, until ``stop``; the camera is released when they end,
        however they end.

        Raises:
            SourceLostError: no frame set for ``stall_s`` seconds, or one of ``errors`` while
                polling (the camera went away).
        """
        last = time.monotonic()
        try:
            while not self._stop.is_set():
                try:
                    frames = self.poll()
                except self.errors as exc:
                    raise SourceLostError(f"camera error: {exc}") from exc
                if frames is None:
                    if time.monotonic() - last > self._stall_s:
                        raise SourceLostError(f"no frames for {self._stall_s:.1f} s")
                    continue
                last = time.monotonic()
                frame = self.frame(frames)
                if frame is not None:
                    yield frame
        finally:
            self.close()


class ReconnectingSource:
    """A live source that survives its device going away (module docstring).

    Attributes:
        reconnects: times the source came back after being lost.
        up: False while the source is lost.
    """

    @property
    def dropped_frames(self) -> int:
        """Frames the inner sources let go before the stream (their ``dropped_frames``), summed
        over connections."""
        current = self._current
        return self._dropped_before + int(getattr(current, "dropped_frames", 0))

    live = True
    frame_count: int | None = None
    dataset: FrameSource | None = None

    def __init__(self, connect: Connector, *, backoff_first_s: float = BACKOFF_FIRST_S,
                 backoff_max_s: float = BACKOFF_MAX_S) -> None:
        """Connects once (the calibration comes from it).

        Raises:
            DatasetError: the first connect failed (its message says why).
        """
        self._connect = connect
        self._stop = threading.Event()
        self._backoff = (backoff_first_s, backoff_max_s)
        first = connect(self._stop)
        self._current: StreamSource | None = first
        self.name = first.name
        self.calibration: Calibration = first.calibration
        self.has_odometry = first.has_odometry
        self.reconnects = 0
        self.up = True
        self._dropped_before = 0  # dropped_frames of the connections that ended

    def stop(self) -> None:
        """End :meth:`events` soon (thread safe): the inner source and any backoff wait return."""
        self._stop.set()

    def close(self) -> None:
        """Release a connection that was never streamed (call after the stream ended)."""
        _close(self._current)
        self._current = None

    def events(self) -> Iterator[SourceEvent]:
        """The inner source's events, across reconnects, until :meth:`stop`.

        Raises:
            DatasetError: the source came back with another calibration, or failed otherwise
                than by :class:`SourceLostError`.
        """
        first, cap = self._backoff
        delay = first
        lost_at = 0.0
        while not self._stop.is_set():
            source = self._current
            if source is None:
                try:
                    source = self._connect(self._stop)
                except SourceLostError as exc:
                    log.debug("%s: still away (%s); next try in %.1f s", self.name, exc, delay)
                    self._stop.wait(delay)
                    delay = min(2 * delay, cap)
                    continue
                if source.calibration != self.calibration:
                    _close(source)
                    raise DatasetError(f"{self.name} came back with another calibration (another "
                                       "camera?); restart the edge to track with it")
                self._current = source  # read by dropped_frames while it streams
            events = source.events()
            flowing = False  # back (or up at start) once the first event came, not at connect
            try:
                for event in events:
                    if not self.up:
                        self.reconnects += 1
                        self.up = True
                        log.warning("%s: back after %.1f s (reconnect %d)", self.name,
                                    time.monotonic() - lost_at, self.reconnects)
                    flowing = True
                    yield event
                    if self._stop.is_set():
                        return
                if self._stop.is_set():
                    return
                raise SourceLostError("its stream ended")
            except SourceLostError as exc:
                if self.up:
                    self.up = False
                    lost_at = time.monotonic()
                    log.warning("%s: lost (%s); reconnecting", self.name, exc)
                else:
                    log.debug("%s: still away (%s); next try in %.1f s", self.name, exc, delay)
                if flowing:
                    delay = first
                else:  # connected but nothing came: a failed try, backed off like one
                    self._stop.wait(delay)
                    delay = min(2 * delay, cap)
            finally:
                _close(events)  # a generator: runs the inner source's own clean-up
                self._dropped_before += int(getattr(source, "dropped_frames", 0))
                self._current = None


class RecordingSource:
    """Pass ``source``'s events through and write them to the data-set folder ``out``
    (module docstring). :meth:`events` closes the folder when it ends, also on an error, so
    what was written is a valid data set.

    Attributes:
        recorded: frames written.
        skipped: frames not written (a problem frame, or a stamp not after the previous one).
    """

    def __init__(self, source: StreamSource, out: str | Path) -> None:
        """Raises:
            DatasetError: ``out`` is not empty or cannot be created.
        """
        self._source = source
        self.out = Path(out)
        self.name = source.name
        self.calibration = source.calibration
        self.live = source.live
        self.has_odometry = source.has_odometry
        self.frame_count = source.frame_count
        self.dataset = source.dataset
        self.recorded = 0
        self.skipped = 0
        self._writer = DatasetWriter(self.out, source.calibration)  # refuses a non-empty folder

    def stop(self) -> None:
        """Forward to the inner source's ``stop`` when it has one."""
        stop = getattr(self._source, "stop", None)
        if stop is not None:
            stop()

    def __getattr__(self, name: str) -> object:  # counters of the inner source (reconnects, up)
        return getattr(self._source, name)

    def close(self) -> None:
        """Close the inner source and the data-set folder (idempotent)."""
        _close(self._source)
        self._writer.close()

    def events(self) -> Iterator[SourceEvent]:
        """See :meth:`StreamSource.events`; each frame and odometry sample is also written."""
        odo_stamps: list[float] = []
        odo_poses: list[np.ndarray] = []
        last = -np.inf
        try:
            for event in self._source.events():
                if isinstance(event, OdometrySample):
                    stamp = round(event.stamp, 6)
                    if not odo_stamps or stamp > odo_stamps[-1]:
                        odo_stamps.append(stamp)
                        odo_poses.append(np.asarray(event.T_odom_base, np.float64))
                elif isinstance(event, Frame) and round(event.stamp, 6) > last:
                    self._writer.write_frame(event.stamp, event.rgb, event.depth_m,
                                             thermal_k=event.thermal_k, thermal_stamp=event.thermal_stamp)
                    last = round(event.stamp, 6)
                    self.recorded += 1
                else:
                    self.skipped += 1
                    if not isinstance(event, FrameProblem):
                        log.warning("--record: frame %.6f not after %.6f: not written", event.stamp, last)
                yield event
        finally:
            if odo_stamps:
                self._writer.write_odometry(odo_stamps, np.stack(odo_poses))
            self._writer.close()
            log.info("recorded %d frames to %s (%d not written)", self.recorded, self.out, self.skipped)

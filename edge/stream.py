"""Streaming frame sources: frames and odometry arrive as they are produced.

A :class:`StreamSource` yields *events* in arrival order: colour+depth :class:`Frame`\\ s,
:class:`OdometrySample`\\ s and :class:`FrameProblem`\\ s (a frame that came but cannot be
used). It needs nothing in advance but its calibration: no list of stamps, no odometry.
Sources today: a data-set folder or the simulator's live run (:class:`FrameSourceStream`
over any :class:`~wardmap.shared.dataset.FrameSource`) and a ROS recording
(:class:`wardmap.edge.bag.BagSource`).

:class:`FrameStream` runs one source on its own *producer* thread and hands the consumer
(the tracker) :class:`StreamItem`\\ s: each frame with its wheel-odometry pose at the frame's
stamp. Threads and state:

- the producer thread owns the source's iterator, the odometry buffer and the frames held
  for odometry (see "Odometry" below); it puts paired frames into the bounded *slot*.
- the consumer (whoever iterates the stream) takes items from the slot.
- the slot (``capacity`` items) is the only state both touch, under one condition variable.
  Its policy is named (:data:`DROP_OLDEST` or :data:`BLOCK`): a live source (a camera), or a
  replay asked to behave like one (``drop_when_behind``), never waits for the tracker: when
  the slot is full the oldest frame is dropped and counted, so the tracker always gets the
  newest frames and the queue never grows. Any other replay blocks instead: reading a file may
  wait, and nothing is lost. ``rate_hz`` paces a replay on a camera clock (at most that many
  frames per second), with either policy.

Odometry: a frame is held until an odometry sample at or after its stamp has arrived (so its
pose can be interpolated, as :func:`wardmap.shared.dataset.odom_at` does on a whole file), until
a frame more than :data:`ODOM_WAIT_S` newer arrives (the odometry is late or stopped: the frame
goes with what there is), or the source ends. Held frames are released in stamp order, so
frames that arrive slightly out of order are put back in order; a frame older than one already
released is dropped and counted (``late``). Sources without odometry release at once.

A source may also let frames go before they reach the stream (a live subscription whose queue
is full, a colour image without a depth partner); one that counts them says so in
``dropped_frames``, which :meth:`FrameStream.counters` reports as ``source_dropped``.
"""

from __future__ import annotations

import bisect
import logging
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Final, Protocol

import numpy as np
from numpy.typing import NDArray

from wardmap.shared.dataset import Calibration, Frame, FrameSource, pose_at
from wardmap.shared.errors import DatasetError, WardmapError

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]

DROP_OLDEST: Final = "drop-oldest"
"""Slot policy of live and paced sources: a full slot drops its oldest frame (counted)."""
BLOCK: Final = "block"
"""Slot policy of a replay as fast as possible: a full slot makes the producer wait."""
ODOM_WAIT_S: Final = 0.1
"""A frame waits for odometry at most until a frame this much newer (seconds) has arrived."""
ODOM_MAX_BRACKET_S: Final = 0.1
"""Odometry is interpolated between samples at most this far from the frame (seconds)."""
ODOM_MAX_NEAREST_S: Final = 0.05
"""Without a bracket, the nearest odometry sample is used up to this far away (seconds)."""
ODOM_KEEP_S: Final = 5.0
"""Odometry older than this behind the newest released frame is forgotten (seconds)."""
MAX_HELD_FRAMES: Final = 16
"""Frames held for odometry at most; beyond, the oldest is released without waiting."""


@dataclass(frozen=True)
class OdometrySample:
    """One wheel-odometry pose.

    Attributes:
        stamp: seconds.
        T_odom_base: (4, 4) the robot base in the odometry frame.
    """

    stamp: float
    T_odom_base: F64


@dataclass(frozen=True)
class FrameProblem:
    """A frame that arrived but cannot be used (unreadable image, ...); tracked as lost."""

    stamp: float
    problem: str


SourceEvent = Frame | OdometrySample | FrameProblem


class StreamSource(Protocol):
    """A source of frames and odometry in arrival order (see the module docstring).

    Attributes:
        name: what to call it in logs (a folder, ``bag:PATH``, ``sim:...``).
        calibration: intrinsics, depth scale and extrinsics (from the source or a
            ``calibration.toml``), known before the first frame.
        live: True when frames come on a device's clock (the stream must never block it).
        has_odometry: True when odometry samples will come (frames then wait for them).
        frame_count: frames it will give when known (progress), else None.
        dataset: the random-access data set behind it (the oracle label source reads its
            instance labels and ``objects.json``), or None.
    """

    name: str
    calibration: Calibration
    live: bool
    has_odometry: bool
    frame_count: int | None
    dataset: FrameSource | None

    def events(self) -> Iterator[SourceEvent]:
        """Frames, odometry and problems in arrival order; ends when the source does.

        Raises:
            DatasetError: the source cannot be read any further.
        """
        ...


class FrameSourceStream:
    """A random-access :class:`~wardmap.shared.dataset.FrameSource` (a data-set folder, the
    simulator's live run) as a :class:`StreamSource`: its odometry samples up to each frame's
    stamp, then the frame, in stamp order. Frames are read one at a time, when the stream
    asks; an unreadable frame becomes a :class:`FrameProblem`."""

    live = False

    def __init__(self, source: FrameSource, *, max_frames: int | None = None) -> None:
        self.dataset: FrameSource | None = source
        self.name = str(source.root)
        self.calibration = source.calibration
        self._source = source
        self._odometry = source.odometry()
        self.has_odometry = self._odometry is not None
        n = len(source)
        self.frame_count: int | None = n if max_frames is None else min(n, max_frames)

    def events(self) -> Iterator[SourceEvent]:
        """See :meth:`StreamSource.events`."""
        empty = (np.zeros(0), np.zeros((0, 4, 4)))
        odo_stamps, odo_T = self._odometry if self._odometry is not None else empty
        k = 0
        n = self.frame_count or 0
        for i in range(n):
            stamp = float(self._source.stamps[i])
            while k < len(odo_stamps) and odo_stamps[k] <= stamp:
                yield OdometrySample(float(odo_stamps[k]), odo_T[k])
                k += 1
            try:
                yield self._source.frame(i)
            except DatasetError as exc:
                log.warning("frame %d: %s", i, exc)
                yield FrameProblem(stamp, f"cannot read frame: {exc}")
        # the odometry after the last frame lets its pose be interpolated
        if k < len(odo_stamps):
            yield OdometrySample(float(odo_stamps[k]), odo_T[k])


@dataclass(frozen=True)
class StreamItem:
    """What the consumer gets: one frame (or a frame problem) with its odometry pose.

    Attributes:
        stamp: the frame's colour stamp, seconds.
        frame: the frame, or None when it could not be used (``problem`` says why).
        T_odom_base: (4, 4) wheel-odometry pose at ``stamp`` or None (no odometry near it).
        problem: why ``frame`` is None.
        released_s: ``time.monotonic()`` when the producer put it into the slot (latency).
    """

    stamp: float
    frame: Frame | None
    T_odom_base: F64 | None
    problem: str | None = None
    released_s: float = 0.0


class _OdometryBuffer:
    """Odometry samples in stamp order (owned by the producer thread), trimmed behind."""

    def __init__(self) -> None:
        self.stamps: list[float] = []
        self.poses: list[F64] = []

    def add(self, sample: OdometrySample) -> None:
        i = bisect.bisect_right(self.stamps, sample.stamp)
        self.stamps.insert(i, sample.stamp)
        self.poses.insert(i, np.asarray(sample.T_odom_base, np.float64))

    @property
    def newest(self) -> float:
        return self.stamps[-1] if self.stamps else -np.inf

    def at(self, stamp: float) -> F64 | None:
        """``T_odom_base`` at ``stamp`` (the rule of :func:`~wardmap.shared.dataset.pose_at`), or None."""
        if not self.stamps:
            return None
        lo = max(0, bisect.bisect_left(self.stamps, stamp) - 2)
        hi = bisect.bisect_right(self.stamps, stamp) + 2
        return pose_at(np.asarray(self.stamps[lo:hi]), np.stack(self.poses[lo:hi]), stamp,
                       max_bracket_s=ODOM_MAX_BRACKET_S, max_nearest_s=ODOM_MAX_NEAREST_S)

    def forget_before(self, stamp: float) -> None:
        k = bisect.bisect_left(self.stamps, stamp - ODOM_KEEP_S)
        if k > 0:
            del self.stamps[:k]
            del self.poses[:k]


class FrameStream:
    """Run a :class:`StreamSource` on a producer thread; iterate to get :class:`StreamItem`\\ s.

    Use as a context manager (the thread starts on enter and is stopped and joined on exit).
    Iteration ends when the source has ended and every item was taken, or after
    :meth:`close`; an error of the source is raised by the iteration, after the items before it.

    Attributes (counters, written by the producer only):
        received: frames the source gave (problems included).
        dropped: frames dropped because the consumer was behind (policy :data:`DROP_OLDEST`).
        late: frames dropped because they came older than a frame already released.
    """

    def __init__(self, source: StreamSource, *, capacity: int = 2, rate_hz: float = 0.0,
                 drop_when_behind: bool = False, max_frames: int | None = None) -> None:
        """Args:
            capacity: items the slot holds at most (>= 1).
            rate_hz: release frames on a clock at this rate; 0 = as they come.
            drop_when_behind: policy :data:`DROP_OLDEST` for a replay too (a live source always
                has it); otherwise :data:`BLOCK`.
            max_frames: stop after this many frames have been released (None: all).
        """
        if capacity < 1:
            raise WardmapError(f"stream capacity must be >= 1, got {capacity}")
        if not (np.isfinite(rate_hz) and rate_hz >= 0):
            raise WardmapError(f"stream rate must be >= 0 Hz, got {rate_hz}")
        self.source = source
        self.capacity = capacity
        self.rate_hz = rate_hz
        self.max_frames = max_frames
        self.policy = DROP_OLDEST if (source.live or drop_when_behind) else BLOCK
        self.received = 0
        self.dropped = 0
        self.late = 0
        self._slot: deque[StreamItem] = deque()
        self._cond = threading.Condition()
        self._done = False  # set by the producer when it has put its last item
        self._closed = False  # set by the consumer: the producer stops
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ consumer

    def __enter__(self) -> FrameStream:
        self._thread = threading.Thread(target=self._produce, name="frame-stream", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
        if self._thread is not None:
            self._thread.join()

    def close(self) -> None:
        """Stop the producer (thread safe); iteration ends at its next item. A source with a
        ``stop()`` method (a live source waiting for its device) is told to stop too."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        stop = getattr(self.source, "stop", None)
        if stop is not None:
            stop()

    def __iter__(self) -> Iterator[StreamItem]:
        while True:
            with self._cond:
                while not self._slot and not self._done and not self._closed:
                    self._cond.wait()
                if self._slot:
                    item = self._slot.popleft()
                    self._cond.notify_all()
                elif self._error is not None:
                    raise self._error
                else:
                    return
            yield item

    def counters(self) -> dict[str, int]:
        """``received``, ``dropped`` (consumer behind) and ``late`` (out of order) frames, and
        ``source_dropped``: frames the source let go before they reached the stream (its
        ``dropped_frames`` when it counts them, e.g. a subscription's full queue; else 0)."""
        return {"received": self.received, "dropped": self.dropped, "late": self.late,
                "source_dropped": int(getattr(self.source, "dropped_frames", 0))}

    # ------------------------------------------------------------------ producer

    def _produce(self) -> None:
        try:
            self._pump()
        except BaseException as exc:  # handed to the consumer by __iter__
            self._error = exc
        finally:
            with self._cond:
                self._done = True
                self._cond.notify_all()

    def _pump(self) -> None:
        odo = _OdometryBuffer()
        held: list[tuple[float, int, Frame | FrameProblem]] = []  # sorted by stamp
        order = 0  # ties keep arrival order
        last_out = -np.inf
        released = 0
        period = 1.0 / self.rate_hz if self.rate_hz > 0 else 0.0
        next_t = time.monotonic()
        events = self.source.events()
        try:
            for event in events:
                if self._closed:  # a frame the source gave (and a recording wrote) is still counted
                    self.received += not isinstance(event, OdometrySample)
                    return
                if isinstance(event, OdometrySample):
                    odo.add(event)
                    ready_before = odo.newest
                else:
                    self.received += 1
                    stamp = float(event.stamp)
                    if stamp <= last_out:
                        self.late += 1
                        log.warning("frame %.6f came after frame %.6f: dropped (late)", stamp, last_out)
                        continue
                    bisect.insort(held, (stamp, order, event))
                    order += 1
                    ready_before = odo.newest if self.source.has_odometry else np.inf
                    ready_before = max(ready_before, stamp - ODOM_WAIT_S)
                while held and (held[0][0] <= ready_before or len(held) > MAX_HELD_FRAMES):
                    stamp0, _, ev = held.pop(0)
                    last_out = stamp0
                    if period:
                        delay = next_t - time.monotonic()
                        if delay > 0:
                            time.sleep(delay)
                        next_t = max(next_t + period, time.monotonic() - period)
                    if not self._put(self._item(ev, odo)):
                        return
                    odo.forget_before(stamp0)
                    released += 1
                    if self.max_frames is not None and released >= self.max_frames:
                        return
            for _, _, ev in held:  # the source ended: nothing more will come
                if not self._put(self._item(ev, odo)):
                    return
                released += 1
                if self.max_frames is not None and released >= self.max_frames:
                    return
        finally:
            close = getattr(events, "close", None)
            if close is not None:
                close()

    def _item(self, ev: Frame | FrameProblem, odo: _OdometryBuffer) -> StreamItem:
        T = odo.at(ev.stamp)
        if isinstance(ev, FrameProblem):
            return StreamItem(ev.stamp, None, T, ev.problem, time.monotonic())
        return StreamItem(ev.stamp, ev, T, None, time.monotonic())

    def _put(self, item: StreamItem) -> bool:
        """Put ``item`` into the slot by the policy; False when the stream was closed."""
        with self._cond:
            if self.policy == BLOCK:
                while len(self._slot) >= self.capacity and not self._closed:
                    self._cond.wait()
            elif len(self._slot) >= self.capacity:
                self._slot.popleft()
                self.dropped += 1
            if self._closed:
                return False
            self._slot.append(item)
            self._cond.notify_all()
            return True


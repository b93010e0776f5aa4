"""The streaming frame source (edge/stream.py): drop policy, bounds, odometry pairing, order."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from wardmap.edge.stream import (
    BLOCK,
    DROP_OLDEST,
    FrameProblem,
    FrameSourceStream,
    FrameStream,
    OdometrySample,
    SourceEvent,
)
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import Calibration, Frame, odom_at
from wardmap.shared.se3 import yaw_transform

CALIB = Calibration(rgb=PinholeCamera(8, 6, 10.0, 10.0, 4.0, 3.0))


def _frame(i: int, stamp: float) -> Frame:
    return Frame(index=i, stamp=stamp, rgb=np.full((6, 8, 3), i % 256, np.uint8),
                 depth_m=np.ones((6, 8), np.float32), thermal_k=None, labels=None, T_world_camera=None)


class _ScriptedSource:
    """A stream source that yields a fixed list of events, then sets ``finished``; it records the
    stream's slot length at every yield (the bound under test)."""

    calibration = CALIB
    frame_count = None
    dataset = None

    def __init__(self, events: list[SourceEvent], *, live: bool, has_odometry: bool = False) -> None:
        self.name = "scripted"
        self.live = live
        self.has_odometry = has_odometry
        self._events = events
        self.finished = threading.Event()
        self.stream: FrameStream | None = None
        self.slot_lengths: list[int] = []

    def events(self) -> Iterator[SourceEvent]:
        for ev in self._events:
            if self.stream is not None:
                self.slot_lengths.append(len(self.stream._slot))
            yield ev
        self.finished.set()


@pytest.mark.parametrize("live", [True, False])
def test_a_slow_consumer_makes_a_camera_like_source_drop_the_oldest_frames_with_a_count(live: bool) -> None:
    """A live source (or a replay with drop_when_behind) gives 50 frames while the consumer is
    stuck on its first one: the producer never waits, the slot never holds more than its
    capacity, the frames that did not fit are counted as dropped and the consumer then gets the
    newest ones."""
    frames: list[SourceEvent] = [_frame(i, 100.0 + i / 30) for i in range(50)]
    source = _ScriptedSource(frames, live=live)
    stream = FrameStream(source, capacity=3, drop_when_behind=not live)
    source.stream = stream
    assert stream.policy == DROP_OLDEST
    got: list[float] = []
    with stream:
        for item in stream:
            got.append(item.stamp)
            if len(got) == 1:  # a slow tracker: busy until the camera has delivered every frame
                assert source.finished.wait(10)
    assert max(source.slot_lengths) <= 3
    counters = stream.counters()
    assert counters["received"] == 50
    assert counters["dropped"] == 50 - len(got) > 0
    assert len(got) <= 1 + 3 + 1  # the first, a full slot, and at most one in hand
    assert got[-1] == pytest.approx(100.0 + 49 / 30)  # the newest frame is never the one dropped
    assert got == sorted(got)


def test_a_replay_as_fast_as_possible_blocks_and_loses_nothing() -> None:
    """Not live and no rate: the producer waits for a slow consumer; every frame comes, in order."""
    frames: list[SourceEvent] = [_frame(i, 100.0 + i / 30) for i in range(20)]
    source = _ScriptedSource(frames, live=False)
    stream = FrameStream(source, capacity=2)
    source.stream = stream
    assert stream.policy == BLOCK
    with stream:
        got = [item.stamp for item in stream]
    assert got == [f.stamp for f in frames]  # type: ignore[union-attr]
    assert stream.counters() == {"received": 20, "dropped": 0, "late": 0, "source_dropped": 0}
    assert max(source.slot_lengths) <= 2


def test_frames_wait_for_odometry_and_get_the_whole_file_interpolation() -> None:
    """Odometry at 50 Hz arriving after each 30 Hz frame (as a robot delivers it): every frame's
    pose equals the whole-file rule (odom_at) on all samples, although the stream only had the
    samples that had arrived when it released the frame."""
    rng = np.random.default_rng(3)
    odo_t = 100.0 + np.arange(60) / 50
    odo_T = np.stack([yaw_transform(0.01 * k, 0.002 * k, rng.normal(0, 0.1)) for k in range(60)])
    frame_t = 100.01 + np.arange(30) / 30
    events: list[tuple[float, int, SourceEvent]] = [(t, 1, _frame(i, t)) for i, t in enumerate(frame_t)]
    # odometry is stamped when measured but arrives 15 ms later
    events += [(t + 0.015, 0, OdometrySample(t, odo_T[k])) for k, t in enumerate(odo_t)]
    source = _ScriptedSource([e for _, _, e in sorted(events, key=lambda e: (e[0], e[1]))],
                             live=False, has_odometry=True)
    with FrameStream(source) as stream:
        items = list(stream)
    assert [it.stamp for it in items] == list(frame_t)
    for it in items:
        want = odom_at((odo_t, odo_T), it.stamp)
        assert want is not None and it.T_odom_base is not None
        np.testing.assert_array_equal(it.T_odom_base, want)


def test_out_of_order_frames_are_put_back_in_order_and_late_ones_counted() -> None:
    """While frames wait for odometry they are released in stamp order (two swapped frames come
    out sorted); a frame older than one already released is dropped and counted as late; a
    problem frame is passed on with its reason."""
    T = np.eye(4)
    ev: list[SourceEvent] = [
        OdometrySample(99.9, T), _frame(1, 100.10), _frame(0, 100.05), OdometrySample(100.2, T),
        _frame(2, 100.00),  # after 100.05 and 100.10 went out: late
        FrameProblem(100.3, "cannot read frame: corrupt"), OdometrySample(100.4, T),
    ]
    source = _ScriptedSource(ev, live=False, has_odometry=True)
    with FrameStream(source) as stream:
        items = list(stream)
    assert [it.stamp for it in items] == [100.05, 100.10, 100.3]
    assert items[2].frame is None and items[2].problem == "cannot read frame: corrupt"
    assert stream.counters() == {"received": 4, "dropped": 0, "late": 1, "source_dropped": 0}


def test_a_source_error_reaches_the_consumer_after_the_frames_before_it() -> None:
    """The source fails after two frames: the consumer gets both, then the error."""
    from wardmap.shared.errors import DatasetError

    class Failing(_ScriptedSource):
        def events(self) -> Iterator[SourceEvent]:
            yield _frame(0, 1.0)
            yield _frame(1, 2.0)
            raise DatasetError("recording truncated")

    got: list[Any] = []
    with pytest.raises(DatasetError, match="truncated"), FrameStream(Failing([], live=False)) as stream:
        got.extend(stream)
    assert [it.stamp for it in got] == [1.0, 2.0]


def test_frame_source_stream_gives_the_folder_frames_and_odometry(tmp_path: Path) -> None:
    """A data-set folder streams its frames in order with the odometry pose odom_at gives on
    the whole odometry.txt; max_frames stops it early."""
    from wardmap.shared.dataset import DatasetReader, DatasetWriter

    odo_t = 10.0 + np.arange(25) / 50
    odo_T = np.stack([yaw_transform(0.02 * k, 0.0, 0.01 * k) for k in range(25)])
    with DatasetWriter(tmp_path / "d", CALIB) as w:
        for i in range(12):
            w.write_frame(10.0 + i / 30, np.zeros((6, 8, 3), np.uint8), np.ones((6, 8)))
        w.write_odometry(odo_t, odo_T)
    reader = DatasetReader(tmp_path / "d")
    with FrameStream(FrameSourceStream(reader), max_frames=10) as stream:
        items = list(stream)
    assert [it.stamp for it in items] == list(reader.stamps[:10])
    for it in items:
        np.testing.assert_array_equal(it.T_odom_base, odom_at(reader.odometry(), it.stamp))

"""Live sources (edge/live.py): reconnect after the camera goes away, record to a data set."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from wardmap.edge.live import ReconnectingSource, RecordingSource, SourceLostError
from wardmap.edge.stream import FrameSourceStream, FrameStream, OdometrySample, SourceEvent
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import Calibration, DatasetReader, Frame
from wardmap.shared.errors import DatasetError
from wardmap.shared.se3 import yaw_transform

CALIB = Calibration(rgb=PinholeCamera(8, 6, 10.0, 10.0, 4.0, 3.0))


def _frame(i: int, stamp: float) -> Frame:
    rng = np.random.default_rng(i)
    return Frame(index=i, stamp=stamp, rgb=rng.integers(0, 256, (6, 8, 3), dtype=np.uint8),
                 depth_m=rng.uniform(0.5, 4.0, (6, 8)).astype(np.float32), thermal_k=None, labels=None,
                 T_world_camera=None)


class _Camera:
    """A camera that is plugged in for ``plugged`` connects' worth of frames: connect ``k``
    gives ``frames[k]`` frames then is lost (unplugged); connects listed in ``absent`` fail."""

    def __init__(self, frames: list[int], absent: set[int], calibration: Calibration = CALIB) -> None:
        self.frames = frames
        self.absent = absent
        self.calibration = calibration
        self.connects = 0  # tries, failed ones included
        self.sessions = 0
        self.closed = 0
        self.stamp = 0.0

    def connect(self, stop: threading.Event) -> _Session:
        k = self.connects
        self.connects += 1
        if k in self.absent:
            raise SourceLostError("no camera is connected")
        n = self.frames[self.sessions] if self.sessions < len(self.frames) else 10**9
        self.sessions += 1
        return _Session(self, n, stop)


class _Session:
    live = True
    has_odometry = False
    frame_count = None
    dataset = None
    name = "fakecam"

    def __init__(self, camera: _Camera, n: int, stop: threading.Event) -> None:
        self.camera = camera
        self.calibration = camera.calibration
        self.n = n
        self.stop = stop
        self.dropped_frames = 0  # one per frame it gives: a driver that lost every other frame

    def close(self) -> None:
        self.camera.closed += 1

    def events(self) -> Iterator[SourceEvent]:
        try:
            for _ in range(self.n):
                if self.stop.is_set():
                    return
                self.camera.stamp += 0.1
                self.dropped_frames += 1
                yield _frame(round(self.camera.stamp * 10), self.camera.stamp)
            raise SourceLostError("unplugged")
        finally:
            self.close()


def test_unplug_and_replug_is_survived_with_one_log_line_per_state_change(
        caplog: pytest.LogCaptureFixture) -> None:
    camera = _Camera(frames=[3, 4, 5], absent={1, 2, 4})  # away for two tries, then for one
    source = ReconnectingSource(camera.connect, backoff_first_s=0.01, backoff_max_s=0.02)
    stamps: list[float] = []
    with caplog.at_level(logging.INFO, logger="wardmap.edge.live"):
        events = source.events()
        for ev in events:
            assert isinstance(ev, Frame)
            stamps.append(ev.stamp)
            if len(stamps) == 12:
                source.stop()
        events.close()
    assert len(stamps) == 12 and np.all(np.diff(stamps) > 0)  # frames flow across both replugs
    assert source.reconnects == 2 and source.up
    assert camera.connects == 6  # 1 + 2 failed + 1, then 1 failed + 1
    assert camera.closed == camera.sessions  # every connection was released
    lines = [r.getMessage() for r in caplog.records]
    assert sum("lost (unplugged)" in m for m in lines) == 2, lines
    assert sum("back after" in m for m in lines) == 2, lines
    assert not any("still away" in m for m in lines)  # failed tries are debug only


def test_the_backoff_is_capped_and_a_stop_ends_the_wait_at_once() -> None:
    camera = _Camera(frames=[1], absent=set(range(1, 1000)))
    source = ReconnectingSource(camera.connect, backoff_first_s=0.01, backoff_max_s=0.04)
    got: list[SourceEvent] = []
    runner = threading.Thread(target=lambda: got.extend(source.events()))
    runner.start()
    time.sleep(0.5)
    tries = camera.connects
    t0 = time.monotonic()
    source.stop()
    runner.join(2)
    assert not runner.is_alive() and time.monotonic() - t0 < 0.2
    assert len(got) == 1 and not source.up and source.reconnects == 0
    # 0.5 s of waits of 0.01, 0.02, then 0.04 s each: about 13 tries; uncapped doubling gives 6
    assert 8 <= tries <= 20, tries


def test_a_camera_that_comes_back_with_another_calibration_is_an_error() -> None:
    camera = _Camera(frames=[2], absent=set())
    source = ReconnectingSource(camera.connect, backoff_first_s=0.01)
    camera.calibration = Calibration(rgb=PinholeCamera(8, 6, 11.0, 11.0, 4.0, 3.0))
    with pytest.raises(DatasetError, match="another calibration"):
        list(source.events())
    assert camera.closed == camera.sessions


def test_a_camera_absent_at_start_is_a_clear_error() -> None:
    camera = _Camera(frames=[], absent={0})
    with pytest.raises(SourceLostError, match="no camera is connected"):
        ReconnectingSource(camera.connect)


def test_a_live_stream_with_a_slow_tracker_drops_with_a_count_and_survives_a_replug() -> None:
    camera = _Camera(frames=[20], absent={1})  # then streams until closed (a finite second
    # connection could run out before the consumer closes the stream: a second replug)
    source = ReconnectingSource(camera.connect, backoff_first_s=0.01)
    taken = 0
    with FrameStream(source, capacity=2) as stream:
        for _ in stream:
            taken += 1
            time.sleep(0.01)  # the tracker is slower than this camera
            if stream.received >= 40:
                stream.close()
    assert source.reconnects == 1
    assert stream.received >= 40 and stream.dropped > 0
    # every frame was taken, dropped, left in the slot, or (one) refused by the closed slot
    assert stream.received - 1 <= taken + stream.dropped + len(stream._slot) <= stream.received


class _Recorded:
    """Frames with odometry between them, as a live source gives them."""

    live = True
    has_odometry = True
    frame_count = None
    dataset = None
    name = "scripted"
    calibration = Calibration(rgb=CALIB.rgb, T_base_rgb=np.eye(4))

    def events(self) -> Iterator[SourceEvent]:
        for i in range(5):
            yield OdometrySample(1.0 + 0.1 * i - 0.02, yaw_transform(0.1 * i, 0.0, 0.01 * i))
            yield _frame(i, 1.0 + 0.1 * i)
            if i == 2:
                yield _frame(99, 1.05)  # older than a frame already written: passed on, not written
        yield OdometrySample(1.5, yaw_transform(0.5, 0.0, 0.05))


def test_record_writes_a_data_set_that_replays_the_same_frames_and_odometry(tmp_path: Path) -> None:
    rec = RecordingSource(_Recorded(), tmp_path / "rec")
    passed = list(rec.events())
    assert len(passed) == 12 and rec.recorded == 5 and rec.skipped == 1
    reader = DatasetReader(tmp_path / "rec")
    assert len(reader) == 5 and reader.calibration == _Recorded.calibration
    replay = [ev for ev in FrameSourceStream(reader).events() if isinstance(ev, Frame)]
    written = [ev for ev in _Recorded().events() if isinstance(ev, Frame) and ev.index != 99]
    assert [f.stamp for f in replay] == pytest.approx([f.stamp for f in written], abs=1e-9)
    for got, want in zip(replay, written, strict=True):
        assert got.stamp == pytest.approx(want.stamp, abs=1e-9)
        np.testing.assert_array_equal(got.rgb, want.rgb)
        np.testing.assert_allclose(got.depth_m, want.depth_m, atol=0.5 / reader.calibration.depth_scale)
    odo = reader.odometry()
    assert odo is not None and len(odo[0]) == 6
    np.testing.assert_allclose(odo[1][-1], yaw_transform(0.5, 0.0, 0.05), atol=1e-6)


def test_record_refuses_a_folder_that_is_not_empty(tmp_path: Path) -> None:
    (tmp_path / "x").write_text("keep me")
    with pytest.raises(DatasetError, match="not empty"):
        RecordingSource(_Recorded(), tmp_path)
    assert (tmp_path / "x").read_text() == "keep me"


def test_frames_a_source_lost_before_the_stream_are_counted_across_reconnects() -> None:
    """A camera whose driver loses one frame per frame it gives, unplugged after 3 and after 2
    frames, then streaming on: the stream's ``source_dropped`` sums every connection's."""
    camera = _Camera([3, 2], absent=set())
    source = ReconnectingSource(camera.connect, backoff_first_s=0.01, backoff_max_s=0.02)
    with FrameStream(source, max_frames=8) as stream:  # live: the slot may drop some (counted)
        list(stream)
    assert source.reconnects == 2  # 8 frames released: the third connection gave some
    assert stream.counters()["source_dropped"] == source.dropped_frames
    assert source.dropped_frames == stream.received  # the ended connections' and the current one's

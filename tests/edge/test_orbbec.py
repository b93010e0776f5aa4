"""The Orbbec source (edge/orbbec.py) without hardware: framesets the SDK itself builds in software
(``FrameSet.create_video_frame``, ``create_frame_set``), read through the source exactly as a
camera's ``Pipeline.wait_for_frames`` is read."""

from __future__ import annotations

import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from cameras import T0, check_unplug_and_replug

from wardmap.edge.live import SourceLostError
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import Calibration, DatasetReader, Frame
from wardmap.shared.errors import ConfigError, DatasetError

pytest.importorskip("pyorbbecsdk", reason="Orbbec SDK v2's bindings (pyorbbecsdk2) are not installed")

from wardmap.edge.orbbec import OrbbecSource, camera_from_profile, import_pyorbbecsdk, parse_spec

ob = import_pyorbbecsdk()  # as the source loads it: no SDK log folder in the working directory

TUM_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tum_fr1_rpy_s3_first100"


def frameset(rgb: np.ndarray | None, depth_m: np.ndarray | None, stamp_s: float, *, fmt: str = "RGB",
             scale_mm: float = 1.0) -> Any:
    """An SDK frameset: colour in ``fmt`` (RGB, BGR or MJPG) and Y16 depth in units of
    ``scale_mm`` millimetres, stamped ``stamp_s`` on arrival at the host (a software frame has
    no global timestamp: the source falls back to the arrival stamp, as on a camera without)."""
    fs = ob.FrameSet.create_frame_set()
    us = round(stamp_s * 1e6)
    if rgb is not None:
        h, w = rgb.shape[:2]
        if fmt == "MJPG":
            data = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 100])[1].tobytes()
            c = ob.FrameSet.create_frame(ob.OBFrameType.COLOR_FRAME, ob.OBFormat.MJPG, len(data))
        else:
            data = np.ascontiguousarray(rgb if fmt == "RGB" else rgb[:, :, ::-1]).tobytes()
            c = ob.FrameSet.create_video_frame(ob.OBFrameType.COLOR_FRAME, getattr(ob.OBFormat, fmt), w, h)
        c.update_data(data)
        c.set_system_timestamp_us(us)
        fs.push_frame(c)
    if depth_m is not None:
        h, w = depth_m.shape
        d = ob.FrameSet.create_video_frame(ob.OBFrameType.DEPTH_FRAME, ob.OBFormat.Y16, w, h)
        d.update_data(np.round(depth_m * 1e3 / scale_mm).astype(np.uint16).tobytes())
        d.as_depth_frame().set_value_scale(scale_mm)
        d.set_system_timestamp_us(us + 1000)
        fs.push_frame(d)
    return fs


class Feed:
    """A ``wait_for_frames`` stand-in over a queue of SDK framesets (None while empty)."""

    def __init__(self) -> None:
        self.queue: deque[Any] = deque()
        self.closed = False

    def __call__(self, timeout_ms: int) -> Any:
        if self.queue:
            return self.queue.popleft()
        time.sleep(min(timeout_ms, 20) / 1e3)
        return None

    def close(self) -> None:
        self.closed = True


def test_spec_names_a_camera_by_index() -> None:
    assert parse_spec("orbbec") == 0 and parse_spec("orbbec:") == 0
    assert parse_spec("orbbec:2") == 2
    with pytest.raises(ConfigError, match="orbbec:N"):
        parse_spec("orbbec:AY3A1234")


def test_intrinsics_and_distortion_come_from_the_profile() -> None:
    intr = ob.OBCameraIntrinsic()
    intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height = 600.0, 601.0, 321.0, 239.0, 640, 480
    dist = ob.OBCameraDistortion()
    dist.k1, dist.k2, dist.k3, dist.p1, dist.p2 = 0.1, -0.2, 0.05, 0.001, -0.002
    dist.k4 = dist.k5 = dist.k6 = 0.0
    dist.model = ob.OBCameraDistortionModel.BROWN_CONRADY
    cam = camera_from_profile(ob, intr, dist)
    assert (cam.width, cam.height) == (640, 480)
    assert [cam.fx, cam.fy, cam.cx, cam.cy] == pytest.approx([600.0, 601.0, 321.0, 239.0])
    assert list(cam.distortion) == pytest.approx([0.1, -0.2, 0.001, -0.002, 0.05])  # OpenCV's order
    dist.model = ob.OBCameraDistortionModel.KANNALA_BRANDT4
    assert not any(camera_from_profile(ob, intr, dist).distortion)  # not OpenCV's model: dropped


@pytest.mark.skipif(not TUM_DIR.is_dir(), reason="TUM excerpt (../shared/data) not present")
@pytest.mark.parametrize("fmt", ["RGB", "BGR", "MJPG"])
def test_tum_frames_come_out_as_recorded_in_every_colour_format(fmt: str) -> None:
    reader = DatasetReader(TUM_DIR)
    want = [reader.frame(i) for i in range(4)]
    feed = Feed()
    for f in want:
        feed.queue.append(frameset(f.rgb, f.depth_m, f.stamp, fmt=fmt, scale_mm=0.2))
    stop = threading.Event()
    source = OrbbecSource("orbbec:test", feed, Calibration(rgb=reader.calibration.rgb), stop,
                          close=feed.close, stall_s=0.3)
    got: list[Frame] = []
    with pytest.raises(SourceLostError, match="no frames"):  # the feed ends: the camera is gone
        for ev in source.events():
            assert isinstance(ev, Frame)
            got.append(ev)
    assert feed.closed and [g.index for g in got] == [0, 1, 2, 3]
    for g, f in zip(got, want, strict=True):
        assert g.stamp == f.stamp and g.depth_stamp == pytest.approx(f.stamp + 1e-3)
        if fmt == "MJPG":  # JPEG at quality 100: within a few levels
            assert np.mean(np.abs(g.rgb.astype(int) - f.rgb)) < 2.0
        else:
            np.testing.assert_array_equal(g.rgb, f.rgb)
        # 0.2 mm units: the depth comes back to within half a unit
        np.testing.assert_allclose(g.depth_m, f.depth_m, atol=1.01e-4)


def test_a_frameset_without_an_image_is_skipped_and_counted_and_a_wrong_size_is_refused() -> None:
    cam = PinholeCamera(32, 24, 30.0, 30.0, 16.0, 12.0)
    rgb, depth = np.zeros((24, 32, 3), np.uint8), np.ones((24, 32), np.float32)
    feed = Feed()
    feed.queue.extend([frameset(rgb, None, T0), frameset(None, depth, T0 + 0.1),
                       frameset(rgb, depth, T0 + 0.2)])
    source = OrbbecSource("orbbec:test", feed, Calibration(rgb=cam), threading.Event(), stall_s=0.2)
    got: list[Frame] = []
    with pytest.raises(SourceLostError):
        got.extend(ev for ev in source.events() if isinstance(ev, Frame))
    assert [f.stamp for f in got] == [pytest.approx(T0 + 0.2)]
    assert source.skipped["incomplete"] == 2 and source.dropped_frames == 2
    big = np.zeros((48, 64, 3), np.uint8)
    with pytest.raises(DatasetError, match=r"64x48 .* but the colour stream is 32x24"):
        source.frame(frameset(big, np.ones((48, 64), np.float32), T0 + 0.4))


def test_unplug_and_replug_of_the_camera_is_survived_and_a_slow_tracker_drops_with_a_count() -> None:
    camera = PinholeCamera(32, 24, 30.0, 30.0, 16.0, 12.0)
    feeds: list[Feed] = []

    def plug_in(stop: threading.Event, start: float) -> OrbbecSource:
        feed = Feed()
        feeds.append(feed)

        def produce() -> None:  # 30 Hz for one second, then the camera is unplugged
            for k in range(30):
                rng = np.random.default_rng(k)
                feed.queue.append(frameset(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8),
                                           np.full((24, 32), 1.0 + 0.01 * k, np.float32), start + k / 30))
                time.sleep(1 / 30)

        threading.Thread(target=produce, daemon=True).start()
        return OrbbecSource(f"orbbec:{len(feeds)}", feed, Calibration(rgb=camera), stop, close=feed.close,
                            stall_s=0.4)

    check_unplug_and_replug(plug_in)
    assert len(feeds) == 2 and all(f.closed for f in feeds)  # both released


def test_arrival_stamps_are_said_once(caplog: pytest.LogCaptureFixture) -> None:
    """Software frames carry no global timestamp, as a camera without: the source stamps them on
    arrival and says so once, not per image or per frame."""
    cam = PinholeCamera(32, 24, 30.0, 30.0, 16.0, 12.0)
    rgb, depth = np.zeros((24, 32, 3), np.uint8), np.ones((24, 32), np.float32)
    source = OrbbecSource("orbbec:test", Feed(), Calibration(rgb=cam), threading.Event())
    with caplog.at_level("WARNING", logger="wardmap.edge.orbbec"):
        frames = [source.frame(frameset(rgb, depth, T0 + k)) for k in range(3)]
    assert [f.stamp for f in frames if f is not None] == [T0, T0 + 1, T0 + 2]
    assert sum("no global timestamps" in r.getMessage() for r in caplog.records) == 1

"""The RealSense source (edge/realsense.py) without hardware: the SDK's own ``rs.software_device``.

Each test builds a software device with a depth sensor (z16, depth units 1 mm) and a colour
sensor (rgb8) whose streams carry intrinsics and extrinsics, feeds them frames, and reads them
back through an ``rs.syncer`` and the source's ``rs.align`` exactly as a camera's pipeline is read.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cameras import check_unplug_and_replug

from wardmap.edge.live import SourceLostError
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import Calibration, DatasetReader, Frame

rs = pytest.importorskip("pyrealsense2", reason="the realsense extra (pyrealsense2) is not installed")

from wardmap.edge.realsense import RealSenseSource, camera_from_intrinsics, parse_spec  # noqa: E402

TUM_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "tum_fr1_rpy_s3_first100"
DEPTH_UNITS = 0.001


class SoftCamera:
    """A software RealSense device of ``camera``'s size and intrinsics (depth registered to colour:
    identity extrinsics), open and streaming into a syncer until :meth:`close`."""

    def __init__(self, camera: PinholeCamera) -> None:
        self.camera = camera
        self.dev = rs.software_device()
        depth_sensor, colour_sensor = self.dev.add_sensor("Depth"), self.dev.add_sensor("Color")
        self.depth_profile = depth_sensor.add_video_stream(
            self._stream(rs.stream.depth, 0, 2, rs.format.z16))
        depth_sensor.add_read_only_option(rs.option.depth_units, DEPTH_UNITS)
        self.colour_profile = colour_sensor.add_video_stream(
            self._stream(rs.stream.color, 1, 3, rs.format.rgb8))
        same = rs.extrinsics()
        same.rotation, same.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
        self.depth_profile.register_extrinsics_to(self.colour_profile, same)
        self.dev.create_matcher(rs.matchers.default)
        self.syncer = rs.syncer()
        self.sensors = [(depth_sensor, self.depth_profile), (colour_sensor, self.colour_profile)]
        for sensor, profile in self.sensors:
            sensor.open(profile)
            sensor.start(self.syncer)
        self.n = 0
        self.lock = threading.Lock()  # a feeder thread injects, the source's thread closes

    def _stream(self, kind: Any, uid: int, bpp: int, fmt: Any) -> Any:
        cam = self.camera
        intr = rs.intrinsics()
        intr.width, intr.height, intr.fx, intr.fy = cam.width, cam.height, cam.fx, cam.fy
        intr.ppx, intr.ppy, intr.model, intr.coeffs = cam.cx, cam.cy, rs.distortion.brown_conrady, [0.0] * 5
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.width, vs.height = kind, 0, uid, cam.width, cam.height
        vs.fps, vs.bpp, vs.fmt, vs.intrinsics = 30, bpp, fmt, intr
        return vs

    def inject(self, stamp_s: float, rgb: np.ndarray, depth_m: np.ndarray) -> None:
        """One colour + depth pair with the hardware timestamp ``stamp_s``."""
        units = np.round(depth_m / DEPTH_UNITS).astype(np.uint16)
        with self.lock:
            self._inject(stamp_s, units, rgb)

    def _inject(self, stamp_s: float, units: np.ndarray, rgb: np.ndarray) -> None:
        if not self.sensors:  # closed: the frames of an unplugged camera go nowhere
            return
        for (sensor, profile), pixels, bpp in zip(self.sensors, (units, np.ascontiguousarray(rgb)), (2, 3),
                                                   strict=True):
            f = rs.software_video_frame()
            f.pixels, f.bpp, f.stride = pixels, bpp, self.camera.width * bpp
            f.timestamp, f.domain, f.frame_number = stamp_s * 1e3, rs.timestamp_domain.global_time, self.n
            f.profile = profile.as_video_stream_profile()
            if bpp == 2:
                f.depth_units = DEPTH_UNITS
            sensor.on_video_frame(f)
        self.n += 1

    def source(self, stop: threading.Event, **kw: Any) -> RealSenseSource:
        intr = self.colour_profile.as_video_stream_profile().get_intrinsics()
        depth_units = self.sensors[0][0].get_option(rs.option.depth_units)
        return RealSenseSource("realsense:soft", self.syncer.try_wait_for_frames,
                               Calibration(rgb=camera_from_intrinsics(rs, intr)), depth_units, stop,
                               close=self.close, **kw)

    def close(self) -> None:
        with self.lock:
            for sensor, _ in self.sensors:
                sensor.stop()
                sensor.close()
            self.sensors = []


def _feed(cam: SoftCamera, frames: list[tuple[float, np.ndarray, np.ndarray]],
          period_s: float) -> threading.Thread:
    def run() -> None:
        for stamp, rgb, depth in frames:
            cam.inject(stamp, rgb, depth)
            time.sleep(period_s)
    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def test_spec_names_the_first_camera_or_a_serial() -> None:
    assert parse_spec("realsense") is None
    assert parse_spec("realsense:") is None
    assert parse_spec("realsense:123456789012") == "123456789012"


@pytest.mark.skipif(not TUM_DIR.is_dir(), reason="TUM excerpt (../shared/data) not present")
def test_tum_frames_through_the_software_device_come_out_aligned_with_intrinsics_and_stamps() -> None:
    reader = DatasetReader(TUM_DIR)
    want = [reader.frame(i) for i in range(8)]
    cam = SoftCamera(reader.calibration.rgb)
    stop = threading.Event()
    source = cam.source(stop, stall_s=1.0)
    got_cam, ref_cam = source.calibration.rgb, reader.calibration.rgb
    assert (got_cam.width, got_cam.height) == (640, 480)
    assert [got_cam.fx, got_cam.fy, got_cam.cx, got_cam.cy] == pytest.approx(
        [ref_cam.fx, ref_cam.fy, ref_cam.cx, ref_cam.cy], rel=1e-6)  # the SDK holds float32
    assert source.depth_units_m == pytest.approx(DEPTH_UNITS)
    feeder = _feed(cam, [(f.stamp, f.rgb, f.depth_m) for f in want], 0.05)
    got: list[Frame] = []
    with pytest.raises(SourceLostError, match="no frames"):  # the feed ends: the camera is gone
        for ev in source.events():
            assert isinstance(ev, Frame)
            got.append(ev)
    feeder.join()
    assert len(got) >= 5 and not cam.sensors  # a few pairs may be split by the syncer; closed at the end
    by_stamp = {round(f.stamp, 6): f for f in want}
    for frame in got:
        ref = by_stamp[frame.stamp]  # hardware timestamps (ms) come back as the stamps (s)
        np.testing.assert_array_equal(frame.rgb, ref.rgb)
        both = (frame.depth_m > 0) & (ref.depth_m > 0)
        assert both.sum() > 0.9 * (ref.depth_m > 0).sum()  # aligned through identity extrinsics
        err = np.abs(frame.depth_m[both] - ref.depth_m[both])
        # 1 mm units; rs.align splats each depth pixel, so at depth edges a neighbour's value may win
        assert np.mean(err <= DEPTH_UNITS) > 0.97, np.mean(err <= DEPTH_UNITS)


def _small(i: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(i)
    return rng.integers(0, 256, (24, 32, 3), dtype=np.uint8), np.full((24, 32), 1.0 + 0.01 * i, np.float32)


def test_unplug_and_replug_of_the_camera_is_survived_and_a_slow_tracker_drops_with_a_count() -> None:
    camera = PinholeCamera(32, 24, 30.0, 30.0, 16.0, 12.0)
    devices: list[SoftCamera] = []

    def plug_in(stop: threading.Event, start: float) -> RealSenseSource:  # host-epoch (global_time) stamps
        cam = SoftCamera(camera)
        devices.append(cam)
        _feed(cam, [(start + k / 30, *_small(k)) for k in range(30)], 1 / 30)  # then it is unplugged
        return cam.source(stop, stall_s=0.4)

    check_unplug_and_replug(plug_in)
    assert len(devices) == 2 and all(not d.sensors for d in devices)  # both released

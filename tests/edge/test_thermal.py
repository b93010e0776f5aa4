"""The UVC thermal camera (edge/thermal.py), unit-tested with a fake OpenCV capture (no device here;
the real path is cv2.VideoCapture(INDEX, cv2.CAP_V4L2) in Y16 mode, docs/sources.md)."""

from __future__ import annotations

import time
from collections.abc import Iterator

import cv2
import numpy as np
import pytest

from wardmap.edge.stream import SourceEvent
from wardmap.edge.thermal import ThermalCapture, WithThermal
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import Calibration, Frame
from wardmap.shared.errors import DatasetError
from wardmap.shared.se3 import make_transform

THERMAL = PinholeCamera(16, 12, 20.0, 20.0, 8.0, 6.0)
T_RGB_THERMAL = make_transform(np.eye(3), [0.05, 0.0, 0.0])
RGB = PinholeCamera(8, 6, 10.0, 10.0, 4.0, 3.0)


class FakeCapture:
    """What cv2.VideoCapture does for a Lepton in Y16 mode: uint16 centikelvin frames."""

    def __init__(self, frames: list[np.ndarray | None]) -> None:
        self.frames = frames
        self.props: dict[int, float] = {}
        self.released = False

    def isOpened(self) -> bool:
        return True

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def read(self) -> tuple[bool, np.ndarray | None]:
        time.sleep(0.005)
        frame = self.frames.pop(0) if len(self.frames) > 1 else self.frames[0]
        return frame is not None, frame

    def release(self) -> None:
        self.released = True


class Colour:
    live = True
    has_odometry = False
    frame_count = None
    dataset = None
    name = "cam"
    calibration = Calibration(rgb=RGB)

    def __init__(self, stamps: list[float]) -> None:
        self.stamps = stamps

    def events(self) -> Iterator[SourceEvent]:
        for i, s in enumerate(self.stamps):
            time.sleep(0.02)
            yield Frame(index=i, stamp=s, rgb=np.zeros((6, 8, 3), np.uint8),
                        depth_m=np.ones((6, 8), np.float32), thermal_k=None, labels=None, T_world_camera=None)


def test_y16_frames_become_kelvin_and_join_colour_frames_close_in_time() -> None:
    raw = np.full((12, 16), 30_000, np.uint16)  # 300.00 K
    fake = FakeCapture([raw])
    capture = ThermalCapture(2, (16, 12), open_capture=lambda index: fake)
    assert fake.props[cv2.CAP_PROP_CONVERT_RGB] == 0
    assert fake.props[cv2.CAP_PROP_FOURCC] == cv2.VideoWriter.fourcc("Y", "1", "6", " ")
    now = time.time()
    source = WithThermal(Colour([now, now + 0.02, now - 100.0]),  # the last: far from any thermal image
                         capture, Calibration(rgb=RGB, thermal=THERMAL, T_rgb_thermal=T_RGB_THERMAL))
    assert source.calibration.thermal == THERMAL and source.calibration.rgb == RGB
    np.testing.assert_array_equal(source.calibration.T_rgb_thermal, T_RGB_THERMAL)
    frames = [ev for ev in source.events() if isinstance(ev, Frame)]
    assert fake.released
    assert [f.thermal_k is not None for f in frames] == [True, True, False]
    assert frames[0].thermal_k is not None
    np.testing.assert_allclose(frames[0].thermal_k, 300.0)
    assert frames[0].thermal_stamp is not None and abs(frames[0].thermal_stamp - frames[0].stamp) < 0.04
    assert source.with_thermal == 2


def test_a_capture_in_the_wrong_mode_or_missing_is_a_clear_error() -> None:
    rgb_like = np.zeros((12, 16, 3), np.uint8)  # RGB conversion on: not radiometric
    with pytest.raises(DatasetError, match=r"no 16-bit frames of 16x12.*Y16"):
        ThermalCapture(0, (16, 12), open_capture=lambda index: FakeCapture([rgb_like]))

    class Closed(FakeCapture):
        def isOpened(self) -> bool:
            return False

    with pytest.raises(DatasetError, match="cannot open thermal camera /dev/video4"):
        ThermalCapture(4, (16, 12), open_capture=lambda index: Closed([None]))


def test_thermal_needs_a_thermal_calibration() -> None:
    fake = FakeCapture([np.zeros((12, 16), np.uint16)])
    capture = ThermalCapture(0, (16, 12), open_capture=lambda index: fake)
    with pytest.raises(DatasetError, match=r"\[thermal\] table"):
        WithThermal(Colour([]), capture, Calibration(rgb=RGB))

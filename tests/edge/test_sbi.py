"""Rotation from small blurry images (``wardmap.edge.sbi``), and the tracker using it when its
motion model is off."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from wardmap.edge.sbi import SmallBlurryImage, rotation_between
from wardmap.edge.tracker import Tracker, TrackerConfig, TrackInput
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import DatasetReader, pose_at
from wardmap.shared.se3 import inverse, rotation_angle, so3_exp
from wardmap.sim.runner import generate


@pytest.fixture(scope="module")
def pan_clip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Thirteen frames (1.2 s) of turning on the spot: the turn starts at 0.5 s at 1.1 rad/s."""
    out = tmp_path_factory.mktemp("pan") / "pan"
    generate("pan_in_place", 1, out, frames=13)
    return out


def _gray(reader: DatasetReader, i: int) -> np.ndarray:
    return np.asarray(cv2.cvtColor(reader.frame(i).rgb, cv2.COLOR_RGB2GRAY))


@pytest.mark.parametrize("rotvec_deg", [(0.0, 4.0, 0.0), (2.0, -3.0, 3.0), (-4.0, 0.0, -2.0)])
def test_a_known_rotation_is_recovered_from_thumbnails(pan_clip: Path, rotvec_deg: tuple) -> None:
    """A frame warped by a pure camera rotation (pitch, yaw, roll of a few degrees: tens of pixels)
    gives that rotation back within 1 deg from an identity guess (a prior for matching: some
    8 px at this focal length; the 2D warp leaves out the image's perspective curvature)."""
    reader = DatasetReader(pan_clip)
    cam: PinholeCamera = reader.calibration.rgb
    R = so3_exp(np.radians(rotvec_deg))
    gray = _gray(reader, 0)
    H = cam.K @ R @ np.linalg.inv(cam.K)  # previous pixel -> current pixel
    turned = cv2.warpPerspective(gray, H, (cam.width, cam.height), flags=cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REFLECT)
    sbi = SmallBlurryImage(cam)
    assert sbi.size == (round(cam.width / 16), round(cam.height / 16))
    got = rotation_between(sbi, sbi.make(gray), sbi.make(turned), np.eye(3))
    assert got is not None
    assert np.degrees(rotation_angle(got @ R.T)) < 1.0
    assert np.degrees(rotation_angle(R)) > 3.5


def test_warp_and_rotation_are_inverse_for_small_turns() -> None:
    cam = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
    sbi = SmallBlurryImage(cam)
    for rv in ((0.0, 0.05, 0.0), (0.03, 0.0, 0.02), (0.0, 0.0, 0.0)):
        R = so3_exp(np.array(rv))
        assert np.degrees(rotation_angle(sbi.rotation_of(sbi.warp_of(R)) @ R.T)) < 0.2


def test_bad_thumbnail_settings_are_refused() -> None:
    cam = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
    for scale, blur in ((0.0, 0.75), (2.0, 0.75), (1 / 16, -1.0)):
        with pytest.raises(ValueError):
            SmallBlurryImage(cam, scale, blur)


def _reversed_turn(reader: DatasetReader) -> list[TrackInput]:
    """Frames 0-8, then 7, 6, 5 on the same 0.1 s clock: at frame 9 the camera turns back while
    the motion model keeps turning it on (about 11 deg, some 90 px, off)."""
    order = [*range(9), 7, 6, 5]
    out = []
    for k, i in enumerate(order):
        f = reader.frame(i)
        out.append(TrackInput(round(0.1 * k, 6), f.rgb, f.depth_m))
    return out


@pytest.mark.parametrize("sbi_scale", [1 / 16, 0.0])
def test_the_turn_back_is_tracked_from_thumbnails_not_relocalised(pan_clip: Path, sbi_scale: float) -> None:
    """With thumbnails (the default) the frame where the turn reverses is tracked from the rotation
    they give (source ``rgb``, an ``sbi`` time) and no frame is relocalised (the turn's sudden start
    is tracked so too); without them that frame takes a relocalisation. Either way every frame's
    pose is within 1 cm and 0.5 deg of the truth relative to the first frame."""
    reader = DatasetReader(pan_clip)
    gt = reader.groundtruth()
    assert gt is not None
    order = [*range(9), 7, 6, 5]
    tracker = Tracker(reader.calibration, TrackerConfig(sbi_scale=sbi_scale))
    results = [tracker.track(f) for f in _reversed_turn(reader)]
    first = pose_at(gt[0], gt[1], reader.frame(0).stamp)
    for i, res in zip(order, results, strict=True):
        truth = inverse(first) @ pose_at(gt[0], gt[1], reader.frame(i).stamp)
        err = inverse(truth) @ inverse(results[0].T_world_camera) @ res.T_world_camera
        assert np.linalg.norm(err[:3, 3]) < 0.01 and np.degrees(rotation_angle(err[:3, :3])) < 0.5, i
    turn = results[9]
    if sbi_scale:
        assert turn.source == "rgb" and "sbi" in turn.timings_ms
        assert all(r.source in ("init", "rgb") for r in results)
    else:
        assert turn.source == "relocalised"
        assert not any("sbi" in r.timings_ms for r in results)

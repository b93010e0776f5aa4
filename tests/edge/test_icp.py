"""Depth-only ICP (edge/icp.py): known motions recovered, degenerate geometry refused, and the
tracker's depth fallback on the blurred frames of the real TUM sequence."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from wardmap.edge.icp import DepthPyramid, IcpConfig, icp
from wardmap.edge.tracker import Tracker, TrackerConfig, TrackInput
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import ConfigError, GeometryError
from wardmap.shared.se3 import inverse, make_transform, rotation_angle, so3_exp

CAM = PinholeCamera(160, 120, 120.0, 120.0, 79.5, 59.5)
TUM = Path(__file__).resolve().parents[3] / "shared" / "data" / "tum_fr1_rpy_s3_first100"

# Planes n . x = c in the world frame: a room corner (floor and two walls) and a box.
CORNER = [((0.0, -1.0, 0.0), -1.0), ((0.0, 0.0, -1.0), -3.0), ((-1.0, 0.0, 0.0), -1.5)]
WALL = [((0.0, 0.0, -1.0), -2.0)]


def render(planes: list[tuple[tuple[float, float, float], float]], T_world_cam: np.ndarray) -> np.ndarray:
    """Depth (H, W) in metres of the nearest plane along every pixel ray (0 where none is hit)."""
    rays_c = CAM.pixel_rays().reshape(-1, 3)
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    rays_w = rays_c @ R.T
    best = np.full(len(rays_c), np.inf)
    for n, c in planes:
        nv = np.asarray(n)
        denom = rays_w @ nv
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (c - nv @ t) / denom
        s = np.where((denom != 0) & (s > 0), s, np.inf)
        best = np.minimum(best, s)
    depth = np.where(np.isfinite(best), best, 0.0)  # s scales a z = 1 ray: s is the depth
    return depth.reshape(CAM.height, CAM.width)


def _pose(rx_deg: float, ry_deg: float, t: tuple[float, float, float]) -> np.ndarray:
    return make_transform(so3_exp(np.radians([rx_deg, ry_deg, 0.0])), t)


CFG = IcpConfig(strides=(4, 2, 1), max_distance_m=(0.3, 0.1, 0.05), min_depth_m=0.2, max_depth_m=6.0)


def test_icp_recovers_a_known_motion() -> None:
    T_w_ref = _pose(0.0, 0.0, (0.0, 0.0, 0.0))
    T_w_cur = _pose(3.0, -4.0, (0.05, -0.02, 0.04))
    ref = DepthPyramid(render(CORNER, T_w_ref), CAM, CFG)
    cur = DepthPyramid(render(CORNER, T_w_cur), CAM, CFG)
    res = icp(ref, cur, CAM, np.eye(4), CFG)
    assert res.ok, res.reason
    err = inverse(inverse(T_w_ref) @ T_w_cur) @ res.T_ref_cur
    assert np.linalg.norm(err[:3, 3]) < 2e-3
    assert np.degrees(rotation_angle(err[:3, :3])) < 0.1
    assert res.rmse_m < 1e-3 and res.inlier_fraction > 0.8


def test_icp_refuses_a_flat_wall() -> None:
    """A single plane leaves sliding along it free: the pose is refused with a reason."""
    ref = DepthPyramid(render(WALL, np.eye(4)), CAM, CFG)
    cur = DepthPyramid(render(WALL, _pose(0.0, 0.0, (0.1, 0.0, 0.0))), CAM, CFG)
    res = icp(ref, cur, CAM, np.eye(4), CFG)
    assert not res.ok and "direction" in res.reason


def test_icp_refuses_empty_depth_and_bad_shapes() -> None:
    ref = DepthPyramid(render(CORNER, np.eye(4)), CAM, CFG)
    empty = DepthPyramid(np.zeros((CAM.height, CAM.width)), CAM, CFG)
    res = icp(ref, empty, CAM, np.eye(4), CFG)
    assert not res.ok and "too few" in res.reason
    with pytest.raises(GeometryError):
        DepthPyramid(np.zeros((10, 10)), CAM, CFG)
    with pytest.raises(ConfigError):
        IcpConfig(strides=(8, 4), max_distance_m=(0.1,))


@pytest.mark.skipif(not TUM.is_dir(), reason="../shared/data/tum_fr1_rpy_s3_first100 not present")
@pytest.mark.parametrize("sbi_scale", [0.0, 1 / 16])
def test_tracker_bridges_blurred_tum_frames_with_depth(sbi_scale: float) -> None:
    """Frames 38-39 of fr1_rpy are smeared by a fast turn: the motion model's prior gives no RGB
    pose. Without the rotation from thumbnails the depth fallback gives one (no odometry on a
    hand-held camera); with it (the default) RGB does. Either way within 6 deg of the ground
    truth's turn."""
    from wardmap.shared.dataset import DatasetReader, pose_at

    reader = DatasetReader(TUM)
    gt = reader.groundtruth()
    assert gt is not None
    tracker = Tracker(reader.calibration, TrackerConfig(sbi_scale=sbi_scale))
    results = []
    for i in range(30, 42):
        f = reader.frame(i)
        results.append(tracker.track(TrackInput(f.stamp, f.rgb, f.depth_m)))
    by_index = dict(zip(range(30, 42), results, strict=True))
    assert not any(r.lost for r in results)
    assert {by_index[38].source, by_index[39].source} == ({"rgb"} if sbi_scale else {"depth"})
    assert ("sbi" in by_index[38].timings_ms) == bool(sbi_scale)
    a, b = by_index[37], by_index[39]
    est = inverse(a.T_world_camera) @ b.T_world_camera
    true = inverse(pose_at(gt[0], gt[1], a.stamp)) @ pose_at(gt[0], gt[1], b.stamp)
    assert np.degrees(rotation_angle((inverse(true) @ est)[:3, :3])) < 6.0

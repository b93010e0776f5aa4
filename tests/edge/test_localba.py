"""Local bundle adjustment (edge/localba.py): a perturbed window is pulled back, the worker keeps up."""

from __future__ import annotations

import numpy as np
import pytest

from wardmap.edge.localba import (
    BaProblem,
    CovisibilityGraph,
    Intrinsics,
    LocalBaConfig,
    LocalBundleAdjuster,
    reprojection_chi2,
    solve_local_ba,
)
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import ConfigError
from wardmap.shared.se3 import inverse, rotation_angle, se3_exp, transform_points

CAM = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
INTR = Intrinsics(CAM.fx, CAM.fy, CAM.cx, CAM.cy, bf=40.0, max_stereo_depth_m=3.1)


def _scene(rng: np.random.Generator, n_kf: int = 6, n_pts: int = 300) -> tuple[list[np.ndarray], np.ndarray]:
    """Cameras 10 cm apart along x looking down +z at points 1-4 m away (a corridor wall)."""
    poses = []
    for k in range(n_kf):
        T = np.eye(4)
        T[:3, 3] = [0.1 * k, 0.01 * np.sin(k), 0.0]
        poses.append(T)
    pts = np.column_stack([rng.uniform(-1.5, 2.0, n_pts), rng.uniform(-1.0, 1.0, n_pts),
                           rng.uniform(1.0, 4.0, n_pts)])
    return poses, pts


def _problem(rng: np.random.Generator, poses: list[np.ndarray], pts: np.ndarray, noise_px: float,
             n_fixed: int) -> BaProblem:
    """Every point seen by every camera that has it in view, pixel noise ``noise_px``, depth noise 1 %."""
    ok, kf, pt, uv, z = [], [], [], [], []
    for k, T in enumerate(poses):
        pc = transform_points(inverse(T), pts)
        p, valid = CAM.project(pc)
        valid &= CAM.in_image(p)
        idx = np.flatnonzero(valid)
        kf.append(np.full(len(idx), k))
        pt.append(idx)
        uv.append(p[idx] + rng.normal(0, noise_px, (len(idx), 2)))
        z.append(pc[idx, 2] * (1 + rng.normal(0, 0.01, len(idx))))
        ok.append(valid)
    fixed = np.zeros(len(poses), bool)
    fixed[:n_fixed] = True
    return BaProblem(
        epoch=0, trigger=len(poses) - 1, kf_index=np.arange(len(poses)), T_world_cam=np.stack(poses),
        fixed=fixed, pid=np.arange(len(pts)), points_world=pts.copy(), obs_kf=np.concatenate(kf),
        obs_point=np.concatenate(pt), uv=np.concatenate(uv), depth_m=np.concatenate(z),
        sigma_px=np.ones(sum(len(i) for i in pt)),
    )


def _pose_error(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    rel = inverse(A) @ B
    return float(np.linalg.norm(rel[:3, 3])), float(np.degrees(rotation_angle(rel[:3, :3])))


def test_bundle_adjustment_lowers_reprojection_error_of_a_perturbed_window() -> None:
    """Six keyframes (two fixed) and 300 points with 0.5 px noise; the four free poses are
    moved by ~2 cm / ~1 deg and the points by ~2 cm. The adjustment brings the whitened
    reprojection RMS back to the noise level and the poses within a few millimetres of the truth,
    while the fixed poses stay where they were."""
    rng = np.random.default_rng(41)
    poses, pts = _scene(rng)
    truth = _problem(rng, poses, pts, noise_px=0.5, n_fixed=2)
    moved = [T if k < 2 else T @ se3_exp(np.r_[rng.normal(0, 0.012, 3), rng.normal(0, 0.012, 3)])
             for k, T in enumerate(poses)]
    start = BaProblem(**{**truth.__dict__, "T_world_cam": np.stack(moved),
                         "points_world": pts + rng.normal(0, 0.02, pts.shape)})
    sol = solve_local_ba(start, INTR, LocalBaConfig())
    chi2_start = reprojection_chi2(start, INTR, start.T_world_cam, start.points_world)
    chi2_end = reprojection_chi2(start, INTR, sol.T_world_cam, sol.points_world)
    assert sol.accepted, sol.reason
    assert np.sqrt(np.mean(chi2_end)) < 0.25 * np.sqrt(np.mean(chi2_start))
    assert np.sqrt(np.mean(chi2_end)) < 1.2  # 3 residuals of 0.5 px noise (+ depth noise): ~0.6-0.8
    assert sol.inlier.mean() > 0.95
    for k in range(len(poses)):
        err_m, err_deg = _pose_error(poses[k], sol.T_world_cam[k])
        assert err_m < 0.005 and err_deg < 0.2, (k, err_m, err_deg)
        if k < 2:
            np.testing.assert_allclose(sol.T_world_cam[k], start.T_world_cam[k], atol=1e-9)


def test_outlier_observations_are_dropped() -> None:
    """Five per cent of the observations moved 30 px: they are classified as outliers and do
    not pull the poses (each free pose within 5 mm of the truth)."""
    rng = np.random.default_rng(7)
    poses, pts = _scene(rng)
    pr = _problem(rng, poses, pts, noise_px=0.5, n_fixed=2)
    bad = rng.random(len(pr.obs_kf)) < 0.05
    uv = pr.uv.copy()
    uv[bad] += 30.0
    sol = solve_local_ba(BaProblem(**{**pr.__dict__, "uv": uv}), INTR, LocalBaConfig())
    assert sol.accepted
    assert not sol.inlier[bad].any() and sol.inlier[~bad].mean() > 0.95
    for k in range(2, len(poses)):
        assert _pose_error(poses[k], sol.T_world_cam[k])[0] < 0.005


def test_covisibility_window_fixes_keyframes_outside_it() -> None:
    """A graph of eight keyframes along a corridor: keyframe 7's window holds the keyframes
    that share at least ``min_shared_points`` with it (up to ``window``), the keyframes outside
    it that see the window's points are fixed, and keyframes seeing none of them are left out."""
    rng = np.random.default_rng(3)
    cfg = LocalBaConfig(window=3, min_shared_points=15, max_fixed=10)
    g = CovisibilityGraph(CAM, cfg)
    # Keyframe k sees points 40k .. 40k + 119: neighbours share 80, two apart 40, three apart 0.
    for k in range(8):
        pid = np.arange(40 * k, 40 * k + 120)
        uv = rng.uniform(0, 400, (120, 2)).astype(np.float32)
        g.add(k, np.eye(4), pid, uv, np.full(120, 2.0), np.ones(120))
    map_pid = np.arange(0, 40 * 7 + 120)
    pr = g.problem(7, 0, map_pid, rng.normal(size=(len(map_pid), 3)))
    assert pr is not None
    assert pr.kf_index[~pr.fixed].tolist() == [5, 6, 7]  # 6 shares 80 points, 5 shares 40, 4 none
    assert pr.kf_index[pr.fixed].tolist() == [3, 4]  # they see points 200-279 of the window
    assert set(pr.pid.tolist()) <= set(range(200, 400))


@pytest.mark.parametrize("bad", [{"worker": "thread"}, {"window": 0}, {"iterations": (0, 5)},
                                 {"graph_keyframes": 5}, {"max_correction_m": 0.0}])
def test_bad_config_is_rejected(bad: dict) -> None:
    with pytest.raises(ConfigError):
        LocalBaConfig(**bad)


def test_worker_process_keeps_up_with_a_bounded_backlog() -> None:
    """Problems submitted faster than one worker process solves them: at most one is being
    solved and one waits (a newer one replaces the waiting one, counted as superseded); every
    submitted problem is solved or superseded, and the counters say so."""
    rng = np.random.default_rng(5)
    poses, pts = _scene(rng)
    pr = _problem(rng, poses, pts, noise_px=0.5, n_fixed=2)
    ba = LocalBundleAdjuster(INTR, LocalBaConfig(worker="process"))
    try:
        got = []
        for _ in range(6):
            ba.submit(pr)
            assert ba.backlog() <= 2
            got += ba.poll()
        ba.wait(timeout_s=120)
        got += ba.poll()
    finally:
        ba.close()
    st = ba.stats
    assert st.max_backlog <= 2
    assert len(got) == st.solved + st.refused == st.submitted - st.superseded
    assert st.superseded >= 1 and all(s.accepted for s in got)
    assert st.unfinished == 0 and ba.stats.summary()["max_backlog"] <= 2

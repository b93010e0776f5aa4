"""The tracking frontend on a short simulated clip, and bad frames that must not crash it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from procs import wardmap

from wardmap.edge.offline import track_dataset
from wardmap.edge.tracker import Tracker, TrackerConfig, TrackInput
from wardmap.shared.dataset import DatasetReader, pose_at
from wardmap.shared.metrics import ate
from wardmap.shared.se3 import transform_from_tum
from wardmap.sim.runner import generate


@pytest.fixture(scope="module")
def aisle_clip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Eighty frames (8 s, 3 m) of the straight aisle, with thermal and odometry."""
    out = tmp_path_factory.mktemp("clip") / "aisle"
    generate("aisle_slow_1", 1, out, frames=80)
    return out


def _read_tum(path: Path) -> tuple[list[float], list[np.ndarray]]:
    rows = [list(map(float, ln.split())) for ln in path.read_text().splitlines() if not ln.startswith("#")]
    return [r[0] for r in rows], [transform_from_tum(r[1:]) for r in rows]


def test_tracks_a_simulated_clip_within_2cm(aisle_clip: Path, tmp_path: Path) -> None:
    """Every frame gets a pose from RGB; ATE (SE3-aligned) is below 2 cm over 3 m."""
    out = tmp_path / "traj.txt"
    summary = track_dataset(aisle_clip, out, labels="none")
    assert summary["frames"] == 80 and summary["lost_frames"] == 0
    assert summary["sources"].get("rgb", 0) >= 75
    assert summary["keyframes"] >= 3
    stamps, poses = _read_tum(out)
    assert len(stamps) == 80
    gt = DatasetReader(aisle_clip).groundtruth()
    assert gt is not None
    assert ate(stamps, poses, gt[0], gt[1]).rmse < 0.02
    assert set(summary["ms_per_frame"]) >= {"features", "match", "pose", "total", "cpu_total"}
    ms = summary["ms_per_frame"]
    assert 0 < ms["cpu_total"]["median"] <= 1.5 * ms["total"]["median"]


def test_local_bundle_adjustment_on_a_simulated_clip(aisle_clip: Path, tmp_path: Path) -> None:
    """With local BA on, ``wardmap track`` solves one problem per keyframe inline (backlog 0),
    every solution is accepted and lowers the window's reprojection error, the trajectory is
    the same on a second run (reproducible) and stays within 2 cm of the truth."""
    from wardmap.edge.localba import LocalBaConfig

    config = TrackerConfig(local_ba=LocalBaConfig(enabled=True))
    out, again = tmp_path / "traj.txt", tmp_path / "again.txt"
    summary = track_dataset(aisle_clip, out, labels="none", config=config)
    track_dataset(aisle_clip, again, labels="none", config=config)
    assert out.read_text() == again.read_text()
    ba = summary["local_ba"]
    assert ba["submitted"] >= summary["keyframes"] - 2 and ba["solved"] == ba["submitted"]
    assert ba["max_backlog"] == 0 and ba["cpu_ms_median"] > 0
    assert ba["rms_after_median"] < ba["rms_before_median"]
    stamps, poses = _read_tum(out)
    gt = DatasetReader(aisle_clip).groundtruth()
    assert gt is not None
    assert ate(stamps, poses, gt[0], gt[1]).rmse < 0.02


def test_oracle_labels_remove_points(tmp_path: Path) -> None:
    """With oracle labels on walking_staff, people's keypoints are reported dynamic."""
    data = tmp_path / "staff"
    generate("walking_staff", 0, data, frames=70)
    summary = track_dataset(data, tmp_path / "t.txt", labels="oracle", max_frames=70)
    assert summary["lost_frames"] == 0
    assert summary["labels_ms"] is not None
    assert summary["dynamic_points"] > 0
    plain = track_dataset(data, tmp_path / "n.txt", labels="none", max_frames=70)
    assert plain["dynamic_points"] == 0


def _frames(reader: DatasetReader, n: int) -> list[TrackInput]:
    out = []
    for i in range(n):
        f = reader.frame(i)
        out.append(TrackInput(f.stamp, f.rgb, f.depth_m, f.thermal_k, None, None))
    return out


@pytest.mark.parametrize(
    ("corrupt", "reason"),
    [
        (lambda f: TrackInput(f.stamp, None, f.depth_m), "empty colour image"),
        (lambda f: TrackInput(f.stamp, np.zeros((0, 0, 3), np.uint8), f.depth_m), "empty colour image"),
        (lambda f: TrackInput(f.stamp, f.rgb, np.zeros_like(f.depth_m)), "no valid pixel"),
        (lambda f: TrackInput(f.stamp, f.rgb, np.full_like(f.depth_m, np.nan)), "no valid pixel"),
        (lambda f: TrackInput(f.stamp, f.rgb, f.depth_m[:10]), "shape"),
    ],
    ids=["no-rgb", "empty-rgb", "zero-depth", "nan-depth", "bad-shape"],
)
def test_bad_frames_are_lost_with_a_reason(aisle_clip: Path, corrupt: object, reason: str) -> None:
    """A bad frame in the middle of a clip is marked lost (no odometry here) with a reason,
    the run goes on, and the next good frame is tracked from RGB again."""
    reader = DatasetReader(aisle_clip)
    calib = reader.calibration
    tracker = Tracker(calib)
    frames = _frames(reader, 12)
    for f in frames[:6]:
        tracker.track(f)
    bad = tracker.track(corrupt(frames[6]))  # type: ignore[operator]
    assert bad.lost and reason in bad.reason
    assert np.all(np.isfinite(bad.T_world_camera))
    after = [tracker.track(f) for f in frames[7:]]
    assert after[-1].source == "rgb" and not after[-1].lost


def test_black_rgb_frame_is_bridged_by_depth(aisle_clip: Path) -> None:
    """Without odometry, a black RGB frame with good depth gets its pose from depth ICP (close to
    the ground truth); with the depth fallback off it is lost, "RGB too dark"."""
    from wardmap.edge.icp import IcpConfig
    from wardmap.edge.tracker import TrackerConfig

    reader = DatasetReader(aisle_clip)
    gt = reader.groundtruth()
    assert gt is not None
    frames = _frames(reader, 8)
    black = TrackInput(frames[6].stamp, np.zeros_like(frames[6].rgb), frames[6].depth_m)
    for config, lost in ((TrackerConfig(), False), (TrackerConfig(icp=IcpConfig(enabled=False)), True)):
        tracker = Tracker(reader.calibration, config)
        first = tracker.track(frames[0])
        for f in frames[1:6]:
            tracker.track(f)
        res = tracker.track(black)
        assert res.lost is lost and "too dark" in res.reason
        if not lost:
            assert res.source == "depth"
            rel = np.linalg.inv(first.T_world_camera) @ res.T_world_camera
            T0, T6 = (pose_at(gt[0], gt[1], frames[i].stamp) for i in (0, 6))
            assert T0 is not None and T6 is not None
            rel_gt = np.linalg.inv(T0) @ T6
            assert np.linalg.norm(rel[:3, 3] - rel_gt[:3, 3]) < 0.03
        assert tracker.track(frames[7]).source == "rgb"


def _tilt_deg(T_a: np.ndarray, T_b: np.ndarray) -> float:
    """Angle (deg) between the world's up axis seen from two camera poses (roll/pitch only)."""
    up_a, up_b = T_a[:3, :3].T @ [0, 0, 1.0], T_b[:3, :3].T @ [0, 0, 1.0]
    return float(np.degrees(np.arccos(np.clip(up_a @ up_b, -1.0, 1.0))))


def test_level_toward_floor_moves_tilt_and_height_only() -> None:
    """Gain 1 puts the base level on the floor with its x, y and yaw; gain 0.5 halves the tilt."""
    from wardmap.edge.tracker import level_toward_floor
    from wardmap.shared.se3 import make_transform, so3_exp

    T_base_rgb = make_transform(so3_exp([-np.pi / 2, 0, 0]) @ so3_exp([0, 0, -np.pi / 2]),
                                [0.2, 0.0, 1.1])
    T_wb = make_transform(so3_exp([0, 0, 0.7]) @ so3_exp([0.01, -0.02, 0]),
                          [3.0, -1.0, 0.05])
    T = T_wb @ T_base_rgb
    level = level_toward_floor(T, T_base_rgb, 1.0)
    base = level @ np.linalg.inv(T_base_rgb)
    assert np.allclose(base[:3, 2], [0, 0, 1], atol=1e-9) and abs(base[2, 3]) < 1e-9
    assert np.allclose(base[:2, 3], T_wb[:2, 3], atol=0.05)  # the camera turns about itself
    assert abs(np.arctan2(base[1, 0], base[0, 0]) - 0.7) < 1e-3
    assert np.allclose(level_toward_floor(T, T_base_rgb, 0.0), T)
    half = level_toward_floor(T, T_base_rgb, 0.5)
    assert _tilt_deg(half, level) == pytest.approx(_tilt_deg(T, level) / 2, rel=0.02)
    assert half[2, 3] == pytest.approx((T[2, 3] + level[2, 3]) / 2)


def test_floor_levelling_removes_a_tilt_error(aisle_clip: Path) -> None:
    """A ground robot whose map starts 1.5 deg pitched (a bad first odometry pose) keeps that tilt
    without the floor filter; with it (tau 0.5 s) the tilt decays within the 8 s clip."""
    from wardmap.edge.tracker import TrackerConfig
    from wardmap.shared.se3 import make_transform, so3_exp

    reader = DatasetReader(aisle_clip)
    gt, odo = reader.groundtruth(), reader.odometry()
    assert gt is not None and odo is not None
    frames = [TrackInput(f.stamp, f.rgb, f.depth_m, None, pose_at(odo[0], odo[1], f.stamp))
              for f in (reader.frame(i) for i in range(len(reader)))]
    pitched = make_transform(so3_exp([0, np.radians(1.5), 0]), [0, 0, 0])
    frames[0] = TrackInput(frames[0].stamp, frames[0].rgb, frames[0].depth_m, None,
                           frames[0].T_odom_base @ pitched)
    T_gt = pose_at(gt[0], gt[1], frames[-1].stamp)
    assert T_gt is not None
    tilt = {}
    for tau in (0.0, 0.5):
        tracker = Tracker(reader.calibration, TrackerConfig(floor_level_tau_s=tau))
        results = [tracker.track(f) for f in frames]
        assert all(r.source in ("init", "rgb") for r in results)
        tilt[tau] = _tilt_deg(results[-1].T_world_camera, T_gt)
    assert tilt[0.0] > 1.0 and tilt[0.5] < 0.3, tilt


def test_nan_in_depth_is_tolerated(aisle_clip: Path) -> None:
    """Scattered NaNs in depth are treated as missing depth, not as a failure."""
    reader = DatasetReader(aisle_clip)
    tracker = Tracker(reader.calibration)
    rng = np.random.default_rng(0)
    for f in _frames(reader, 5):
        d = f.depth_m.copy() if f.depth_m is not None else None
        assert d is not None
        d[rng.random(d.shape) < 0.1] = np.nan
        res = tracker.track(TrackInput(f.stamp, f.rgb, d))
    assert res.source == "rgb"


def test_cli_track_prints_json_last(aisle_clip: Path, tmp_path: Path) -> None:
    """``wardmap track`` writes a TUM file and ends stdout with one JSON object."""
    out = tmp_path / "t.txt"
    p = wardmap("track", str(aisle_clip), "--out", str(out), "--max-frames", "10")
    assert p.returncode == 0, p.stderr
    summary = json.loads(p.stdout.strip().splitlines()[-1])
    assert summary["frames"] == 10 and "total" in summary["ms_per_frame"]
    assert len(_read_tum(out)[0]) == 10


def test_cli_track_bad_input(tmp_path: Path) -> None:
    """A missing data set or an unknown label source: one line, exit code 1."""
    for args in (["track", str(tmp_path / "nope"), "--out", str(tmp_path / "t.txt")],):
        p = wardmap(*args, timeout_s=120)
        assert p.returncode == 1 and "Traceback" not in p.stderr
        assert len(p.stderr.strip().splitlines()) == 1


def test_example_config_matches_the_defaults() -> None:
    """deploy/tracker.toml loads without error and equals the built-in defaults."""
    from wardmap.edge.tracker import TrackerConfig
    from wardmap.shared.config import load_config

    path = Path(__file__).resolve().parents[2] / "deploy" / "tracker.toml"
    assert load_config(TrackerConfig, path, section="tracker") == TrackerConfig()


def test_bad_tracker_config_is_rejected(tmp_path: Path) -> None:
    """A typo or an impossible value in the tracker config is a ConfigError."""
    from wardmap.edge.tracker import TrackerConfig
    from wardmap.shared.config import load_config
    from wardmap.shared.errors import ConfigError

    for text in (
        "[tracker]\nmin_inlier = 30\n",
        "[tracker]\nmin_inliers = 3\n",
        "[tracker.orb]\nn_features = 'x'\n",
        "[tracker]\nfloor_level_tau_s = -1.0\n",
        "[tracker]\nfloor_level_tau_s = nan\n",
        "[tracker]\nfuse_radius_px = -1.0\n",
        "[tracker]\nfuse_max_hamming = 300\n",
    ):
        p = tmp_path / "c.toml"
        p.write_text(text)
        with pytest.raises(ConfigError):
            load_config(TrackerConfig, p, section="tracker")


def test_the_motion_model_extrapolates_over_a_gap_but_not_over_jitter(aisle_clip: Path) -> None:
    """After dropped frames (more than 1.5 steps since the last frame) the prediction is the last
    step's twist over the time that passed, at most 0.2 s; a recording's stamp jitter leaves the
    last step as measured (decision 0043)."""
    from wardmap.shared.se3 import se3_exp, se3_log

    tracker = Tracker(DatasetReader(aisle_clip).calibration)
    for f in _frames(DatasetReader(aisle_clip), 4):
        tracker.track(f)
    step, dt, last = tracker._velocity, tracker._prev_dt, tracker._prev_stamp
    assert dt > 0 and last is not None and np.linalg.norm(se3_log(step)) > 1e-4
    np.testing.assert_array_equal(tracker._motion_step(last + 1.2 * dt), step)  # jitter
    np.testing.assert_allclose(tracker._motion_step(last + 2 * dt), se3_exp(2 * se3_log(step)), atol=1e-12)
    capped = se3_exp(min(10 * dt, 0.2) / dt * se3_log(step))
    np.testing.assert_allclose(tracker._motion_step(last + 10 * dt), capped, atol=1e-12)


def test_keyframe_point_ids_name_one_world_point(aisle_clip: Path) -> None:
    """Keypoints of two keyframes with the same map point id see the same world point (their
    depths back-projected with ground-truth poses meet within a few cm), no id repeats within a
    keyframe, and most keypoints with depth carry one."""
    reader = DatasetReader(aisle_clip)
    gt = reader.groundtruth()
    assert gt is not None
    tracker = Tracker(reader.calibration, TrackerConfig())
    seen: dict[int, list[np.ndarray]] = {}
    n_kf, with_depth, with_id = 0, 0, 0
    for f in _frames(reader, 50):
        res = tracker.track(f)
        if not res.keyframe or res.features is None:
            continue
        ids = res.point_ids
        assert ids is not None and ids.dtype == np.int64 and ids.shape == (len(res.features.uv),)
        named = ids[ids >= 0]
        assert len(np.unique(named)) == len(named)
        n_kf += 1
        T = pose_at(gt[0], gt[1], f.stamp)
        assert T is not None and f.depth_m is not None
        uv = res.features.uv.astype(np.float64)
        rows, cols = np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)
        h, w = f.depth_m.shape
        z = f.depth_m[rows.clip(0, h - 1), cols.clip(0, w - 1)].astype(float)
        good = np.isfinite(z) & (z > 0.3) & (z < 6.0)
        with_depth += int(good.sum())
        with_id += int((good & (ids >= 0)).sum())
        pts = tracker.cam.unproject(uv[good], z[good]) @ T[:3, :3].T + T[:3, 3]
        for pid, p in zip(ids[good].tolist(), pts, strict=True):
            if pid >= 0:
                seen.setdefault(pid, []).append(p)
    spread = [float(np.linalg.norm(p - ps[0])) for ps in seen.values() if len(ps) > 1 for p in ps[1:]]
    assert n_kf >= 4
    assert with_id > 0.9 * with_depth
    assert len(spread) > 300
    p50, p95 = np.percentile(spread, [50, 95])
    assert p50 < 0.02 and p95 < 0.10, (p50, p95)


def _duplicate_pairs(tracker: Tracker, max_m: float = 0.015, max_hamming: int = 50) -> int:
    """Pairs of map points within ``max_m`` of each other with descriptors within ``max_hamming``."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(tracker.map.pos_world).query_pairs(max_m, output_type="ndarray")
    if len(pairs) == 0:
        return 0
    desc = tracker.map.desc
    dist = np.unpackbits(desc[pairs[:, 0]] ^ desc[pairs[:, 1]], axis=1).sum(axis=1)
    return int((dist <= max_hamming).sum())


def test_map_point_fusion_gives_old_points_the_new_observations(aisle_clip: Path) -> None:
    """With fusion (ORB-SLAM2's Fuse at each keyframe) a keypoint that lands on an old map point
    the frame did not match observes it instead of making a twin: over 50 frames such
    observations are taken, the map holds fewer near-identical pairs than without it, and
    tracking stays within 2 cm."""
    reader = DatasetReader(aisle_clip)
    gt = reader.groundtruth()
    assert gt is not None
    frames = _frames(reader, 50)
    runs = {}
    for radius in (0.0, 3.0):
        tracker = Tracker(reader.calibration, TrackerConfig(fuse_radius_px=radius))
        poses = [tracker.track(f).T_world_camera for f in frames]
        runs[radius] = (tracker, ate([f.stamp for f in frames], poses, gt[0], gt[1]).rmse)
    off, on = runs[0.0][0], runs[3.0][0]
    assert off.fused_points == 0 and on.fused_points >= 10, on.fused_points
    assert _duplicate_pairs(on) < _duplicate_pairs(off), (_duplicate_pairs(on), _duplicate_pairs(off))
    assert runs[3.0][1] < 0.02


_WARM_UP_PROBE = """
import sys
from wardmap.edge import features, pose
from wardmap.edge.tracker import warm_up
from wardmap.shared.dataset import DatasetReader
kernels = {"rbrief": features._rbrief, "match": features._match_projected_kernel,
           "refine": pose._refine_rounds, "rolling_shutter": pose._rolling_shutter_system}
before = sorted(k for k, f in kernels.items() if f.signatures)
warm_up(DatasetReader(sys.argv[1]).calibration)
after = sorted(k for k, f in kernels.items() if f.signatures)
print(",".join(before) + "|" + ",".join(after))
"""


def test_warm_up_readies_the_kernels_a_frame_needs(aisle_clip: Path, tmp_path: Path) -> None:
    """In a fresh process no tracking kernel is ready; after warm_up (synthetic frames of the
    camera's size, readout set so the rolling-shutter fit runs) the ones every frame uses are,
    so a live camera's first frames are not dropped while numba compiles."""
    cal = aisle_clip / "calibration.toml"
    text = cal.read_text(encoding="utf-8")
    rolling = tmp_path / "clip"
    rolling.mkdir()
    for item in aisle_clip.iterdir():
        (rolling / item.name).symlink_to(item)
    (rolling / "calibration.toml").unlink()
    rolled = text.replace("readout_s = 0.0", "readout_s = 0.02")
    (rolling / "calibration.toml").write_text(rolled, encoding="utf-8")
    assert "readout_s = 0.02" in (rolling / "calibration.toml").read_text(encoding="utf-8")
    p = subprocess.run([sys.executable, "-c", _WARM_UP_PROBE, str(rolling)], capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr
    before, after = p.stdout.strip().splitlines()[-1].split("|")
    assert before == ""
    assert after == "match,rbrief,refine,rolling_shutter"


def test_keypoints_behind_a_depth_edge_are_found() -> None:
    """A keypoint reading the background next to a nearer surface is behind an edge; the
    nearer side, a smooth slope, holes and NaN are not; ratio 0 turns the test off."""
    from wardmap.edge.tracker import _behind_depth_edge

    depth = np.full((40, 60), 1.0, np.float32)
    depth[:, 30:] = 3.0  # a step: 1 m left of column 30, 3 m right
    depth[:, 40:] = np.linspace(3.0, 3.3, 20, dtype=np.float32)  # a slope, 1.6 cm a pixel
    depth[10, 10] = 0.0  # a hole
    depth[30, 20] = np.nan
    uv = np.array([[20.0, 20.0], [29.4, 20.0], [30.4, 20.0], [11.0, 11.0], [50.0, 20.0],
                   [20.0, 29.0], [0.0, 0.0], [10.0, 10.0]], np.float32)
    behind = _behind_depth_edge(depth, uv, 0.04)
    assert behind.tolist() == [False, False, True, False, False, False, False, False]
    assert not _behind_depth_edge(depth, uv, 0.0).any()
    assert _behind_depth_edge(depth, uv[4:5], 0.004)[0]  # the slope is an edge at a tighter ratio


def test_depth_edge_ratio_keeps_keypoints_behind_an_edge_out_of_the_map(aisle_clip: Path) -> None:
    """The first keyframe's map points: with the option on, those of the keypoints behind a
    depth edge are missing, and only those."""
    from wardmap.edge.features import OrbExtractor
    from wardmap.edge.tracker import _behind_depth_edge, _depth_at

    reader = DatasetReader(aisle_clip)
    f = reader.frame(0)
    sizes = []
    for ratio in (0.0, 0.04):
        tracker = Tracker(reader.calibration, TrackerConfig(depth_edge_ratio=ratio, thermal=False))
        tracker.track(TrackInput(f.stamp, f.rgb, f.depth_m))
        sizes.append(len(tracker.map))
    feats = OrbExtractor(TrackerConfig().orb).extract(cv2.cvtColor(f.rgb, cv2.COLOR_RGB2GRAY))
    z = _depth_at(f.depth_m, feats.uv)
    behind = _behind_depth_edge(f.depth_m, feats.uv, 0.04) & (z > 0.3) & (z < 6.0)
    assert behind.sum() > 0
    assert sizes[0] - sizes[1] == behind.sum()

"""Ground-truth consistency of a generated data set: depth, colour, thermal calibration,
labels and odometry agree with the ground-truth poses, and output is reproducible."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from wardmap.shared import se3
from wardmap.shared.dataset import DatasetReader
from wardmap.sim import raster
from wardmap.sim.odometry import BaseGeometry, OdometryNoise, odometry_error_bound
from wardmap.sim.runner import generate
from wardmap.sim.scenarios import build_scene
from wardmap.sim.sensors import SensorSimulator


@pytest.fixture(scope="module")
def staff_clip(tmp_path_factory: pytest.TempPathFactory) -> DatasetReader:
    """Forty frames (4 s) of walking_staff: people in view, robot moving."""
    out = tmp_path_factory.mktemp("sim") / "walking_staff"
    generate("walking_staff", 0, out, frames=40)
    return DatasetReader(out)


def _warp(reader: DatasetReader, i: int, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixels of frame i with depth, moved into frame j with ground truth.

    Returns (uv_i (N, 2) int, uv_j (N, 2) int, predicted depth in j (N,), mask of rows in view).
    """
    fi, fj = reader.frame(i), reader.frame(j)
    cam = reader.calibration.rgb
    assert fi.T_world_camera is not None and fj.T_world_camera is not None
    v, u = np.nonzero(fi.depth_m > 0)
    pts_i = cam.unproject(np.column_stack([u, v]).astype(float), fi.depth_m[v, u])
    T_j_i = se3.inverse(fj.T_world_camera) @ fi.T_world_camera
    pts_j = se3.transform_points(T_j_i, pts_i)
    uv_j, ok = cam.project(pts_j)
    ok &= cam.in_image(uv_j, margin=1.0)
    uvj = np.round(np.nan_to_num(uv_j)).astype(int)
    return np.column_stack([u, v]), uvj, pts_j[:, 2], ok


def test_depth_warped_between_frames_agrees(staff_clip: DatasetReader) -> None:
    """Depth of frame i warped into frame j (5 frames later) matches j's depth: median
    error below 1 cm on static overlapping pixels (people and occlusions excluded)."""
    for i, j in ((0, 5), (10, 15), (30, 39)):
        fi, fj = staff_clip.frame(i), staff_clip.frame(j)
        uv_i, uv_j, z_pred, ok = _warp(staff_clip, i, j)
        z_obs = fj.depth_m[uv_j[ok, 1], uv_j[ok, 0]]
        static = _static_mask(staff_clip, fi.labels)[uv_i[ok, 1], uv_i[ok, 0]]
        visible = (z_obs > 0) & (np.abs(z_obs - z_pred[ok]) < 0.2) & static
        assert visible.sum() > 50_000
        err = np.abs(z_obs - z_pred[ok])[visible]
        assert np.median(err) < 0.01, f"frames {i}->{j}: median depth error {np.median(err):.4f} m"


def test_colour_agrees_between_frames(staff_clip: DatasetReader) -> None:
    """The colour of a static surface point is the same in two frames (Lambertian world)."""
    fi, fj = staff_clip.frame(10), staff_clip.frame(14)
    uv_i, uv_j, z_pred, ok = _warp(staff_clip, 10, 14)
    z_obs = fj.depth_m[uv_j[ok, 1], uv_j[ok, 0]]
    static = _static_mask(staff_clip, fi.labels)[uv_i[ok, 1], uv_i[ok, 0]]
    visible = (z_obs > 0) & (np.abs(z_obs - z_pred[ok]) < 0.02) & static
    ci = fi.rgb[uv_i[ok, 1], uv_i[ok, 0]].astype(float)[visible]
    cj = fj.rgb[uv_j[ok, 1], uv_j[ok, 0]].astype(float)[visible]
    diff = np.abs(ci - cj).mean(axis=1)
    assert np.median(diff) < 8.0
    # A wrong pose would break this: shifting the match by 6 px makes colours disagree.
    shifted = fj.rgb[np.clip(uv_j[ok, 1] + 6, 0, 479), uv_j[ok, 0]].astype(float)[visible]
    assert np.median(np.abs(ci - shifted).mean(axis=1)) > np.median(diff)


def _static_mask(reader: DatasetReader, labels: np.ndarray | None) -> np.ndarray:
    assert labels is not None
    objs = reader.objects()
    assert objs is not None
    moving = [o["id"] for o in objs["objects"] if o["moves"]]
    return ~np.isin(labels, moving)


def test_thermal_pixels_land_on_the_same_instance(staff_clip: DatasetReader) -> None:
    """A thermal pixel with its (rendered) depth, moved through calibration.toml's
    T_rgb_thermal into the RGB image, hits the same object instance in the RGB labels."""
    calib = staff_clip.calibration
    assert calib.thermal is not None and calib.T_rgb_thermal is not None
    scene = build_scene("walking_staff", 0)
    sim = SensorSimulator(scene.world.static, scene.world.bank.stack())
    frame = staff_clip.frame(20)
    assert frame.T_world_camera is not None and frame.labels is not None
    from wardmap.sim.geometry import TriangleSoup
    from wardmap.sim.runner import SIM_EPOCH_S
    from wardmap.sim.world import soup_of

    t = frame.stamp - SIM_EPOCH_S
    dyn = TriangleSoup.concat([soup_of(*a.at(t), a.id, scene.world.bank) for a in scene.actors])
    th = calib.thermal
    T_world_th = frame.T_world_camera @ calib.T_rgb_thermal
    out = raster.render(
        sim.mesh(dyn),
        sim.atlas,
        (th.fx, th.fy, th.cx, th.cy),
        th.width,
        th.height,
        se3.inverse(T_world_th),
        sample_color=False,
        sample_gray=False,
    )
    v, u = np.nonzero((out.instance > 0) & (out.depth > 0))
    assert len(v) > 2000
    pts_th = th.unproject(np.column_stack([u, v]).astype(float), out.depth[v, u])
    uv, ok = calib.rgb.project(se3.transform_points(calib.T_rgb_thermal, pts_th))
    ok &= calib.rgb.in_image(uv, margin=1.0)
    uvi = np.round(np.nan_to_num(uv)).astype(int)
    hit = frame.labels[uvi[ok, 1], uvi[ok, 0]] == out.instance[v[ok], u[ok]]
    assert hit.mean() > 0.95
    # People are warm: their thermal pixels read about 30-35 C.
    assert frame.thermal_k is not None
    person_ids = [a.id for a in scene.actors if a.cls == "person"]
    warm = np.isin(out.instance, person_ids)
    if warm.sum() > 100:
        assert 302.0 < float(np.median(frame.thermal_k[warm])) < 309.0


def test_odometry_stays_within_its_noise_model(staff_clip: DatasetReader) -> None:
    """Wheel odometry over the clip: relative motion agrees with ground truth within the
    3-sigma bound of the noise model (camera ground truth mapped to the base)."""
    odo = staff_clip.odometry()
    gt = staff_clip.groundtruth()
    calib = staff_clip.calibration
    assert odo is not None and gt is not None and calib.T_base_rgb is not None
    t_gt, T_w_cam = gt
    t_odo, T_odom_base = odo
    T_w_base = T_w_cam @ se3.inverse(calib.T_base_rgb)
    k = np.searchsorted(t_odo, t_gt[-1])
    assert abs(t_odo[k] - t_gt[-1]) < 1e-3 and abs(t_odo[0] - t_gt[0]) < 1e-3
    rel_gt = se3.inverse(T_w_base[0]) @ T_w_base[-1]
    rel_odo = se3.inverse(T_odom_base[0]) @ T_odom_base[k]
    dist = float(np.linalg.norm(rel_gt[:2, 3]))
    assert dist > 0.5
    bound, _ = odometry_error_bound(dist, t_gt[-1] - t_gt[0], OdometryNoise(), BaseGeometry())
    assert np.linalg.norm(rel_gt[:2, 3] - rel_odo[:2, 3]) < bound


def test_same_scenario_and_seed_give_identical_bytes(tmp_path: Path) -> None:
    """Two runs of the same scenario and seed write byte-identical folders; another seed differs."""

    def digest(root: Path) -> dict[str, str]:
        return {
            str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*"))
            if p.is_file()
        }

    generate("ward_chairs", 5, tmp_path / "a", frames=3)
    generate("ward_chairs", 5, tmp_path / "b", frames=3)
    generate("ward_chairs", 6, tmp_path / "c", frames=3)
    a, b, c = digest(tmp_path / "a"), digest(tmp_path / "b"), digest(tmp_path / "c")
    assert a == b
    assert a != c
    assert any(name.startswith("rgb/") for name in a)


def test_two_robots_write_two_data_sets_in_one_world(tmp_path: Path) -> None:
    """two_robots writes robot_0/ and robot_1/ with the same objects.json world."""
    generate("two_robots", 0, tmp_path / "pair", frames=2)
    r0 = DatasetReader(tmp_path / "pair" / "robot_0")
    r1 = DatasetReader(tmp_path / "pair" / "robot_1")
    assert len(r0) == len(r1) == 2
    assert r0.objects() == r1.objects()
    f0, f1 = r0.frame(0), r1.frame(0)
    assert f0.T_world_camera is not None and f1.T_world_camera is not None
    assert np.linalg.norm(f0.T_world_camera[:3, 3] - f1.T_world_camera[:3, 3]) > 1.0


def test_hospital_days_writes_each_days_world(tmp_path: Path) -> None:
    """hospital_days writes day_1/ and day_2/; each objects.json is its day's world (the moved
    objects differ, every other object is the same); day 2's stamps are a day later."""
    generate("hospital_days", 0, tmp_path / "days", frames=2)
    d1 = DatasetReader(tmp_path / "days" / "day_1")
    d2 = DatasetReader(tmp_path / "days" / "day_2")
    assert len(d1) == len(d2) == 2
    assert d2.stamps[0] - d1.stamps[0] > 80_000.0
    o1, o2 = d1.objects()["objects"], d2.objects()["objects"]
    assert [o["id"] for o in o1] == [o["id"] for o in o2]
    differ = [b for a, b in zip(o1, o2, strict=True) if a != b]
    assert sorted(o["class"] for o in differ) == ["cart", "chair", "wheelchair"]
    assert all(o["note"] == "moved" for o in differ)

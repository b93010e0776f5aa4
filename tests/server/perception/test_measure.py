"""3D measurements (``server/perception/measure.py``) on synthetic scenes with known ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
from perception_scenes import (
    BGR,
    CAMERA,
    look_at,
    render_box,
)

from wardmap.server.perception.measure import (
    MeasureConfig,
    mean_rgb,
    measure_instances,
    measure_instances_report,
)
from wardmap.server.perception.types import Instance
from wardmap.shared.errors import ConfigError, GeometryError
from wardmap.shared.se3 import yaw_transform

BOX_SIZE = np.array([0.9, 0.5, 0.8])


T_WORLD_BOX = yaw_transform(2.0, 0.3, math.radians(25.0), z=0.4)  # x is the longer side


T_WORLD_CAM = look_at(np.array([1.0, -0.6, 1.7]), np.array([2.0, 0.3, 0.4]))


def measure_one(mask: np.ndarray, depth: np.ndarray, **kw: object) -> list:
    inst = Instance("cabinet", 0.9, mask, np.array([0.0, 0.0, 1.0, 1.0]))
    return measure_instances([inst], bgr=BGR, depth_m=depth, camera=CAMERA, T_world_camera=T_WORLD_CAM,
                             keyframe="test/1", stamp=1.0, **kw)


def yaw_error_deg(yaw_a: float, yaw_b: float) -> float:
    """Yaw difference modulo the 180 deg symmetry of a box."""
    d = (yaw_a - yaw_b) % math.pi
    return math.degrees(min(d, math.pi - d))


def check_box(m: object, tol_centre: float = 0.02, tol_yaw_deg: float = 3.0, tol_size: float = 0.05) -> None:
    centre_err = np.linalg.norm(m.T_world_object[:3, 3] - T_WORLD_BOX[:3, 3])
    assert centre_err < tol_centre, centre_err
    yaw = math.atan2(m.T_world_object[1, 0], m.T_world_object[0, 0])
    assert yaw_error_deg(yaw, math.radians(25.0)) < tol_yaw_deg
    np.testing.assert_allclose(m.size, BOX_SIZE, atol=tol_size)
    np.testing.assert_allclose(m.T_world_object[:3, 2], [0, 0, 1], atol=1e-9)


def test_box_pose_and_size_from_its_visible_faces() -> None:
    """A 0.9 x 0.5 x 0.8 m box seen from above one corner: centroid, yaw, size recovered."""
    depth, mask = render_box(T_WORLD_CAM, T_WORLD_BOX, BOX_SIZE)
    assert mask.sum() > 2000
    (m,) = measure_one(mask, depth)
    check_box(m)
    # Camera and world frames agree, points are camera-frame inliers on the box.
    np.testing.assert_allclose(m.T_world_camera @ m.T_camera_object, m.T_world_object, atol=1e-9)
    points_h = np.c_[m.points_camera, np.ones(len(m.points_camera))].T
    pts_box = (np.linalg.inv(T_WORLD_BOX) @ T_WORLD_CAM) @ points_h
    assert np.all(np.abs(pts_box[:3].T) <= BOX_SIZE / 2 + 0.01)
    assert m.color_hist.shape == (16 * 4 * 4,) and abs(float(m.color_hist.sum()) - 1.0) < 1e-5
    assert m.descriptors.dtype == np.uint8 and m.descriptors.shape[1] == 32 and len(m.descriptors) > 0
    assert m.confidence == pytest.approx(0.9) and m.category == "cabinet"


def test_outliers_are_removed() -> None:
    """10% of the mask's depth replaced by far background and random spikes: the box is still found."""
    depth, mask = render_box(T_WORLD_CAM, T_WORLD_BOX, BOX_SIZE)
    rng = np.random.default_rng(7)
    rows, cols = np.nonzero(mask)
    pick = rng.choice(rows.size, size=rows.size // 10, replace=False)
    noisy = depth.copy()
    half = pick[: pick.size // 2]
    noisy[rows[half], cols[half]] = 6.0  # wall behind the box bleeding into the mask
    rest = pick[pick.size // 2:]
    noisy[rows[rest], cols[rest]] += rng.uniform(-0.6, 0.6, rest.size).astype(np.float32)
    (m,) = measure_one(mask, noisy)
    check_box(m, tol_centre=0.05, tol_yaw_deg=3.0, tol_size=0.08)
    # Without outlier removal the far points would stretch the box by metres.
    assert m.size.max() < 1.0


def test_a_door_mask_bleeding_along_the_wall_is_cut_to_the_widest_door() -> None:
    """A 1.0 m door in a wall seen at a grazing angle; its mask also holds a band of the wall
    1.2 m beyond its near edge. With the door's width bound (1.3 m) the box keeps the door and
    at most the 0.3 m of slack: its centre moves by at most half of that towards the band."""
    T_world_wall = yaw_transform(0.0, 3.0, 0.0, z=1.25)  # wall along world x, face at y = 2.95
    depth, hit = render_box(T_WORLD_WALL_CAM, T_world_wall, np.array([8.0, 0.1, 2.5]))
    world = (CAMERA.pixel_rays() * depth[..., None]) @ T_WORLD_WALL_CAM[:3, :3].T + T_WORLD_WALL_CAM[:3, 3]
    x, z = world[..., 0], world[..., 2]
    door = hit & (np.abs(x - 2.0) <= 0.5) & (z <= 2.1)
    band = hit & (x >= 0.3) & (x < 1.5) & (np.abs(z - 1.0) <= 0.15)
    assert door.sum() > 10000 and band.sum() > 3000

    def centre_and_width(max_width_m: tuple) -> tuple[float, float]:
        inst = Instance("door", 0.9, door | band, np.array([0.0, 0.0, 1.0, 1.0]))
        (m,) = measure_instances([inst], bgr=BGR, depth_m=depth, camera=CAMERA,
                                 T_world_camera=T_WORLD_WALL_CAM, keyframe="test/1", stamp=1.0,
                                 config=MeasureConfig(max_width_m=max_width_m))
        return float(m.T_world_object[0, 3]), float(m.size[0])

    x_free, w_free = centre_and_width(())
    assert x_free < 1.7 and w_free > 1.6  # the band stretches the box along the wall
    x_cut, w_cut = centre_and_width((("door", 1.3), ("cabinet", 0.5)))
    assert abs(x_cut - 2.0) <= 0.15 + 0.07 and 1.0 - 0.05 <= w_cut <= 1.3
    assert centre_and_width((("cabinet", 0.5),))[0] == pytest.approx(x_free)  # other classes only
    with pytest.raises(ConfigError, match="max_width_m"):
        MeasureConfig(max_width_m=(("door", 0.0),))


T_WORLD_WALL_CAM = look_at(np.array([0.0, 1.0, 1.2]), np.array([2.5, 2.95, 1.0]))


def test_a_door_cut_by_the_image_border_is_widened_beyond_it() -> None:
    """A 1.0 m door (x 1.5..2.5 m) whose right part lies beyond the right image border: its
    visible part's box is centred 0.2-0.3 m left of the door; widened to the door's usual width
    on the border's side, it is centred on the door. A door in full view, another class, and a
    mask over both borders are left as measured."""
    T_world_door = yaw_transform(2.0, 3.0, 0.0, z=1.05)
    door_size = np.array([1.0, 0.05, 2.1])

    def measure_door(T_world_camera: np.ndarray, widths: tuple) -> tuple[float, float]:
        depth, hit = render_box(T_world_camera, T_world_door, door_size)
        inst = Instance("door", 0.9, hit, np.array([0.0, 0.0, 1.0, 1.0]))
        (m,) = measure_instances([inst], bgr=BGR, depth_m=depth, camera=CAMERA, T_world_camera=T_world_camera,
                                 keyframe="test/1", stamp=1.0,
                                 config=MeasureConfig(max_width_m=(), clipped_width_m=widths))
        return float(m.T_world_object[0, 3]), float(m.size[0])

    cut_right = look_at(np.array([1.0, 0.5, 1.2]), np.array([0.6, 3.0, 1.0]))
    _, hit = render_box(cut_right, T_world_door, door_size)
    assert hit[:, -1].any() and not hit[:, 0].any()
    x_seen, w_seen = measure_door(cut_right, ())
    assert 0.4 < w_seen < 0.65 and 0.2 < 2.0 - x_seen < 0.3
    x_wide, w_wide = measure_door(cut_right, (("door", 1.0),))
    assert abs(x_wide - 2.0) < 0.03 and w_wide == pytest.approx(1.0)
    # Mirrored: the left part beyond the left border.
    cut_left = look_at(np.array([3.0, 0.5, 1.2]), np.array([3.4, 3.0, 1.0]))
    assert abs(measure_door(cut_left, (("door", 1.0),))[0] - 2.0) < 0.03
    assert measure_door(cut_right, (("cabinet", 1.0),)) == (x_seen, w_seen)
    in_view = look_at(np.array([2.0, 0.0, 1.2]), np.array([2.0, 3.0, 1.0]))
    assert measure_door(in_view, (("door", 1.2),)) == pytest.approx(measure_door(in_view, ()))
    both = look_at(np.array([2.0, 2.6, 1.2]), np.array([2.0, 3.0, 1.2]))
    _, hit = render_box(both, T_world_door, door_size)
    assert hit[:, 0].any() and hit[:, -1].any()
    assert measure_door(both, (("door", 1.5),)) == measure_door(both, ())
    with pytest.raises(ConfigError, match="clipped_width_m"):
        MeasureConfig(clipped_width_m=(("door", -1.0),))


def test_square_footprint_yaw_is_modulo_90_and_x_is_the_longer_side() -> None:
    """x of the measurement follows the longer horizontal side even if it is the box's y."""
    size = np.array([0.5, 0.9, 0.8])
    depth, mask = render_box(T_WORLD_CAM, T_WORLD_BOX, size)
    (m,) = measure_one(mask, depth)
    yaw = math.atan2(m.T_world_object[1, 0], m.T_world_object[0, 0])
    assert yaw_error_deg(yaw, math.radians(25.0 + 90.0)) < 3.0
    assert -math.pi / 2 <= yaw < math.pi / 2
    np.testing.assert_allclose(m.size, [0.9, 0.5, 0.8], atol=0.05)


def test_largest_piece_when_clustering() -> None:
    """A mask that also covers a small box 0.4 m away: clustering keeps the big box only."""
    depth, mask = render_box(T_WORLD_CAM, T_WORLD_BOX, BOX_SIZE)
    T_small = yaw_transform(2.0, -0.6, 0.0, z=0.15)
    depth2, mask2 = render_box(T_WORLD_CAM, T_small, np.array([0.3, 0.3, 0.3]))
    assert mask2.any() and not (mask & mask2).any()
    both = np.where(mask2, depth2, depth).astype(np.float32)
    (joined,) = measure_one(mask | mask2, both)
    assert joined.size[0] > 1.0  # without clustering the box spans both objects
    (m,) = measure_one(mask | mask2, both, config=MeasureConfig(cluster_gap_m=0.05))
    check_box(m)


def test_empty_and_depthless_masks_are_skipped_with_a_reason() -> None:
    """An empty mask and a mask without depth are reported as skipped; the box is still measured."""
    depth, mask = render_box(T_WORLD_CAM, T_WORLD_BOX, BOX_SIZE)
    empty = np.zeros_like(mask)
    no_depth = ~mask & (np.arange(CAMERA.width)[None, :] < 20)
    rows, cols = np.nonzero(mask)
    speck = np.zeros_like(mask)
    speck[rows[0], cols[0]] = True  # depth on all of it, but one point < min_points
    insts = [Instance("cabinet", 1.0, m, np.zeros(4)) for m in (empty, mask, no_depth, speck)]
    report = measure_instances_report(insts, bgr=BGR, depth_m=depth, camera=CAMERA,
                                      T_world_camera=T_WORLD_CAM, keyframe="k", stamp=0.0)
    assert len(report.measurements) == 1
    assert [(s.instance, s.kind) for s in report.skipped] == [(0, "empty_mask"), (2, "little_depth"),
                                                           (3, "few_points")]
    assert "min_points" in report.skipped[0].reason
    assert "depth on 0 % of the mask" in report.skipped[1].reason


def test_masks_mostly_without_depth_are_skipped() -> None:
    """Depth on only 10 % of the box's mask (a black screen's bezel): skipped with a reason under
    the default min_depth_fraction 0.25, measured when the check is off."""
    depth, mask = render_box(T_WORLD_CAM, T_WORLD_BOX, BOX_SIZE)
    holes = depth.copy()
    rng = np.random.default_rng(0)
    holes[mask & (rng.random(mask.shape) < 0.9)] = 0.0
    report = measure_instances_report([Instance("cabinet", 1.0, mask, np.zeros(4))], bgr=BGR, depth_m=holes,
                                      camera=CAMERA, T_world_camera=T_WORLD_CAM, keyframe="k", stamp=0.0)
    assert not report.measurements and "< 25 %" in report.skipped[0].reason
    assert report.skipped[0].kind == "little_depth"
    assert len(measure_one(mask, holes, config=MeasureConfig(min_depth_fraction=0.0))) == 1


def test_a_monitor_flush_with_the_wall_is_a_picture() -> None:
    """A 'wall_monitor' mask 6 cm proud of a wall at 3 m is measured; one 1 cm proud (a poster)
    is skipped as flush; a cabinet flush with the wall (not a raised class) is measured."""
    wall = np.full((CAMERA.height, CAMERA.width), 3.0, np.float32)
    rect = np.zeros(wall.shape, bool)
    rect[100:140, 140:200] = True
    rng = np.random.default_rng(1)
    noise = rng.normal(0.0, 0.004, wall.shape).astype(np.float32)  # Kinect-like at 3 m
    def report(proud_m: float, category: str = "wall_monitor") -> object:
        depth = np.where(rect, 3.0 - proud_m, wall).astype(np.float32) + noise
        return measure_instances_report([Instance(category, 0.9, rect, np.zeros(4))], bgr=BGR, depth_m=depth,
                                        camera=CAMERA, T_world_camera=T_WORLD_CAM, keyframe="k", stamp=0.0)
    assert len(report(0.06).measurements) == 1
    poster = report(0.01)
    assert not poster.measurements and "flush with its surroundings" in poster.skipped[0].reason
    assert poster.skipped[0].kind == "flush"
    assert len(report(0.01, "cabinet").measurements) == 1
    off = MeasureConfig(flush_tolerance_m=0.0)
    depth = np.where(rect, 2.99, wall).astype(np.float32)
    assert len(measure_instances([Instance("wall_monitor", 0.9, rect, np.zeros(4))], bgr=BGR, depth_m=depth,
                                 camera=CAMERA, T_world_camera=T_WORLD_CAM, keyframe="k", stamp=0.0,
                                 config=off)) == 1
    with pytest.raises(ConfigError, match="flush"):
        MeasureConfig(flush_tolerance_m=-0.01)


@pytest.mark.parametrize(("rgb", "tol"), [((200, 30, 40), 35), ((30, 60, 200), 35), ((40, 160, 60), 35),
                                          ((128, 128, 128), 35), ((20, 20, 20), 15)])
def test_mean_colour_from_the_histograms(rgb: tuple[int, int, int], tol: float) -> None:
    """A uniformly coloured box: the colour from its HSV histogram is within the bins' coarseness;
    greys get no tint; two measurements of it give the same colour."""
    depth, mask = render_box(T_WORLD_CAM, T_WORLD_BOX, BOX_SIZE)
    bgr = np.zeros_like(BGR)
    bgr[:] = rgb[::-1]
    (m,) = measure_instances([Instance("cabinet", 1.0, mask, np.zeros(4))], bgr=bgr, depth_m=depth,
                             camera=CAMERA, T_world_camera=T_WORLD_CAM, keyframe="k", stamp=0.0)
    got = mean_rgb([m.color_hist], MeasureConfig().hist_bins)
    assert got is not None
    np.testing.assert_allclose(got, rgb, atol=tol)
    if len(set(rgb)) == 1:
        assert got[0] == pytest.approx(got[1]) == pytest.approx(got[2])
    assert mean_rgb([m.color_hist, m.color_hist], MeasureConfig().hist_bins) == pytest.approx(got)


def test_mean_colour_of_nothing_is_none() -> None:
    bins = MeasureConfig().hist_bins
    assert mean_rgb([], bins) is None
    assert mean_rgb([np.zeros(256, np.float32)], bins) is None
    assert mean_rgb([np.ones(10, np.float32)], bins) is None  # another binning


def test_gravity_other_than_minus_z() -> None:
    """The same scene in a world whose up axis is +y: object z follows -gravity."""
    depth, mask = render_box(T_WORLD_CAM, T_WORLD_BOX, BOX_SIZE)
    T_new_old = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])  # old z -> new y
    inst = Instance("cabinet", 1.0, mask, np.zeros(4))
    (m,) = measure_instances([inst], bgr=BGR, depth_m=depth, camera=CAMERA,
                             T_world_camera=T_new_old @ T_WORLD_CAM, keyframe="k", stamp=0.0,
                             gravity_world=(0.0, -9.81, 0.0))
    np.testing.assert_allclose(m.T_world_object[:3, 2], [0, 1, 0], atol=1e-9)
    np.testing.assert_allclose(m.T_world_object[:3, 3], (T_new_old @ T_WORLD_BOX)[:3, 3], atol=0.02)
    np.testing.assert_allclose(m.size, BOX_SIZE, atol=0.05)


def test_bad_inputs_raise() -> None:
    depth, mask = render_box(T_WORLD_CAM, T_WORLD_BOX, BOX_SIZE)
    with pytest.raises(GeometryError, match="depth"):
        measure_one(mask, depth[:10])
    with pytest.raises(GeometryError, match="mask"):
        measure_one(mask[:10], depth)
    with pytest.raises(ConfigError, match="min_depth_m"):
        MeasureConfig(min_depth_m=3.0, max_depth_m=1.0)

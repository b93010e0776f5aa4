"""Instances and 3D measurements on synthetic scenes with known ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.perception.floor import flat_on_floor, floating_above_floor, part_of_taller_surface
from wardmap.server.perception.instances import (
    attach_gt_instances,
    gt_instance_of,
    id_to_class,
    instances_from_classes,
    merge_stacked,
    off_background_planes,
    oracle_instances,
    split_side_by_side,
)
from wardmap.server.perception.masks import box_of_mask, densest_window
from wardmap.server.perception.measure import (
    MeasureConfig,
    mean_rgb,
    measure_instances,
    measure_instances_report,
)
from wardmap.server.perception.types import Instance
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import ConfigError, DatasetError, GeometryError
from wardmap.shared.se3 import yaw_transform

CAMERA = PinholeCamera(320, 240, 262.5, 262.5, 159.5, 119.5)


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """T_world_camera of a camera at ``eye`` looking at ``target`` (world z up, no roll)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, z])
    T[:3, 3] = eye
    return T


def render_box(T_world_camera: np.ndarray, T_world_box: np.ndarray, size: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Depth (H, W) float32 and hit mask of an oriented box, by exact ray/slab intersection."""
    rays_c = CAMERA.pixel_rays().reshape(-1, 3)  # z = 1, so the ray parameter is the depth
    T_box_cam = np.linalg.inv(T_world_box) @ T_world_camera
    origin = T_box_cam[:3, 3]
    dirs = rays_c @ T_box_cam[:3, :3].T
    half = size / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - origin) / dirs
        t2 = (half - origin) / dirs
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (t_near <= t_far) & (t_near > 0)
    depth = np.where(hit, t_near, 0.0).astype(np.float32).reshape(CAMERA.height, CAMERA.width)
    return depth, hit.reshape(CAMERA.height, CAMERA.width)


BOX_SIZE = np.array([0.9, 0.5, 0.8])
T_WORLD_BOX = yaw_transform(2.0, 0.3, math.radians(25.0), z=0.4)  # x is the longer side
T_WORLD_CAM = look_at(np.array([1.0, -0.6, 1.7]), np.array([2.0, 0.3, 0.4]))
BGR = np.random.default_rng(3).integers(0, 256, (CAMERA.height, CAMERA.width, 3), dtype=np.uint8)


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


def test_densest_window() -> None:
    """The width-wide interval holding the most points; a sparse tail beyond it is left out."""
    rng = np.random.default_rng(5)
    dense = rng.uniform(0.0, 1.0, 900)
    tail = rng.uniform(1.0, 2.5, 60)
    keep = densest_window(np.r_[dense, tail], 1.2)
    assert keep[:900].all() and keep[900:].sum() < 20
    assert densest_window(np.array([0.0, 0.1, 5.0]), 1.0).tolist() == [True, True, False]
    assert densest_window(np.array([3.0]), 1.0).tolist() == [True]


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


# ---------------------------------------------------------------------------- instances


def test_oracle_instances_on_a_crafted_label_image() -> None:
    """Two objects and a tiny one: every class returned, small ones dropped, boxes exact."""
    labels = np.zeros((60, 80), np.uint16)
    labels[10:30, 5:25] = 7  # 400 px person
    labels[40:60, 60:80] = 3  # 400 px door reaching the image corner
    labels[0:5, 70:75] = 9  # 25 px
    classes = id_to_class({"objects": [{"id": 7, "class": "person"}, {"id": 3, "class": "door"},
                                       {"id": 9, "class": "cup"}]})
    insts = oracle_instances(labels, classes, min_pixels=100)
    got = [(i.gt_instance, i.category, i.confidence) for i in insts]
    assert got == [(3, "door", 1.0), (7, "person", 1.0)]
    np.testing.assert_array_equal(insts[0].box_xyxy, [60, 40, 80, 60])
    np.testing.assert_array_equal(insts[1].box_xyxy, [5, 10, 25, 30])
    assert insts[1].mask.sum() == 400
    with pytest.raises(DatasetError, match="instance id 9"):
        oracle_instances(labels, {7: "person", 3: "door"}, min_pixels=100)


def test_connected_components_split_at_a_depth_jump() -> None:
    """One class region of two chairs touching in the image at 2 m and 3 m: two instances."""
    classes = np.zeros((60, 100), np.uint8)
    depth = np.full((60, 100), 5.0, np.float32)
    classes[10:50, 10:90] = 2
    depth[10:50, 10:50] = 2.0
    depth[10:50, 50:90] = 3.0
    classes[52:58, 0:10] = 1  # 60 px of class 1, below min_pixels
    conf = np.full((60, 100), 0.8, np.float32)
    insts = instances_from_classes(classes, depth, ["background", "person", "chair"], conf, min_pixels=100)
    assert [i.category for i in insts] == ["chair", "chair"]
    assert sorted(int(i.mask.sum()) for i in insts) == [1600, 1600]  # far-side edge pixels re-joined
    for inst in insts:
        assert np.ptp(depth[inst.mask]) == 0.0
        assert inst.confidence == pytest.approx(0.8)
    # A smooth slope (a floor-like ramp) stays one instance.
    depth[10:50, 10:90] = np.linspace(2.0, 3.0, 80, dtype=np.float32)[None, :]
    assert len(instances_from_classes(classes, depth, ["background", "person", "chair"], min_pixels=100)) == 1
    with pytest.raises(GeometryError, match="class names"):
        instances_from_classes(classes, depth, ["background", "person"])


def test_low_confidence_components_are_left_out() -> None:
    """Two chairs, one the network is unsure of (mean confidence 0.4): min_confidence 0.5 keeps one."""
    classes = np.zeros((60, 100), np.uint8)
    depth = np.full((60, 100), 3.0, np.float32)
    classes[10:50, 5:40] = 2
    classes[10:50, 60:95] = 2
    conf = np.full((60, 100), 0.9, np.float32)
    conf[10:50, 60:95] = 0.4
    names = ["background", "person", "chair"]
    kept = instances_from_classes(classes, depth, names, conf, min_pixels=100, min_confidence=0.5)
    assert len(kept) == 1 and kept[0].box_xyxy[0] == 5
    assert len(instances_from_classes(classes, depth, names, conf, min_pixels=100)) == 2
    with pytest.raises(GeometryError, match="min_confidence"):
        instances_from_classes(classes, depth, names, conf, min_confidence=1.5)


def _wall_and_floor(h: int = 120, w: int = 200) -> np.ndarray:
    """Depth of a slanted wall (upper part) and a floor (lower rows), both planes: inverse
    depth affine in the pixel coordinates."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    wall = 1.0 / (1 / 3.0 - 0.0006 * u)  # 3 m at the left edge, farther to the right
    floor = 1.0 / (1 / 3.0 + 0.01 * (v - 90) - 0.0006 * u)
    return np.where(v < 90, wall, floor).astype(np.float32)


def test_default_trim_takes_a_cabinets_spill_off_the_wall_and_leaves_doors_alone() -> None:
    """A cabinet 10 cm nearer than the slanted wall around it (less than a depth jump), its
    mask running 12 px onto the wall beside it (a corridor wall at a grazing view): untrimmed,
    the spill is part of the instance; the default ``trim_classes`` hold cabinet, not door,
    and trimming leaves the cabinet without the spill."""
    names = ["background", "person", "cabinet", "door"]
    trim = tuple(names.index(c) for c in PerceptionConfig().trim_classes if c in names)
    assert trim == (2,)
    depth = _wall_and_floor()
    depth += np.random.default_rng(1).normal(0.0, 0.003, depth.shape).astype(np.float32)
    cabinet = np.zeros(depth.shape, bool)
    cabinet[20:80, 100:140] = True
    depth[cabinet] -= 0.1
    classes = np.zeros(depth.shape, np.uint8)
    classes[20:80, 100:152] = 2
    (whole,) = instances_from_classes(classes, depth, names, min_pixels=100)
    assert np.array_equal(whole.mask, classes == 2)
    (inst,) = instances_from_classes(classes, depth, names, min_pixels=100, trim_classes=trim)
    assert (inst.mask & cabinet).sum() > 0.95 * cabinet.sum()
    assert (inst.mask & ~cabinet).sum() < 0.1 * (classes.astype(bool) & ~cabinet).sum()


def test_bleed_onto_the_wall_joining_two_chairs_is_trimmed() -> None:
    """Two chairs leaning on a wall (up to 0.6 m in front of it, meeting it at their sides, so
    no depth jump separates them), the class mask bleeding over the wall between them and the
    floor below: with chair in trim_classes they are two instances, each on its chair;
    without, one. A door flush with the wall is never trimmed (not listed)."""
    depth = _wall_and_floor()
    rng = np.random.default_rng(0)
    depth += rng.normal(0.0, 0.003, depth.shape).astype(np.float32)
    chairs = np.zeros(depth.shape, bool)
    relief = np.zeros(depth.shape)
    tent = 1.0 - np.abs(np.arange(50) - 24.5) / 25.0  # 0.02 at the sides, 1 in the middle
    for c0 in (30, 110):
        chairs[40:85, c0:c0 + 50] = True
        relief[40:85, c0:c0 + 50] = 0.6 * tent[None, :]
    depth -= relief.astype(np.float32)
    classes = np.zeros(depth.shape, np.uint8)
    classes[35:100, 25:165] = 2  # bleed: the wall between the chairs, a band of wall and floor around
    classes[10:30, 170:195] = 3  # a door on the wall
    names = ["background", "person", "chair", "door"]
    joined = instances_from_classes(classes, depth, names, min_pixels=100)
    assert [i.category for i in joined] == ["chair", "door"]
    insts = instances_from_classes(classes, depth, names, min_pixels=100, trim_classes=(2,))
    assert [i.category for i in insts] == ["chair", "chair", "door"]
    for inst in insts[:2]:
        on_chair = (inst.mask & chairs).sum() / inst.mask.sum()
        assert on_chair > 0.95, on_chair
        assert (inst.mask & chairs).sum() > 0.9 * 45 * 50
    assert insts[2].mask.sum() == 20 * 25
    # The planes alone: nothing of the chairs 5 cm or more off the wall, most of the bleed.
    on = off_background_planes(classes == 2, depth)
    assert not (on & (relief > 0.05)).any()
    assert on.sum() > 0.9 * ((classes == 2) & ~chairs).sum()


def test_touching_chairs_in_one_mask_are_split_at_the_gap() -> None:
    """A mask over three touching chairs 2 m away (0.55, 0.45, 0.5 m wide, a 1-pixel seam without
    depth between them) becomes three pieces, each on its chair, or only those pieces large
    enough to measure; a single chair, an unlisted class and a mask without depth stay whole."""
    camera = PinholeCamera(200, 100, 100.0, 100.0, 100.0, 50.0)
    depth = np.full((100, 200), 2.0, np.float32)
    bounds = np.array([30.0, 57.5, 80.0, 105.0])  # pixel columns: 0.5 px = 1 cm at 2 m
    cols = np.arange(200)
    chair_of = np.searchsorted(bounds, cols + 0.5) - 1  # -1 / 3: outside
    depth[:, (cols == 57) | (cols == 80)] = 0.0  # the seams
    mask = np.zeros((100, 200), bool)
    mask[40:80, 30:105] = True
    joined = Instance("chair", 0.9, mask, np.array([30.0, 40.0, 105.0, 80.0]))
    pieces = split_side_by_side([joined], depth, camera, classes=("chair",), width_m=0.5, min_pixels=50)
    assert len(pieces) == 3 and all(p.category == "chair" and p.confidence == 0.9 for p in pieces)
    for k, piece in enumerate(sorted(pieces, key=lambda p: p.box_xyxy[0])):
        on = chair_of[np.nonzero(piece.mask)[1]] == k
        assert on.mean() > 0.95, (k, on.mean())
        assert piece.box_xyxy[0] >= 29 and piece.box_xyxy[2] <= 106
    single = mask.copy()
    single[:, 57:] = False
    for inst, classes, d in ((Instance("chair", 0.9, single, np.zeros(4)), ("chair",), depth),
                             (Instance("door", 0.9, mask, np.zeros(4)), ("chair",), depth),
                             (joined, ("chair",), np.zeros_like(depth))):
        assert split_side_by_side([inst], d, camera, classes=classes, width_m=0.5, min_pixels=50) == [inst]
    # Pieces too small to measure: the mask holds three chairs, so it is not kept whole either.
    one = split_side_by_side([joined], depth, camera, classes=("chair",), width_m=0.5, min_pixels=1050)
    assert len(one) == 1 and (chair_of[np.nonzero(one[0].mask)[1]] == 0).mean() > 0.95
    assert split_side_by_side([joined], depth, camera, classes=("chair",), width_m=0.5, min_pixels=1400) == []
    with pytest.raises(GeometryError):
        split_side_by_side([joined], depth, camera, classes=("chair",), width_m=0.0, min_pixels=50)


def test_one_door_with_a_thin_spill_along_the_wall_is_not_cut() -> None:
    """A 1.2 m door 2 m away (60 columns of 2 cm, 60 rows) whose mask spills 1.2 m further
    along the wall in an 8-row band is 2.4 m wide, two doors' worth at 1.4 m each; but a 1.4 m
    window holds 90 % of its pixels, so it stays whole. Two doors under one mask are cut."""
    camera = PinholeCamera(200, 100, 100.0, 100.0, 100.0, 50.0)
    depth = np.full((100, 200), 2.0, np.float32)
    spill = np.zeros((100, 200), bool)
    spill[20:80, 30:90] = True
    spill[50:58, 90:150] = True
    door = Instance("door", 0.9, spill, box_of_mask(spill))
    assert split_side_by_side([door], depth, camera, classes=("door",), width_m=1.4, min_pixels=50) == [door]
    cut = split_side_by_side([door], depth, camera, classes=("door",), width_m=1.4, min_pixels=50,
                             one_object_share=1.0)
    assert len(cut) == 2  # without the share test the spill makes it two doors
    pair = np.zeros((100, 200), bool)
    pair[20:80, 30:90] = True
    pair[20:80, 110:170] = True
    pair[20:80, 90:110] = True  # the network's mask over the wall between them
    two = Instance("door", 0.9, pair, box_of_mask(pair))
    assert len(split_side_by_side([two], depth, camera, classes=("door",), width_m=1.4, min_pixels=50)) == 2
    with pytest.raises(GeometryError, match="one_object_share"):
        split_side_by_side([door], depth, camera, classes=("door",), width_m=1.4, min_pixels=50,
                           one_object_share=0.0)


def render_doors_on_a_wall(T_world_camera: np.ndarray, door_x: tuple[float, ...]
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth (H, W), door index per pixel (0 = wall, k = door k) and world points (H, W, 3) of
    1.16 x 2.18 m doors centred at ``door_x`` in front of a wall at y = 3.1 m."""
    depth, _ = render_box(T_world_camera, yaw_transform(6.0, 3.15, 0.0, z=1.25), np.array([14.0, 0.1, 2.5]))
    label = np.zeros(depth.shape, int)
    for k, x in enumerate(door_x, 1):
        d, hit = render_box(T_world_camera, yaw_transform(x, 3.07, 0.0, z=1.09), np.array([1.16, 0.06, 2.18]))
        near = hit & ((depth == 0) | (d < depth))
        depth[near], label[near] = d[near], k
    points = (CAMERA.pixel_rays() * depth[..., None]) @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]
    return depth, label, points


def test_twin_doors_cut_by_the_image_border_are_split_from_their_far_end() -> None:
    """A corridor wall seen at a grazing angle: doors A and B 8 cm apart, A cut by the left image
    border, and door C 0.97 m further on. The network's mask covers all three, the 8 cm between
    A and B, and a 0.3 m strip along the floor between B and C. With the doors' usual width the
    mask is cut at the strip (its top lies far below the doors' top line) and the run A + B from
    B's far end, so each piece is on one door and A's piece, widened beyond the border, is
    measured at A. The even cut alone puts a cut inside B. A door in full view with a person in
    front of its lower part, and one door cut by the border with a spill, stay whole; a sliver
    of a door at the border, beyond a gap, is dropped."""
    T = look_at(np.array([2.9, 1.6, 1.05]), np.array([10.3, 2.3, 1.05]))
    door_x = (4.95, 6.19, 8.32)  # A 4.37-5.53, B 5.61-6.77, C 7.74-8.90
    depth, label, points = render_doors_on_a_wall(T, door_x)
    assert label[:, 0].max() == 1 and (label == 2).any() and (label == 3).any()
    x, z = points[..., 0], points[..., 2]
    wall = (label == 0) & (depth > 0)
    strip = wall & (x > 6.7) & (x < 7.8) & (z < 0.3)
    mask = (label > 0) | (wall & (x > 5.5) & (x < 5.65) & (z < 2.18)) | strip
    joined = Instance("door", 0.9, mask, box_of_mask(mask))

    def split(inst: Instance, usual: float | None) -> list[Instance]:
        return split_side_by_side([inst], depth, CAMERA, classes=("door",), width_m=1.4, min_pixels=50,
                                  usual_width_m=usual)

    pieces = sorted(split(joined, 1.2), key=lambda p: p.box_xyxy[0])
    assert len(pieces) == 3
    for k, piece in enumerate(pieces, 1):
        assert np.mean(label[piece.mask] == k) > 0.9, (k, np.bincount(label[piece.mask]))
        assert not (piece.mask & strip).any()
    (a,) = measure_instances([pieces[0]], bgr=BGR, depth_m=depth, camera=CAMERA, T_world_camera=T,
                             keyframe="test/1", stamp=1.0,
                             config=MeasureConfig(clipped_width_m=(("door", 1.2),)))
    assert abs(a.T_world_object[0, 3] - door_x[0]) < 0.15
    even = sorted(split(joined, None), key=lambda p: p.box_xyxy[0])
    assert np.mean(label[even[0].mask] == 1) < 0.85  # the even cut lies inside door B
    # A person before the lower part of a door in full view: the door's top is left, no gap.
    T_front = look_at(np.array([6.19, 0.5, 1.2]), np.array([6.19, 3.0, 1.0]))
    depth, label, _ = render_doors_on_a_wall(T_front, (6.19,))
    door = label == 1
    cols = np.flatnonzero(door.any(axis=0))
    hidden = door.copy()
    hidden[np.flatnonzero(door.any(axis=1))[40]:, cols[30]:cols[50]] = False
    one = Instance("door", 0.9, hidden, box_of_mask(hidden))
    assert split(one, 1.2) == [one]
    # One door cut by the border, its mask spilling 0.25 m onto the wall beyond its far end.
    depth, label, points = render_doors_on_a_wall(T, (5.05,))
    x, z = points[..., 0], points[..., 2]
    spill = (label == 0) & (depth > 0) & (x > 5.63) & (x < 5.88) & (z < 2.18)
    cut_one = Instance("door", 0.9, (label == 1) | spill, box_of_mask((label == 1) | spill))
    assert split(cut_one, 1.2) == [cut_one]
    # A 0.2 m sliver of a door at the border (the image ends at x = 4.91 m), a floor strip, then
    # a whole door: the sliver is dropped, not kept as a door to be widened beyond the border.
    depth, label, points = render_doors_on_a_wall(T, (4.53, 6.38))
    x, z = points[..., 0], points[..., 2]
    strip = (label == 0) & (depth > 0) & (x > 5.1) & (x < 5.81) & (z < 0.3)
    mask = (label > 0) | strip
    assert label[:, 0].max() == 1 and np.ptp(x[label == 1]) < 0.3  # 0.2 m of door A in view
    (kept,) = split(Instance("door", 0.9, mask, box_of_mask(mask)), 1.2)
    assert np.array_equal(kept.mask, label == 2)
    with pytest.raises(GeometryError, match="usual_width_m"):
        split(joined, 0.0)


def test_chair_back_above_its_seat_is_joined_to_it() -> None:
    """Two chairs 2 m away, each cut into an open back (rows 20-39) above its seat (rows 42-79):
    each back joins its own seat; a back over a chair 0.8 m farther, a door, a piece far
    above and one overlapping too little stay apart."""
    camera = PinholeCamera(200, 100, 100.0, 100.0, 100.0, 50.0)
    depth = np.full((100, 200), 2.0, np.float32)
    depth[:40, :] = 2.2  # the backs stand 20 cm behind the seats

    def inst(cat: str, rows: slice, cols: slice, conf: float = 0.9) -> Instance:
        m = np.zeros((100, 200), bool)
        m[rows, cols] = True
        return Instance(cat, conf, m, box_of_mask(m))

    seats = [inst("chair", slice(42, 80), slice(20, 70)), inst("chair", slice(42, 80), slice(80, 130), 0.8)]
    backs = [inst("chair", slice(20, 40), slice(25, 68), 1.0), inst("chair", slice(20, 40), slice(82, 128))]
    out = merge_stacked(seats + backs, depth, camera, classes=("chair",))
    assert len(out) == 2
    for joined, seat, back in zip(out, seats, backs, strict=True):
        assert np.array_equal(joined.mask, seat.mask | back.mask)
        assert joined.box_xyxy[1] == 20 and joined.box_xyxy[3] == 80
    n_seat, n_back = 38 * 50, 20 * 43
    assert out[0].confidence == pytest.approx((0.9 * n_seat + 1.0 * n_back) / (n_seat + n_back))
    far = depth.copy()
    far[:40, :] = 2.8
    assert len(merge_stacked([seats[0], backs[0]], far, camera, classes=("chair",))) == 2
    assert len(merge_stacked([seats[0], backs[0]], depth, camera, classes=("door",))) == 2
    high = inst("chair", slice(0, 25), slice(25, 68))  # 17 rows = 34 cm above the seat
    assert len(merge_stacked([seats[0], high], depth, camera, classes=("chair",))) == 2
    side = inst("chair", slice(20, 40), slice(60, 110))  # covers 10 of the seat's 50 columns
    assert len(merge_stacked([seats[0], side], depth, camera, classes=("chair",))) == 2
    with pytest.raises(GeometryError):
        merge_stacked(seats, depth, camera, classes=("chair",), min_overlap=0.0)


def corridor_depth(wall_m: float = 3.0) -> np.ndarray:
    """Depth (H, W) of a camera 1.05 m above the floor looking level at a wall ``wall_m`` ahead:
    the wall, and the floor in the rows whose ray meets it first."""
    rows = (np.arange(CAMERA.height) - CAMERA.cy) / CAMERA.fy
    with np.errstate(divide="ignore"):
        floor = np.where(rows > 0, 1.05 / rows, np.inf)
    depth = np.minimum(floor, wall_m)[:, None] * np.ones((1, CAMERA.width))
    return depth.astype(np.float32)


T_LEVEL = look_at(np.array([0.0, 0.0, 1.05]), np.array([3.0, 0.0, 1.05]))


def box_instance(category: str, rows: slice, cols: slice) -> Instance:
    m = np.zeros((CAMERA.height, CAMERA.width), bool)
    m[rows, cols] = True
    return Instance(category, 0.9, m, box_of_mask(m))


def test_a_chair_floating_on_the_wall_is_flagged() -> None:
    """A 'chair' 0.7-1.2 m up the wall, 10 cm in front of it, with the wall right below (a fire
    extinguisher the network took for a chair) floats; the same mask with a cart in front
    below it, a chair standing on the floor, a mask running down near the floor without depth
    on its lower part, a mask reaching the image's bottom rows and a door do not."""
    depth = corridor_depth()
    rows, cols = slice(106, 152), slice(150, 166)  # 0.7-1.2 m high at 2.9 m
    depth[rows, cols] = 2.9
    extinguisher = box_instance("chair", rows, cols)
    on_floor = box_instance("chair", slice(136, 230), slice(60, 111))
    standing = depth.copy()
    standing[136:230, 60:111] = 2.5  # 0.9 m tall chair at 2.5 m, its legs on the floor
    gaps = {"chair": 0.6}

    def flags(instances: list[Instance], d: np.ndarray, **kw: object) -> list[bool]:
        return floating_above_floor(instances, d, CAMERA, T_LEVEL, floor_z_m=0.0, max_gap_m=gaps, **kw)

    assert flags([extinguisher, box_instance("door", rows, cols)], depth) == [True, False]
    assert flags([on_floor], standing) == [False]
    occluded = depth.copy()
    occluded[152:212, 140:176] = 2.0  # a cart in front, below it
    assert flags([extinguisher], occluded) == [False]
    legs = depth.copy()
    legs[152:201, cols] = 0.0  # down to 0.16 m at 2.9 m, no depth there; the wall below
    assert flags([box_instance("chair", slice(106, 201), cols)], legs) == [False]
    # Cut by the image's bottom edge (0.75 m above a floor 1 m lower): it may go on below.
    bottom = depth.copy()
    bottom[106:, cols] = 2.9
    low = floating_above_floor([box_instance("chair", slice(106, CAMERA.height - 2), cols)], bottom, CAMERA,
                               T_LEVEL, floor_z_m=-1.0, max_gap_m=gaps)
    assert low == [False]
    assert floating_above_floor([box_instance("chair", slice(106, CAMERA.height - 10), cols)], bottom,
                                CAMERA, T_LEVEL, floor_z_m=-1.0, max_gap_m=gaps) == [True]
    # The same wall patch with the floor 0.2 m higher, or a larger gap, does not float either.
    assert floating_above_floor([extinguisher], depth, CAMERA, T_LEVEL, floor_z_m=0.2,
                                max_gap_m=gaps) == [False]
    assert floating_above_floor([extinguisher], depth, CAMERA, T_LEVEL, floor_z_m=0.0,
                                max_gap_m={"chair": 0.8}) == [False]
    with pytest.raises(GeometryError):
        floating_above_floor([extinguisher], depth, CAMERA, np.eye(3), floor_z_m=0.0, max_gap_m=gaps)
    with pytest.raises(GeometryError):
        flags([extinguisher], depth, open_fraction=0.0)


def test_drop_floating_needs_a_known_floor() -> None:
    from wardmap.server.perception.config import PerceptionConfig
    from wardmap.server.perception.floor import drop_floating, floor_under

    depth = corridor_depth()
    depth[106:152, 150:166] = 2.9
    extinguisher = box_instance("chair", slice(106, 152), slice(150, 166))
    cfg = PerceptionConfig()
    T_base_camera = T_LEVEL.copy()  # its base at the world origin, on the floor
    raised = T_LEVEL.copy()
    raised[2, 3] += 0.4  # the same robot on a floor 0.4 m higher
    assert floor_under(T_LEVEL, T_base_camera) == pytest.approx(0.0)
    assert floor_under(raised, T_base_camera) == pytest.approx(0.4)
    assert drop_floating([extinguisher], depth, CAMERA, cfg, T_LEVEL, 0.0) == ([], 1)
    assert drop_floating([extinguisher], depth, CAMERA, cfg, T_LEVEL, None) == ([extinguisher], 0)
    off = PerceptionConfig(floor_gap_m=())
    assert drop_floating([extinguisher], depth, CAMERA, off, T_LEVEL, 0.0) == ([extinguisher], 0)
    with pytest.raises(ConfigError, match="floor_gap_m"):
        PerceptionConfig(floor_gap_m=(("chair", -0.1),))


def room_depth(wall_m: float = 4.0, ceiling_m: float = 2.6) -> np.ndarray:
    """Depth (H, W) of the camera of ``T_LEVEL`` (1.05 m up, looking level) at a wall ``wall_m``
    ahead, with the floor and a ceiling ``ceiling_m`` high where their rays meet them first."""
    rows = (np.arange(CAMERA.height) - CAMERA.cy) / CAMERA.fy
    with np.errstate(divide="ignore"):
        floor = np.where(rows > 0, 1.05 / rows, np.inf)
        ceiling = np.where(rows < 0, (ceiling_m - 1.05) / -rows, np.inf)
    depth = np.minimum(np.minimum(floor, ceiling), wall_m)[:, None] * np.ones((1, CAMERA.width))
    return depth.astype(np.float32)


def test_a_strip_of_wall_taken_for_a_cabinet_is_a_piece_of_a_taller_surface() -> None:
    """A 'cabinet' at the image's left border that is a strip of the wall 4 m ahead: the wall
    goes on above it into the ceiling (2.6 m), so it is flagged. A 1.9 m cabinet 0.5 m in
    front of that wall, its mask cut short of its top, its mask running onto the wall above
    it, the strip as a door, or with the floor 0.5 m higher are not."""
    depth = room_depth()
    top = {}

    def flags(instances: list[Instance], d: np.ndarray, floor_z: float = 0.0, **kw: object) -> list[bool]:
        return part_of_taller_surface(instances, d, CAMERA, T_LEVEL, floor_z_m=floor_z,
                                      max_top_m={"cabinet": 2.1}, **kw)

    strip = box_instance("cabinet", slice(130, 200), slice(0, 20))
    assert flags([strip, box_instance("door", slice(130, 200), slice(0, 20))], depth) == [True, False]
    assert flags([strip], depth, floor_z=0.5) == [False]  # the ceiling is then 2.1 m up
    cabinet = depth.copy()
    cabinet[56:199, 100:160] = 3.5  # 0-1.9 m high at 3.5 m, the wall 0.5 m behind it
    top["whole"] = box_instance("cabinet", slice(56, 199), slice(100, 160))
    top["cut short"] = box_instance("cabinet", slice(90, 199), slice(100, 160))
    top["onto the wall"] = box_instance("cabinet", slice(46, 199), slice(100, 160))
    assert flags(list(top.values()), cabinet) == [False, False, False]
    # The same region in the plane of the wall is a piece of it.
    assert flags([top["whole"]], depth) == [True]
    with pytest.raises(GeometryError):
        part_of_taller_surface([strip], depth, CAMERA, np.eye(3), floor_z_m=0.0, max_top_m={"cabinet": 2.1})
    with pytest.raises(GeometryError):
        flags([strip], depth, on_share=0.0)


def test_drop_wall_pieces_by_default_and_only_with_a_floor() -> None:
    from wardmap.server.perception.floor import drop_wall_pieces

    strip = box_instance("cabinet", slice(130, 200), slice(0, 20))
    chair = box_instance("chair", slice(150, 199), slice(100, 140))
    depth = room_depth()
    depth[150:199, 100:140] = 3.0  # a chair-high box on the floor, 1 m in front of the wall
    cfg = PerceptionConfig()
    assert ("cabinet", 2.1) in cfg.max_top_m and "door" not in dict(cfg.max_top_m)
    assert drop_wall_pieces([strip, chair], depth, CAMERA, cfg, T_LEVEL, 0.0) == ([chair], 1)
    assert drop_wall_pieces([strip], depth, CAMERA, cfg, T_LEVEL, None) == ([strip], 0)
    off = PerceptionConfig(max_top_m=())
    assert drop_wall_pieces([strip], depth, CAMERA, off, T_LEVEL, 0.0) == ([strip], 0)
    with pytest.raises(ConfigError, match="max_top_m"):
        PerceptionConfig(max_top_m=(("cabinet", 0.0),))


def test_a_strip_of_floor_taken_for_a_cart_lies_flat_on_the_floor() -> None:
    """A 'cart' that is a strip of floor 2.5-2.7 m ahead is flagged, also under the nearer front
    of a bed's footboard; a cart standing there, a strip reaching the image's top rows, a strip
    without depth and the strip as an IV pole are not."""
    depth = corridor_depth(wall_m=4.0)
    rows, cols = slice(222, 230), slice(100, 160)  # floor rows 2.5-2.7 m ahead
    strip = box_instance("cart", rows, cols)
    tops = {"cart": 0.2}

    def flags(instances: list[Instance], d: np.ndarray, floor_z: float = 0.0, **kw: object) -> list[bool]:
        return flat_on_floor(instances, d, CAMERA, T_LEVEL, floor_z_m=floor_z, min_top_m=tops, **kw)

    assert flags([strip, box_instance("iv_pole", rows, cols)], depth) == [True, False]
    standing = depth.copy()
    standing[136:230, cols] = 2.5  # a 0.9 m cart at 2.5 m
    assert flags([box_instance("cart", slice(136, 230), cols)], standing) == [False]
    assert flags([box_instance("cart", slice(136, 230), cols)], standing, top_percentile=5.0) == [True]
    bed = depth.copy()
    bed[170:222, 90:170] = 2.3  # a footboard 0.2 m nearer, right above the strip
    assert flags([strip], bed) == [True]
    # The wall's top rows, 0-0.12 m above a floor put at 2.75 m: the mask may go on above the image.
    assert flags([box_instance("cart", slice(0, 9), cols)], depth, floor_z=2.75) == [False]
    assert flags([box_instance("cart", slice(4, 13), cols)], depth, floor_z=2.75) == [True]
    blind = depth.copy()
    blind[rows, cols] = 0.0
    assert flags([strip], blind) == [False]
    with pytest.raises(GeometryError):
        flags([strip], depth, top_percentile=0.0)
    with pytest.raises(GeometryError):
        flat_on_floor([strip], depth, CAMERA, np.eye(3), floor_z_m=0.0, min_top_m=tops)


def test_drop_floor_pieces_by_default_and_only_with_a_floor() -> None:
    from wardmap.server.perception.floor import drop_floor_pieces

    strip = box_instance("cart", slice(222, 230), slice(100, 160))
    depth = corridor_depth(wall_m=4.0)
    cfg = PerceptionConfig()
    assert dict(cfg.min_top_m).get("cart") == 0.2 and "iv_pole" not in dict(cfg.min_top_m)
    assert drop_floor_pieces([strip], depth, CAMERA, cfg, T_LEVEL, 0.0) == ([], 1)
    assert drop_floor_pieces([strip], depth, CAMERA, cfg, T_LEVEL, None) == ([strip], 0)
    off = PerceptionConfig(min_top_m=())
    assert drop_floor_pieces([strip], depth, CAMERA, off, T_LEVEL, 0.0) == ([strip], 0)
    with pytest.raises(ConfigError, match="min_top_m"):
        PerceptionConfig(min_top_m=(("cart", 0.0),))


def test_no_planes_without_depth_around() -> None:
    mask = np.zeros((40, 40), bool)
    mask[10:30, 10:30] = True
    assert not off_background_planes(mask, np.zeros((40, 40), np.float32)).any()
    assert not off_background_planes(np.zeros((40, 40), bool), np.ones((40, 40), np.float32)).any()


def test_gt_instance_attached_by_majority() -> None:
    labels = np.zeros((20, 20), np.uint16)
    labels[:, :12] = 5
    mask = np.zeros((20, 20), bool)
    mask[:, 4:16] = True  # 8/12 columns on id 5
    assert gt_instance_of(mask, labels) == 5
    mask[:, :] = False
    mask[:, 8:20] = True  # 4/12 on id 5, rest on 0
    assert gt_instance_of(mask, labels) is None
    inst = Instance("door", 0.5, mask, np.zeros(4))
    assert attach_gt_instances([inst], labels, min_fraction=0.3)[0].gt_instance == 5


def test_drop_misplaced_runs_the_three_floor_checks_and_counts_each() -> None:
    """One call for the server, the offline runner and the bench: a floating "chair", a
    "cabinet" strip of wall and a "cart" strip on the floor are each left out by their own
    check and counted there; a standing chair stays; no floor keeps all four."""
    from wardmap.server.perception.floor import LeftOut, drop_misplaced

    depth = room_depth()
    depth[150:199, 100:140] = 3.0  # a chair-high box on the floor, 1 m in front of the wall
    depth[106:152, 200:216] = 2.9  # a box hanging on the wall, clear of the floor
    depth[222:230, 250:300] = 3.5  # a strip along the floor
    chair = box_instance("chair", slice(150, 199), slice(100, 140))
    floating = box_instance("chair", slice(106, 152), slice(200, 216))
    strip = box_instance("cabinet", slice(130, 200), slice(0, 20))
    flat = box_instance("cart", slice(222, 230), slice(250, 300))
    given = [chair, floating, strip, flat]
    cfg = PerceptionConfig()
    assert drop_misplaced(given, depth, CAMERA, cfg, T_LEVEL, 0.0) == ([chair], LeftOut(1, 1, 1))
    assert drop_misplaced(given, depth, CAMERA, cfg, T_LEVEL, None) == (given, LeftOut(0, 0, 0))

"""Instances from class maps and ground truth, and their split into one instance per object
(``server/perception/instances.py``), on synthetic scenes with known ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from perception_scenes import (
    BGR,
    CAMERA,
    look_at,
    render_doors_on_a_wall,
)

from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.perception.instances import (
    attach_gt_instances,
    gt_instance_of,
    id_to_class,
    instances_from_classes,
    merge_stacked,
    off_background_planes,
    oracle_instances,
    split_instances,
    split_side_by_side,
)
from wardmap.server.perception.masks import box_of_mask
from wardmap.server.perception.measure import (
    MeasureConfig,
    measure_instances,
)
from wardmap.server.perception.types import Instance
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import DatasetError, GeometryError


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


def test_no_planes_without_depth_around() -> None:
    mask = np.zeros((40, 40), bool)
    mask[10:30, 10:30] = True
    assert not off_background_planes(mask, np.zeros((40, 40), np.float32)).any()
    assert not off_background_planes(np.zeros((40, 40), bool), np.ones((40, 40), np.float32)).any()


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


def test_split_instances_cuts_door_pairs_and_joins_iv_pole_parts() -> None:
    """Default config, 3 m away (1 px = 3 cm): one door mask 2.7 m wide (two doors and the wall
    between) becomes two pieces; a single door (1.2 m) stays whole; an IV pole's bag 0.8 m above
    its base joins it, while two chair pieces as far apart stay two; a detector's instances are
    returned as they are."""
    camera = PinholeCamera(400, 300, 100.0, 100.0, 200.0, 150.0)
    depth = np.full((300, 400), 3.0, np.float32)

    def inst(cat: str, rows: slice, cols: slice) -> Instance:
        m = np.zeros((300, 400), bool)
        m[rows, cols] = True
        return Instance(cat, 0.9, m, box_of_mask(m))

    cfg = PerceptionConfig()
    pair = inst("door", slice(40, 110), slice(100, 190))
    pieces = split_instances([pair], depth, camera, cfg, "model")
    assert len(pieces) == 2 and all(p.category == "door" for p in pieces)
    widths = sorted(float(p.box_xyxy[2] - p.box_xyxy[0]) * 0.03 for p in pieces)
    assert widths[0] >= 1.0 and widths[1] <= 1.7, widths
    single = inst("door", slice(40, 110), slice(100, 140))
    assert split_instances([single], depth, camera, cfg, "model") == [single]
    upper, lower = (slice(230, 243), slice(195, 205)), (slice(270, 280), slice(190, 210))
    bag, base = inst("iv_pole", *upper), inst("iv_pole", *lower)
    (pole,) = split_instances([base, bag], depth, camera, cfg, "model")
    assert np.array_equal(pole.mask, base.mask | bag.mask)
    back, seat = inst("chair", *upper), inst("chair", *lower)
    assert len(split_instances([seat, back], depth, camera, cfg, "model")) == 2
    assert split_instances([pair, base, bag], depth, camera, cfg, "yolox:x.onnx") == [pair, base, bag]

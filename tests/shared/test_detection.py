"""Tests of wardmap.shared.detection: YOLOX decoding, NMS, the COCO class map, depth masks."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from wardmap.shared.detection import (
    LETTERBOX_PAD,
    CocoMap,
    Detections,
    MaskConfig,
    decode_yolox,
    detection_labels,
    labels_from_detections,
    letterbox,
    nms_per_class,
)
from wardmap.shared.errors import ConfigError, GeometryError
from wardmap.shared.knowledge import KnowledgeGraph

ANCHORS_416 = 52 * 52 + 26 * 26 + 13 * 13
COCO_PERSON, COCO_CHAIR, COCO_TV, COCO_LAPTOP = 0, 56, 62, 63
COCO_CUP, COCO_TABLE = 41, 60


@pytest.fixture(scope="module")
def kg() -> KnowledgeGraph:
    return KnowledgeGraph.load()


@pytest.fixture(scope="module")
def coco() -> CocoMap:
    return CocoMap.load()


def anchor_index(stride: int, gx: int, gy: int) -> int:
    """Row of grid cell (gx, gy) of ``stride`` in a 416 x 416 YOLOX output."""
    offset = {8: 0, 16: 52 * 52, 32: 52 * 52 + 26 * 26}[stride]
    return offset + gy * (416 // stride) + gx


def set_anchor(out: np.ndarray, stride: int, gx: int, gy: int, centre: tuple[float, float],
               size: tuple[float, float], obj: float, cls: int, cls_score: float) -> None:
    """Write raw outputs that decode to a box of ``centre``/``size`` in letterboxed pixels."""
    row = out[0, anchor_index(stride, gx, gy)]
    row[0] = centre[0] / stride - gx
    row[1] = centre[1] / stride - gy
    row[2] = math.log(size[0] / stride)
    row[3] = math.log(size[1] / stride)
    row[4] = obj
    row[5 + cls] = cls_score


# ------------------------------------------------------------------------- letterbox / decode


def test_letterbox_resizes_top_left_and_pads_with_114() -> None:
    """Scenario: a uniform 640 x 480 image: ratio 0.65, content in the top-left 416 x 312,
    padding value 114 below, channels first, float32."""
    image = np.full((480, 640, 3), (10, 20, 30), dtype=np.uint8)
    blob, ratio = letterbox(image, 416)
    assert blob.shape == (1, 3, 416, 416) and blob.dtype == np.float32
    assert ratio == pytest.approx(0.65)
    np.testing.assert_array_equal(blob[0, :, :312, :], np.array([10, 20, 30], np.float32)[:, None, None]
                                  * np.ones((1, 312, 416), np.float32))
    assert np.all(blob[0, :, 312:, :] == LETTERBOX_PAD)
    with pytest.raises(GeometryError):
        letterbox(np.zeros((10, 10), np.uint8))


def test_decode_gives_the_planted_box_in_original_pixels() -> None:
    """Scenario: an all-zero output with one stride-16 anchor set to a tv box of centre
    (164, 120) and size 64 x 96 in letterboxed pixels, objectness 0.9 and class score 0.8;
    decoding with the ratio of a 640 x 480 image gives that box divided by the ratio."""
    out = np.zeros((1, ANCHORS_416, 85), np.float32)
    set_anchor(out, 16, 10, 7, (164.0, 120.0), (64.0, 96.0), 0.9, COCO_TV, 0.8)
    _, ratio = letterbox(np.zeros((480, 640, 3), np.uint8))
    det = decode_yolox(out, ratio, (640, 480))
    assert len(det) == 1
    np.testing.assert_allclose(det.boxes_xyxy[0], np.array([132, 72, 196, 168]) / ratio, rtol=1e-5)
    assert det.scores[0] == pytest.approx(0.72)
    assert det.coco_class.tolist() == [COCO_TV]
    assert det.image_wh == (640, 480)


def test_decode_thresholds_scores_and_clips_to_the_image() -> None:
    """Scenario: a box below the score threshold is dropped; a box running over the image
    border is clipped to it."""
    out = np.zeros((1, ANCHORS_416, 85), np.float32)
    set_anchor(out, 8, 3, 3, (30.0, 30.0), (20.0, 20.0), 0.5, COCO_PERSON, 0.5)  # score 0.25
    set_anchor(out, 32, 12, 9, (400.0, 300.0), (64.0, 64.0), 0.9, COCO_PERSON, 0.9)
    det = decode_yolox(out, 1.0, (416, 312), score_threshold=0.3)
    assert len(det) == 1
    np.testing.assert_allclose(det.boxes_xyxy[0], [368, 268, 416, 312])


def test_nms_removes_a_duplicate_of_the_same_class_only() -> None:
    """Scenario: two heavily overlapping person boxes from neighbouring anchors and a chair
    box at the same place: the weaker person box goes, the chair stays (per-class NMS)."""
    out = np.zeros((1, ANCHORS_416, 85), np.float32)
    set_anchor(out, 16, 10, 10, (168.0, 168.0), (80.0, 160.0), 0.95, COCO_PERSON, 0.9)
    set_anchor(out, 16, 11, 10, (172.0, 170.0), (80.0, 156.0), 0.9, COCO_PERSON, 0.8)
    set_anchor(out, 16, 10, 11, (170.0, 170.0), (80.0, 160.0), 0.9, COCO_CHAIR, 0.7)
    det = decode_yolox(out, 1.0, (416, 416))
    assert sorted(det.coco_class.tolist()) == [COCO_PERSON, COCO_CHAIR]
    assert det.scores[0] == pytest.approx(0.95 * 0.9)
    assert np.all(np.diff(det.scores) <= 0)


def test_nms_per_class_direct() -> None:
    """Scenario: greedy per-class NMS on hand-made boxes: IoU 0.81 suppressed, IoU 0.14 kept,
    another class never suppressed."""
    boxes = np.array([[0, 0, 10, 10], [0, 0, 9, 9], [8, 8, 18, 18], [0, 0, 10, 10]], float)
    scores = np.array([0.9, 0.8, 0.7, 0.6])
    classes = np.array([0, 0, 0, 1])
    assert nms_per_class(boxes, scores, classes, 0.45).tolist() == [0, 2, 3]


def test_decode_rejects_a_wrong_layout() -> None:
    """Scenario: an output whose row count fits no square YOLOX input, or a bad ratio."""
    with pytest.raises(GeometryError):
        decode_yolox(np.zeros((1, 1000, 85), np.float32), 1.0, (416, 416))
    with pytest.raises(GeometryError):
        decode_yolox(np.zeros((1, ANCHORS_416, 85), np.float32), 0.0, (416, 416))
    assert len(decode_yolox(np.zeros((1, 8400, 85), np.float32), 1.0, (640, 640))) == 0  # 640 input


# ------------------------------------------------------------------------- class map


def test_packaged_coco_map(coco: CocoMap, kg: KnowledgeGraph) -> None:
    """Scenario: the packaged map has the 80 COCO classes in order; person -> person, tv ->
    wall_monitor, laptop ignored; every mapped name is a knowledge-graph class."""
    assert len(coco.names) == 80
    assert coco.names[0] == "person" and coco.names[79] == "toothbrush"
    assert coco.id_of("tv") == COCO_TV
    assert coco.kg_class(COCO_PERSON) == "person"
    assert coco.kg_class(COCO_TV) == "wall_monitor"
    assert coco.kg_class(COCO_LAPTOP) is None
    lut = coco.kg_lut(kg)
    assert lut[COCO_PERSON] == kg.index_of("person")
    assert lut[COCO_LAPTOP] == -1
    assert set(coco.to_kg.values()) <= set(kg.names)


@pytest.mark.parametrize(
    "text",
    [
        'version = 1\nclasses = [{ id = 1, name = "a" }]\n',
        'version = 2\nclasses = [{ id = 0, name = "a" }]\n',
        'version = 1\nclasses = [{ id = 0, name = "a", colour = 3 }]\n',
        'version = 1\nclasses = [{ id = 0, name = "a" }, { id = 1, name = "a" }]\n',
        'version = 1\nclasses = [{ id = 0, name = "a", kg = "Not A Name" }]\n',
        "version = 1\nclasses = [\n",
    ],
)
def test_malformed_coco_map_files(tmp_path: Path, text: str) -> None:
    """Scenario: wrong id order, unknown version, unknown key, duplicate name, bad kg name,
    broken TOML: each raises ConfigError."""
    path = tmp_path / "map.toml"
    path.write_text(text)
    with pytest.raises(ConfigError):
        CocoMap.load(path)


def test_coco_map_naming_an_unknown_kg_class(tmp_path: Path, kg: KnowledgeGraph) -> None:
    """Scenario: a map sending a class to 'spaceship', which the knowledge graph lacks."""
    path = tmp_path / "map.toml"
    path.write_text('version = 1\nclasses = [{ id = 0, name = "person", kg = "spaceship" }]\n')
    with pytest.raises(ConfigError, match="spaceship"):
        CocoMap.load(path).kg_lut(kg)
    with pytest.raises(ConfigError):
        CocoMap.load(tmp_path / "missing.toml")


# ------------------------------------------------------------------------- label images


def wall_and_person(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """120 x 160 depth: a far wall at 4 m (noise 1 cm) and a person-shaped block at 1.5 m
    (rows 30..99, columns 65..94, with a 10 x 10 hole of missing depth in its middle);
    returns depth and the block's mask."""
    depth = (4.0 + rng.normal(0, 0.01, (120, 160))).astype(np.float32)
    person = np.zeros((120, 160), bool)
    person[30:100, 65:95] = True
    person[30:45, 60:65] = True  # an arm
    depth[person] = (1.5 + rng.normal(0, 0.01, int(person.sum()))).astype(np.float32)
    depth[60:70, 75:85] = 0.0
    return depth, person


def detections(boxes: list[list[float]], scores: list[float], classes: list[int],
               wh: tuple[int, int] = (160, 120)) -> Detections:
    return Detections(np.array(boxes, np.float32).reshape(-1, 4), np.array(scores, np.float32),
                      np.array(classes, np.int64), wh)


def test_depth_mask_marks_the_near_person_and_not_the_wall(coco: CocoMap, kg: KnowledgeGraph) -> None:
    """Scenario: a person box (columns 50..110, rows 20..110) around the near block in front
    of the far wall: nearly all block pixels (including the depth hole) become person with
    instance 1, no wall pixel does."""
    rng = np.random.default_rng(10)
    depth, person = wall_and_person(rng)
    det = detections([[50, 20, 110, 110]], [0.9], [COCO_PERSON])
    class_image, instance_image = labels_from_detections(det, coco, kg, depth, min_score=0.3)
    assert class_image.dtype == np.uint8 and instance_image.dtype == np.uint16
    marked = class_image == kg.index_of("person")
    assert np.mean(marked[person]) >= 0.95
    assert np.all(marked[60:70, 75:85])  # the depth hole is filled
    assert not np.any(marked & ~person)
    np.testing.assert_array_equal(instance_image > 0, marked)
    assert set(np.unique(instance_image).tolist()) == {0, 1}


def test_without_depth_the_shrunken_box_is_filled(coco: CocoMap, kg: KnowledgeGraph) -> None:
    """Scenario: no depth image: the 60 x 90 box scaled by 0.9 about its centre is filled."""
    det = detections([[50, 20, 110, 110]], [0.9], [COCO_PERSON])
    class_image, instance_image = labels_from_detections(det, coco, kg, None)
    expected = np.zeros((120, 160), bool)
    expected[24:106, 53:107] = True
    np.testing.assert_array_equal(class_image == kg.index_of("person"), expected)
    np.testing.assert_array_equal(instance_image == 1, expected)


def test_nearer_instances_are_painted_over_farther_ones(coco: CocoMap, kg: KnowledgeGraph) -> None:
    """Scenario: a chair at 3 m (columns 20..79) partly behind the 1.5 m person, each with its
    box; the chair box scores higher (instance 1) but the person wins where they overlap."""
    rng = np.random.default_rng(11)
    depth, person = wall_and_person(rng)
    chair = np.zeros_like(person)
    chair[50:110, 20:80] = True
    depth[chair & ~person] = 3.0
    det = detections([[20, 50, 80, 110], [50, 20, 110, 110]], [0.95, 0.8], [COCO_CHAIR, COCO_PERSON])
    class_image, instance_image = labels_from_detections(det, coco, kg, depth)
    overlap = chair & person
    assert np.mean(class_image[overlap] == kg.index_of("person")) >= 0.95
    assert np.mean(class_image[chair & ~person] == kg.index_of("chair")) >= 0.9
    assert np.mean(instance_image[chair & ~person] == 1) >= 0.9
    assert np.mean(instance_image[person] == 2) >= 0.95


def test_ignored_classes_and_low_scores_paint_nothing(coco: CocoMap, kg: KnowledgeGraph) -> None:
    """Scenario: a laptop (no knowledge-graph class) and a person below min_score."""
    det = detections([[10, 10, 60, 60], [70, 10, 120, 60]], [0.9, 0.2], [COCO_LAPTOP, COCO_PERSON])
    class_image, instance_image = labels_from_detections(det, coco, kg, None, min_score=0.3)
    assert not class_image.any() and not instance_image.any()


def test_depth_of_the_wrong_size_is_rejected(coco: CocoMap, kg: KnowledgeGraph) -> None:
    """Scenario: a depth image that does not match the detections' image size."""
    det = detections([[10, 10, 60, 60]], [0.9], [COCO_PERSON])
    with pytest.raises(GeometryError):
        labels_from_detections(det, coco, kg, np.ones((10, 10), np.float32))
    with pytest.raises(ConfigError):
        MaskConfig(band_m=0.0)


def desk_with_cups(rng: np.random.Generator) -> np.ndarray:
    """120 x 160 depth: a far wall at 4 m, a desk top seen from above at an angle (rows 40..99,
    columns 20..139; 1.8 m at its far edge, row 40, to 1.2 m at its near edge) and two cups
    standing at its back at 1.68 m (rows 45..64, columns 40..54 and 100..114), farther than
    most of the desk: depth noise 5 mm."""
    depth = (4.0 + rng.normal(0, 0.005, (120, 160))).astype(np.float32)
    ramp = np.linspace(1.8, 1.2, 60, dtype=np.float32)[:, None]
    depth[40:100, 20:140] = ramp + rng.normal(0, 0.005, (60, 120))
    depth[45:65, 40:55] = 1.68 + rng.normal(0, 0.005, (20, 15))
    depth[45:65, 100:115] = 1.68 + rng.normal(0, 0.005, (20, 15))
    return depth


def test_a_desk_mask_never_swallows_the_cups_on_it(coco: CocoMap, kg: KnowledgeGraph) -> None:
    """Scenario: a desk box around the desk and two cup boxes inside it, the desk scoring highest
    and the cups within its depth band: every cup pixel is cup (its own instance), no cup
    pixel is desk, and the desk keeps the rest of its surface."""
    depth = desk_with_cups(np.random.default_rng(20))
    det = detections([[18, 38, 142, 102], [38, 43, 57, 67], [98, 43, 117, 67]], [0.9, 0.6, 0.5],
                     [COCO_TABLE, COCO_CUP, COCO_CUP])
    class_image, instance_image = labels_from_detections(det, coco, kg, depth)
    cup, desk = kg.index_of("cup"), kg.index_of("desk")
    for k, cols in ((2, slice(40, 55)), (3, slice(100, 115))):
        assert np.mean(class_image[45:65, cols] == cup) >= 0.9
        assert np.mean(instance_image[45:65, cols] == k) >= 0.9
        assert not np.any(class_image[45:65, cols] == desk)
    rest = np.zeros((120, 160), bool)
    rest[40:100, 20:140] = True
    rest[40:70, 35:60] = rest[40:70, 95:120] = False
    assert np.mean(class_image[rest] == desk) >= 0.9


def test_a_box_only_partly_over_another_keeps_its_pixels(coco: CocoMap, kg: KnowledgeGraph) -> None:
    """Scenario: the chair box overlaps the person box by half: not inside it, so the person's
    mask is not cut by the chair's (the nearer object still wins where masks overlap)."""
    rng = np.random.default_rng(21)
    depth, person = wall_and_person(rng)
    det = detections([[50, 20, 110, 110], [20, 50, 80, 110]], [0.9, 0.8], [COCO_PERSON, COCO_CHAIR])
    labels = detection_labels(det, coco, kg, depth)
    assert np.mean(labels.class_image[person] == kg.index_of("person")) >= 0.95
    assert labels.implausible == ()


def test_a_mask_larger_than_its_class_is_dropped(coco: CocoMap, kg: KnowledgeGraph) -> None:
    """Scenario: a "cup" box over the 30 x 70 px block at 1.5 m: at 160 px across a 45 deg view
    (the narrowest lens the gate assumes) the block is at least 0.5 m tall, more than any cup
    (0.3 m): reported, no pixel painted. A real cup (15 x 20 px at 1.45 m, at least 0.15 m)
    stays."""
    rng = np.random.default_rng(22)
    depth, _ = wall_and_person(rng)
    depth[5:25, 120:135] = 1.45
    det = detections([[50, 20, 110, 110], [118, 3, 137, 27]], [0.9, 0.8], [COCO_CUP, COCO_CUP])
    labels = detection_labels(det, coco, kg, depth)
    assert labels.implausible == (1,)
    assert not np.any(labels.instance_image == 1)
    assert np.mean(labels.class_image[5:25, 120:135] == kg.index_of("cup")) >= 0.9
    tele = detection_labels(det, coco, kg, depth, config=MaskConfig(min_hfov_deg=10.0))
    assert tele.implausible == ()  # behind a 10 deg lens 70 px at 1.5 m may be 0.12 m: kept


def test_no_size_gate_without_depth(coco: CocoMap, kg: KnowledgeGraph) -> None:
    """Scenario: the same large cup box without depth: its size is unknown, so it is kept."""
    det = detections([[50, 20, 110, 110]], [0.9], [COCO_CUP])
    labels = detection_labels(det, coco, kg, None)
    assert labels.implausible == () and labels.class_image.any()


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ("[max_size_m]\ncup = 0\n", "positive"),
        ("[max_size_m]\ncup = true\n", "positive"),
        ("[max_size_m]\nCup = 0.2\n", "snake_case"),
        ("max_size_m = 3\n", "table"),
    ],
)
def test_bad_max_size_table(tmp_path: Path, table: str, message: str) -> None:
    path = tmp_path / "map.toml"
    path.write_text('version = 1\nclasses = [{ id = 0, name = "cup", kg = "cup" }]\n' + table)
    with pytest.raises(ConfigError, match=message):
        CocoMap.load(path)


def test_max_size_of_an_unknown_class_fails_against_the_graph(tmp_path: Path, kg: KnowledgeGraph) -> None:
    path = tmp_path / "map.toml"
    path.write_text('version = 1\nclasses = [{ id = 0, name = "cup", kg = "cup" }]\n'
                    '[max_size_m]\nmug = 0.2\n')
    with pytest.raises(ConfigError, match="mug"):
        CocoMap.load(path).kg_lut(kg)


def test_packaged_table_maps_no_appliance_or_sofa(coco: CocoMap, kg: KnowledgeGraph) -> None:
    """The reviewed table: a refrigerator, microwave, oven, toaster or couch is no hospital
    object; every mapped class has a size bound; the mapped rows are exactly the reviewed ones."""
    for name in ("refrigerator", "microwave", "oven", "toaster", "couch", "hair drier"):
        assert coco.kg_class(coco.id_of(name)) is None, name
    mapped = {coco.names[i]: k for i, k in coco.to_kg.items()}
    assert mapped == {"person": "person", "chair": "chair", "wine glass": "cup", "cup": "cup", "bed": "bed",
                      "dining table": "desk", "tv": "wall_monitor", "sink": "sink"}
    assert set(mapped.values()) == set(coco.max_size_m)
    coco.kg_lut(kg)

"""Segmenter adapters: the ONNX contract of the trained network, start-up checks, YOLOX on TUM."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from types import ModuleType

import cv2
import numpy as np
import pytest

from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.perception.models import OnnxSegmenter, YoloxDetector, make_segmenter, packaged_model_path
from wardmap.shared.errors import ConfigError, GeometryError

pytest.importorskip("onnx", reason="building test models needs the onnx package (dev dependency)")

REPO = Path(__file__).resolve().parents[3]
SHARED = REPO.parent / "shared"
YOLOX = SHARED / "models" / "yolox_nano.onnx"
TUM = SHARED / "data" / "tum_fr1_rpy_s3_first100"


def _helper() -> ModuleType:
    spec = importlib.util.spec_from_file_location("tiny_onnx", Path(__file__).with_name("tiny_onnx.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


tiny = _helper()


def scene() -> tuple[np.ndarray, np.ndarray]:
    """64 x 48 BGR image: red block (person) at 2 m, green block (door) at 3 m, grey rest."""
    bgr = np.full((48, 64, 3), 90, np.uint8)
    bgr[8:24, 4:20] = (0, 0, 255)  # red in BGR order
    bgr[20:44, 36:60] = (0, 255, 0)
    depth = np.full((48, 64), 5.0, np.float32)
    depth[8:24, 4:20] = 2.0
    depth[20:44, 36:60] = 3.0
    return bgr, depth


def test_class_mapping_of_the_onnx_contract(tmp_path: Path) -> None:
    """Logit channel i is the i-th knowledge-graph class; RGB order, resize and softmax are right."""
    seg = OnnxSegmenter(tiny.write_tiny_seg(tmp_path / "m.onnx"), kg=None, min_pixels=10, refine_edges=False)
    names = seg.class_names
    assert names == tuple(tiny.kg_classes()) and names[0] == "background"
    bgr, depth = scene()
    out = seg.segment(bgr, depth)
    assert out.class_map.shape == (48, 64) and out.class_map.dtype == np.uint8
    assert np.all(out.class_map[8:24, 4:20] == names.index("person"))
    assert np.all(out.class_map[20:44, 36:60] == names.index("door"))
    assert np.count_nonzero(out.class_map) == 16 * 16 + 24 * 24
    # logits (background 0, person 5, others -100): softmax max = 1 / (1 + e^-5).
    assert out.confidence[10, 10] == pytest.approx(1 / (1 + math.exp(-5)), rel=1e-4)
    got = sorted((i.category, int(i.mask.sum()), tuple(i.box_xyxy)) for i in out.instances)
    assert got == [("door", 576, (36.0, 20.0, 60.0, 44.0)), ("person", 256, (4.0, 8.0, 20.0, 24.0))]
    assert [i.category for i in seg(bgr, depth)] == [i.category for i in out.instances]
    # A blue image (BGR order!) is not red: all background.
    blue = np.zeros_like(bgr)
    blue[..., 0] = 255
    assert not seg.segment(blue, None).class_map.any()


def test_refined_edges_move_only_boundary_pixels(tmp_path: Path) -> None:
    """refine_edges (the default): the 32 x 24 network's class boundaries are taken from its
    bilinearly upsampled logits. The tiny model's grey background has person logit -1.5
    against 0, so the person block grows by a pixel where the red cells' +5 outweighs it;
    pixels away from a boundary keep their class. Instances come from the nearest cells' map."""
    path = tiny.write_tiny_seg(tmp_path / "m.onnx")
    bgr, depth = scene()
    coarse = OnnxSegmenter(path, refine_edges=False).segment(bgr, depth).class_map
    fine = make_segmenter(str(path)).segment(bgr, depth).class_map
    changed = fine != coarse
    assert changed.any()
    near_edge = cv2.dilate(cv2.Canny(coarse * 50, 1, 1), np.ones((5, 5), np.uint8)) > 0
    assert not (changed & ~near_edge).any()
    assert np.all(fine[8:24, 4:20] == tiny.kg_classes().index("person"))
    # Instances keep the nearest cells' classes: the 16 x 16 person block, not the grown one.
    instances = OnnxSegmenter(path, min_pixels=10).segment(bgr, depth).instances
    person = [i for i in instances if i.category == "person"]
    assert len(person) == 1 and int(person[0].mask.sum()) == 16 * 16
    assert int((fine == tiny.kg_classes().index("person")).sum()) > 16 * 16


def test_rgbd_network_takes_the_depth_image(tmp_path: Path) -> None:
    """A 4-channel network is RGB-D: depth (metres, resized by nearest neighbour) is its
    fourth input channel; without a depth image it is a clear error, not a silent zero."""
    seg = OnnxSegmenter(tiny.write_tiny_seg(tmp_path / "d.onnx", depth_channel=True), min_pixels=10)
    assert seg.depth_input
    bgr = np.zeros((48, 64, 3), np.uint8)
    depth = np.full((48, 64), 1.0, np.float32)
    depth[:, 32:] = 4.0
    depth[0:8, 40:48] = 0.0  # no data: not far
    classes, _ = seg.classify(bgr, depth)
    chair = seg.class_names.index("chair")
    assert np.all(classes[:, :32] == 0) and np.all(classes[8:, 32:] == chair)
    assert np.all(classes[0:8, 40:48] == 0)
    assert [i.category for i in seg(bgr, depth)] == ["chair"]
    with pytest.raises(GeometryError, match="RGB-D"):
        seg.classify(bgr)
    with pytest.raises(GeometryError, match="RGB-D"):
        seg.segment(bgr, None)
    with pytest.raises(GeometryError, match="depth"):
        seg.classify(bgr, depth[:10])
    assert not OnnxSegmenter(tiny.write_tiny_seg(tmp_path / "rgb.onnx")).depth_input


def test_flip_average_mirrors_the_logits_back(tmp_path: Path) -> None:
    """flip_average: the mean of the logits of the image and of its mirror image, mirrored back
    (the tiny model's person logit has a -8..+8 ramp from left to right, which cancels)."""
    path = tiny.write_tiny_seg(tmp_path / "r.onnx", input_wh=(64, 48), ramp=8.0)
    bgr = np.zeros((48, 64, 3), np.uint8)
    bgr[:, :, 2] = 255  # red everywhere: person logit 5 + ramp, background 0
    person = tiny.kg_classes().index("person")
    one_pass = OnnxSegmenter(path, flip_average=False)
    classes, _ = one_pass.classify(bgr)
    assert np.all(classes[:, :12] == 0) and np.all(classes[:, -12:] == person)  # the ramp shows
    both = OnnxSegmenter(path, flip_average=True)
    classes, confidence = both.classify(bgr)
    assert np.all(classes == person)
    assert np.allclose(confidence, 1 / (1 + math.exp(-5)), rtol=1e-4)  # ramp averaged away
    one_pass_default = make_segmenter(str(path), PerceptionConfig(flip_average=False))
    assert one_pass_default.segment(bgr, None).class_map[0, 0] == 0
    assert np.all(make_segmenter(str(path)).segment(bgr, None).class_map == person)  # the default averages


def test_missing_model_fails_at_start_up(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"not found: .*nope\.onnx"):
        OnnxSegmenter(tmp_path / "nope.onnx")
    with pytest.raises(ConfigError, match="not found"):
        make_segmenter(f"yolox:{tmp_path / 'nope.onnx'}")


def test_corrupt_model_fails_at_start_up(tmp_path: Path) -> None:
    bad = tmp_path / "random.onnx"
    bad.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(ConfigError, match=r"random\.onnx is not a readable ONNX model"):
        OnnxSegmenter(bad)
    with pytest.raises(ConfigError, match="not a readable ONNX model"):
        YoloxDetector(bad)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"input_name": "input"}, "input named 'image'"),
        ({"output_name": "out"}, "output named 'logits'"),
        ({"out_channels": 5}, r"output 'logits' has shape \[1, 5, 24, 32\], expected \[1, 14, 24, 32\]"),
        ({"metadata": {"wardmap.input_size": "64x48"}}, r"input 'image' has shape"),
        ({"metadata": {"wardmap.input_size": "big"}}, "must be 'WxH'"),
        ({"metadata": {"wardmap.classes": None}}, "'wardmap.classes'.*missing"),
        ({"metadata": {"wardmap.classes": "[1, 2"}}, "not JSON"),
    ],
)
def test_wrong_model_fails_at_start_up(tmp_path: Path, kwargs: dict, message: str) -> None:
    path = tiny.write_tiny_seg(tmp_path / "wrong.onnx", **kwargs)
    with pytest.raises(ConfigError, match=message) as info:
        OnnxSegmenter(path)
    assert "wrong.onnx" in str(info.value)


def test_unknown_trim_class_fails_at_start_up(tmp_path: Path) -> None:
    path = tiny.write_tiny_seg(tmp_path / "m.onnx")
    with pytest.raises(ConfigError, match=r"trim_classes.*'stool'"):
        OnnxSegmenter(path, trim_classes=("chair", "stool"))
    assert OnnxSegmenter(path, trim_classes=("chair",)).class_names[0] == "background"


def test_class_list_must_match_the_knowledge_graph(tmp_path: Path) -> None:
    classes = tiny.kg_classes()
    swapped = [classes[0], classes[2], classes[1], *classes[3:]]
    with pytest.raises(ConfigError, match=f"index 1 is {classes[2]!r}, expected {classes[1]!r}"):
        OnnxSegmenter(tiny.write_tiny_seg(tmp_path / "a.onnx", classes=swapped))
    with pytest.raises(ConfigError, match="index 14 is 'extra'"):
        OnnxSegmenter(tiny.write_tiny_seg(tmp_path / "b.onnx", classes=[*classes, "extra"]))


def test_wrong_yolox_model_fails_at_start_up(tmp_path: Path) -> None:
    """A segmentation network given as a YOLOX detector is refused by its input shape."""
    path = tiny.write_tiny_seg(tmp_path / "seg.onnx")
    with pytest.raises(ConfigError, match=r"seg\.onnx: input 'image' has shape \[1, 3, 24, 32\]"):
        YoloxDetector(path)


def test_make_segmenter_specs(tmp_path: Path) -> None:
    path = tiny.write_tiny_seg(tmp_path / "m.onnx")
    assert isinstance(make_segmenter(str(path)), OnnxSegmenter)
    assert isinstance(make_segmenter(f"model:{path}"), OnnxSegmenter)
    with pytest.raises(ConfigError, match="empty"):
        make_segmenter("  ")
    if packaged_model_path().is_file():
        assert isinstance(make_segmenter("model"), OnnxSegmenter)
    else:
        with pytest.raises(ConfigError, match="packaged segmentation model is not installed"):
            make_segmenter("model")




@pytest.mark.skipif(not (YOLOX.is_file() and TUM.is_dir()), reason="needs ../shared (YOLOX, TUM excerpt)")
def test_yolox_finds_the_monitor_on_a_real_tum_frame() -> None:
    """Frame 90 of fr1/rpy shows the monitor: COCO 'tv' -> knowledge-graph 'wall_monitor'."""
    import cv2

    from wardmap.shared.dataset import DatasetReader

    frame = DatasetReader(TUM).frame(90)
    bgr = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR)
    seg = make_segmenter(f"yolox:{YOLOX}")
    out = seg.segment(bgr, frame.depth_m)
    monitors = [i for i in out.instances if i.category == "wall_monitor"]
    assert len(monitors) == 1 and monitors[0].confidence > 0.5
    x1, _, _, y2 = monitors[0].box_xyxy
    assert x1 > 250 and y2 < 250  # the upper right of the image
    depths = frame.depth_m[monitors[0].mask]
    assert np.median(depths[depths > 0]) < 2.0  # the mask is on the monitor, not the far wall
    index = seg.class_names.index("wall_monitor")
    assert np.all(out.class_map[monitors[0].mask] == index)
    assert np.all(out.confidence[monitors[0].mask] == pytest.approx(monitors[0].confidence))


@pytest.mark.skipif(not (YOLOX.is_file() and TUM.is_dir()), reason="needs ../shared (YOLOX, TUM excerpt)")
def test_yolox_gives_no_hospital_only_class_in_the_tum_office() -> None:
    """Every 10th frame of the TUM office (no hospital furniture in it): no pixel of a class COCO
    cannot give or the table no longer maps (cabinet from refrigerator, bed from couch)."""
    from wardmap.shared.dataset import DatasetReader
    from wardmap.shared.detection import CocoMap

    coco = CocoMap.load()
    # the reviewed table: only COCO's own bed class gives beds, nothing gives a cabinet
    assert {coco.names[i] for i, k in coco.to_kg.items() if k == "bed"} == {"bed"}
    seg = make_segmenter(f"yolox:{YOLOX}")
    forbidden = [seg.class_names.index(c) for c in ("door", "wheelchair", "cart", "iv_pole",
                                                     "temperature_gun", "cabinet", "bed")]
    reader = DatasetReader(TUM)
    for i in range(0, len(reader), 10):
        frame = reader.frame(i)
        out = seg.segment(np.ascontiguousarray(frame.rgb[..., ::-1]), frame.depth_m)
        assert not np.isin(out.class_map, forbidden).any(), f"frame {i}"


@pytest.mark.skipif(not (YOLOX.is_file() and TUM.is_dir()), reason="needs ../shared (YOLOX, TUM excerpt)")
def test_yolox_desk_mask_keeps_the_cup_on_it_on_a_real_tum_frame() -> None:
    """Frame 50 of fr1/rpy at a low score threshold (0.1): the desk's box holds the white cup
    outlined in bench/data/tum_fr1_rpy_labels.json, and the desk's depth band takes it in
    unless the cup's mask is cut out of the desk's first (before: 1654 of its 1786 pixels desk)."""
    import json

    from wardmap.shared.dataset import DatasetReader

    labels = json.loads((REPO / "bench" / "data" / "tum_fr1_rpy_labels.json").read_text())
    (frame_label,) = [f for f in labels["frames"] if f["index"] == 50]
    (cup_polygon,) = [o["polygon"] for o in frame_label["objects"] if o["class"] == "cup"]
    outline = np.zeros((480, 640), np.uint8)
    cv2.fillPoly(outline, [np.asarray(cup_polygon, np.int32)], 1)
    frame = DatasetReader(TUM).frame(50)
    seg = make_segmenter(f"yolox:{YOLOX}", PerceptionConfig(score_threshold=0.1))
    out = seg.segment(np.ascontiguousarray(frame.rgb[..., ::-1]), frame.depth_m)
    inside = out.class_map[outline.astype(bool)]
    desk = seg.class_names.index("desk")
    assert np.any(out.class_map == desk)  # the desk is detected at this threshold
    assert np.mean(inside == seg.class_names.index("cup")) >= 0.8
    assert np.mean(inside == desk) <= 0.05

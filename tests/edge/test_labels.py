"""Tests of wardmap.edge.labels: the none / oracle / onnx label sources and their registry."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from wardmap.edge.labels import LABEL_SOURCES, LabelResult, make_label_source
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.dataset import Calibration, DatasetReader, DatasetWriter, Frame
from wardmap.shared.errors import ConfigError, DatasetError
from wardmap.shared.knowledge import KnowledgeGraph

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
MODEL = SHARED / "models" / "yolox_nano.onnx"
TUM_DIR = SHARED / "data" / "tum_fr1_rpy_s3_first100"
needs_model = pytest.mark.skipif(not MODEL.is_file(), reason=f"reference model absent: {MODEL}")
needs_tum = pytest.mark.skipif(not TUM_DIR.is_dir(), reason=f"reference data absent: {TUM_DIR}")

W, H = 32, 24
T0 = 1_700_000_000.0


@pytest.fixture(scope="module")
def kg() -> KnowledgeGraph:
    return KnowledgeGraph.load()


def write_tiny(root: Path, *, labels: bool = True, objects: Mapping[str, Any] | None = None) -> np.ndarray:
    """Two 32 x 24 frames; instance 5 (a bed) on the left, 9 (a person) on the right and
    instance 40, which objects.json does not list, in one corner. Returns the label image."""
    rng = np.random.default_rng(3)
    instances = np.zeros((H, W), np.uint16)
    instances[4:20, 2:14] = 5
    instances[2:22, 18:28] = 9
    instances[0:2, 0:2] = 40
    calibration = Calibration(rgb=PinholeCamera(W, H, 30.0, 30.0, 15.5, 11.5))
    with DatasetWriter(root, calibration) as writer:
        for k in range(2):
            writer.write_frame(
                T0 + 0.1 * k,
                rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
                np.full((H, W), 2.0),
                labels=instances if labels else None,
            )
        if objects is not None:
            writer.write_objects(objects)
    return instances


OBJECTS: dict[str, Any] = {"objects": [{"id": 5, "class": "bed"}, {"id": 9, "class": "person"}]}


def test_none_source_gives_no_labels(tmp_path: Path, kg: KnowledgeGraph) -> None:
    """Scenario: spec 'none' on a data set with ground truth still returns None per frame."""
    write_tiny(tmp_path, objects=OBJECTS)
    dataset = DatasetReader(tmp_path)
    source = make_label_source("none", dataset=dataset, kg=kg)
    assert source.name == "none"
    assert source.labels(dataset.frame(0)) is None
    assert make_label_source(" none ", dataset=None, kg=kg).labels(dataset.frame(1)) is None


def test_oracle_maps_instances_to_classes(tmp_path: Path, kg: KnowledgeGraph) -> None:
    """Scenario: spec 'oracle': instance 5 -> bed, 9 -> person, the unlisted 40 and 0 ->
    background; the instance image is the ground truth itself."""
    instances = write_tiny(tmp_path, objects=OBJECTS)
    dataset = DatasetReader(tmp_path)
    result = make_label_source("oracle", dataset=dataset, kg=kg).labels(dataset.frame(1))
    assert isinstance(result, LabelResult)
    expected = np.zeros((H, W), np.uint8)
    expected[instances == 5] = kg.index_of("bed")
    expected[instances == 9] = kg.index_of("person")
    assert result.class_image.dtype == np.uint8
    np.testing.assert_array_equal(result.class_image, expected)
    assert result.instance_image is not None
    np.testing.assert_array_equal(result.instance_image, instances)
    assert result.inference_ms >= 0.0


def test_oracle_needs_labels_and_objects(tmp_path: Path, kg: KnowledgeGraph) -> None:
    """Scenario: 'oracle' on a data set without labels, one without objects.json, and without
    any data set (live sensors): ConfigError naming what is missing."""
    write_tiny(tmp_path / "no_labels", labels=False, objects=OBJECTS)
    with pytest.raises(ConfigError, match="labels"):
        make_label_source("oracle", dataset=DatasetReader(tmp_path / "no_labels"), kg=kg)
    write_tiny(tmp_path / "no_objects")
    with pytest.raises(ConfigError, match=r"objects\.json"):
        make_label_source("oracle", dataset=DatasetReader(tmp_path / "no_objects"), kg=kg)
    with pytest.raises(ConfigError, match="data set"):
        make_label_source("oracle", dataset=None, kg=kg)


def test_oracle_rejects_bad_objects(tmp_path: Path, kg: KnowledgeGraph) -> None:
    """Scenario: objects.json naming a class the knowledge graph lacks (ConfigError), and one
    with a malformed id (DatasetError)."""
    write_tiny(tmp_path / "a", objects={"objects": [{"id": 5, "class": "spaceship"}]})
    with pytest.raises(ConfigError, match="spaceship"):
        make_label_source("oracle", dataset=DatasetReader(tmp_path / "a"), kg=kg)
    write_tiny(tmp_path / "b", objects={"objects": [{"id": "five", "class": "bed"}]})
    with pytest.raises(DatasetError):
        make_label_source("oracle", dataset=DatasetReader(tmp_path / "b"), kg=kg)


@pytest.mark.parametrize("spec", ["seg:model.onnx", "mask-rcnn", "", "onnx", "onnx:", "none:x", "oracle:gt"])
def test_bad_specs_are_config_errors(spec: str, kg: KnowledgeGraph) -> None:
    """Scenario: an unknown prefix (the not yet implemented 'seg'), an empty spec, onnx
    without a path, arguments to argument-less sources."""
    with pytest.raises(ConfigError):
        make_label_source(spec, dataset=None, kg=kg)


def test_unknown_prefix_lists_the_known_ones(kg: KnowledgeGraph) -> None:
    """Scenario: the error for 'seg:...' names every registered source."""
    with pytest.raises(ConfigError) as info:
        make_label_source("seg:weights.onnx", dataset=None, kg=kg)
    for prefix in LABEL_SOURCES:
        assert prefix in str(info.value)
    with pytest.raises(ConfigError):
        make_label_source("none", dataset=None, kg=kg, threads=0)


def test_missing_or_bad_model_file(tmp_path: Path, kg: KnowledgeGraph) -> None:
    """Scenario: onnx:PATH with a path that does not exist, and with a file that is not an
    ONNX model: ConfigError naming the path and where to get weights."""
    missing = tmp_path / "nowhere" / "yolox_nano.onnx"
    with pytest.raises(ConfigError) as info:
        make_label_source(f"onnx:{missing}", dataset=None, kg=kg)
    assert str(missing) in str(info.value) and "YOLOX" in str(info.value)
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"this is not a protobuf" * 10)
    with pytest.raises(ConfigError) as info:
        make_label_source(f"onnx:{garbage}", dataset=None, kg=kg)
    assert str(garbage) in str(info.value)


@needs_model
@needs_tum
def test_onnx_detector_on_a_real_tum_frame(kg: KnowledgeGraph) -> None:
    """Scenario: YOLOX-Nano on one thread labels a real TUM fr1 frame (640 x 480, a desk
    scene): a class image of the frame's size, instance ids matching it, and a timing."""
    dataset = DatasetReader(TUM_DIR)
    source = make_label_source(f"onnx:{MODEL}", dataset=dataset, kg=kg, threads=1)
    assert source.name == "onnx:yolox_nano.onnx"
    frame = dataset.frame(0)
    result = source.labels(frame)
    assert result is not None
    assert result.class_image.shape == (480, 640) and result.class_image.dtype == np.uint8
    assert result.instance_image is not None and result.instance_image.shape == (480, 640)
    np.testing.assert_array_equal(result.class_image > 0, result.instance_image > 0)
    assert 0.0 < result.inference_ms < 10_000.0
    assert int(result.class_image.max()) < kg.num_classes


@pytest.fixture(scope="module")
def walking_staff(tmp_path_factory: pytest.TempPathFactory) -> DatasetReader:
    """The simulated 'walking_staff' scenario, seed 0, first 171 frames (17 s at 10 Hz)."""
    from wardmap.sim.runner import generate

    out = tmp_path_factory.mktemp("walking_staff")
    generate("walking_staff", 0, out, frames=171)
    return DatasetReader(out)


def _persons(dataset: DatasetReader, index: int) -> tuple[Frame, np.ndarray]:
    """Frame ``index`` of ``dataset`` and its ground-truth person pixels (H, W) bool."""
    frame = dataset.frame(index)
    assert frame.labels is not None
    document = dataset.objects()
    assert document is not None
    person_ids = [o["id"] for o in document["objects"] if o["class"] == "person"]
    return frame, np.isin(frame.labels, person_ids)


@needs_model
@pytest.mark.slow
def test_onnx_detector_finds_a_simulated_person(walking_staff: DatasetReader, kg: KnowledgeGraph) -> None:
    """Scenario: frame 170 (t = 17 s) of the simulated walking-staff corridor, where a visitor
    crosses close in front of the robot: the detector finds at least one person whose box holds
    ground-truth person pixels, and the person pixels of its label image overlap the ground truth."""
    from wardmap.edge.labels import OnnxDetectorLabels

    source = make_label_source(f"onnx:{MODEL}", dataset=walking_staff, kg=kg, threads=1)
    assert isinstance(source, OnnxDetectorLabels)
    frame, truth = _persons(walking_staff, 170)
    assert truth.any()

    detections = source.detect(frame.rgb)
    hits = []
    for box, cls in zip(detections.boxes_xyxy, detections.coco_class, strict=True):
        if cls != 0:
            continue
        x1, y1, x2, y2 = (round(float(v)) for v in box)
        hits.append(int(truth[y1:y2, x1:x2].sum()))
    assert any(h > 0 for h in hits), (hits, json.dumps(detections.coco_class.tolist()))

    result = source.labels(frame)
    assert result.inference_ms > 0.0
    labelled_person = result.class_image == kg.index_of("person")
    assert np.count_nonzero(labelled_person & truth) > 0


SEG_MODEL = Path(__file__).resolve().parents[2] / "server" / "models" / "hospital_seg.onnx"


@pytest.mark.skipif(not SEG_MODEL.is_file(), reason="the packaged segmentation network is not built")
def test_onnx_source_runs_a_segmentation_network(walking_staff: DatasetReader, kg: KnowledgeGraph) -> None:
    """onnx:PATH recognises a wardmap segmentation network by its metadata; its class map is the
    label image: on frame 60 (the nurse pushing a cart ahead) its person pixels overlap the truth."""
    from wardmap.edge.labels import OnnxSegmentationLabels

    source = make_label_source(f"onnx:{SEG_MODEL}", dataset=walking_staff, kg=kg, threads=1)
    assert isinstance(source, OnnxSegmentationLabels)
    frame, truth = _persons(walking_staff, 60)
    result = source.labels(frame)
    assert result.class_image.shape == truth.shape and result.instance_image is None
    person = result.class_image == kg.index_of("person")
    iou = np.count_nonzero(person & truth) / max(1, np.count_nonzero(person | truth))
    assert iou > 0.5, iou

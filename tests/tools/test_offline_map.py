"""The offline runner on a small simulated data set (a few frames of ward_chairs)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from wardmap.server.association.associator import AssociationConfig
from wardmap.shared.errors import DatasetError, WardmapError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.se3 import yaw_transform
from wardmap.sim.runner import generate
from wardmap.tools.evaluate import score_landmarks
from wardmap.tools.offline_map import (
    MapConfig,
    associate,
    landmarks_document,
    measure_dataset,
    run_map,
    score_against_truth,
    select_keyframes,
)

FRAMES = 10


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """ward_chairs, seed 0, the first 10 frames (identical chairs and doors in view)."""
    out = tmp_path_factory.mktemp("sim") / "ward_chairs_s0"
    generate("ward_chairs", 0, out, frames=FRAMES)
    return out


@pytest.fixture(scope="module")
def config_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Every frame a keyframe (the robot barely moves in 10 frames), groups of 4 sharing 1."""
    p = tmp_path_factory.mktemp("cfg") / "assoc.toml"
    p.write_text("[map]\nkeyframe_min_translation_m = 0.0\nkeyframe_min_rotation_deg = 0.0\n\n"
                 "[association]\ngroup_size = 4\ngroup_overlap = 1\n")
    return p


def test_keyframe_selection() -> None:
    """Keyframes: the first posed frame, then each 0.1 m or 10 deg of motion since the last one."""
    poses = [yaw_transform(0.04 * i, 0, 0) for i in range(10)] + [None, yaw_transform(0.4, 0, 0.2)]
    assert select_keyframes(poses, 0.1, 10.0) == [0, 3, 6, 9, 11]
    assert select_keyframes([None, yaw_transform(0, 0, 0)], 0.1, 10.0) == [1]


def test_oracle_map_of_a_small_sequence(small: Path, config_file: Path, tmp_path: Path) -> None:
    """landmarks.json holds every measurement once, with boxes, stamps and ground-truth ids;
    with oracle measurements every landmark is one object and the count matches ground truth."""
    summary = run_map([small], tmp_path / "out", config_path=config_file)
    doc = json.loads((tmp_path / "out" / "landmarks.json").read_text())
    assert doc["method"] == "hierarchical" and doc["measurements"] == "oracle"
    assert doc["datasets"][0]["keyframes"] == FRAMES
    assert summary["landmarks"] == len(doc["landmarks"]) > 0
    keys = set()
    gt_ids = set()
    for lm in doc["landmarks"]:
        T = np.array(lm["T_world_object"])
        assert T.shape == (4, 4) and len(lm["size"]) == 3
        assert len(lm["color_rgb"]) == 3 and all(0 <= c <= 255 for c in lm["color_rgb"])
        ids = {m["gt_instance"] for m in lm["measurements"]}
        assert len(ids) == 1  # oracle: one object per landmark
        gt_ids |= ids
        for m in lm["measurements"]:
            assert m["category"] == lm["class"] and len(m["box_xyxy"]) == 4
            key = (m["keyframe"], m["gt_instance"])
            assert key not in keys
            keys.add(key)
    assert len(gt_ids) == len(doc["landmarks"])
    assert summary["measurements"] == len(keys)
    assert summary["score"]["accuracy"] == summary["score"]["completeness"] == 1.0
    assert summary["score"]["objects"] == summary["score"]["gt_objects"] == len(gt_ids)


def test_score_only_against_one_world(small: Path) -> None:
    """The summary's score needs ground truth for every data set, from one world: data sets whose
    objects.json give one id two classes, or one without ground truth, are not scored."""
    every_frame = MapConfig(keyframe_min_translation_m=0.0, keyframe_min_rotation_deg=0.0)
    ds = measure_dataset(small, config=every_frame)
    kg = KnowledgeGraph.load()
    landmarks = associate([ds], AssociationConfig())
    assert score_against_truth(landmarks, [ds, ds], kg) is not None  # the same world twice
    assert ds.gt_classes is not None
    renamed = {i: ("bed" if c != "bed" else "door") for i, c in ds.gt_classes.items()}
    other = dataclasses.replace(ds, gt_classes=renamed)
    assert score_against_truth(landmarks, [ds, other], kg) is None
    assert score_against_truth(landmarks, [ds, dataclasses.replace(ds, gt_classes=None)], kg) is None


def test_methods_share_the_measurements(small: Path) -> None:
    """Measure once, associate three ways: same measurements scored; nothing is lost."""
    every_frame = MapConfig(keyframe_min_translation_m=0.0, keyframe_min_rotation_deg=0.0)
    ds = measure_dataset(small, config=every_frame)
    total = sum(len(k.measurements) for k in ds.keyframes)
    assert total > 0
    for method in ("hierarchical", "per_keyframe_hdp", "nearest"):
        score = score_landmarks(associate([ds], AssociationConfig(method=method)), ds.gt_classes, ("person",))
        assert score.measurements == total
        assert 0.0 <= score.accuracy <= 1.0


def test_measurements_beyond_range_are_counted_in_landmarks_json(small: Path) -> None:
    """With a range that cuts the data set's measurements in two, landmarks.json counts the far
    ones per data set and the landmarks hold the rest: none is unaccounted for."""
    every_frame = MapConfig(keyframe_min_translation_m=0.0, keyframe_min_rotation_deg=0.0)
    ds = measure_dataset(small, config=every_frame)
    depths = [float(m.T_camera_object[2, 3]) for k in ds.keyframes for m in k.measurements]
    cfg = AssociationConfig(max_range_m=float(np.median(depths)))
    landmarks = associate([ds], cfg)
    doc = landmarks_document(landmarks, method=cfg.method, measurements="oracle", datasets=[ds], config=cfg)
    far = doc["datasets"][0]["beyond_range"]
    assert 0 < far < len(depths)
    assert far + sum(len(lm["measurements"]) for lm in doc["landmarks"]) == len(depths)


def test_instances_not_measured_are_counted_by_kind(small: Path) -> None:
    """Every oracle instance of a kept class is either measured or counted as skipped, by kind,
    in the data set and in landmarks.json (far objects have no depth: some are skipped)."""
    from wardmap.server.perception.instances import oracle_instances
    from wardmap.server.perception.measure import SKIP_KINDS
    from wardmap.shared.dataset import DatasetReader
    from wardmap.shared.knowledge import KnowledgeGraph

    cfg = MapConfig(keyframe_min_translation_m=0.0, keyframe_min_rotation_deg=0.0)
    ds = measure_dataset(small, config=cfg)
    assert ds.gt_classes is not None
    kg = KnowledgeGraph.load()
    reader = DatasetReader(small)
    found = sum(1 for i in range(len(reader))
                for inst in oracle_instances(reader.frame(i).labels, ds.gt_classes, min_pixels=cfg.min_pixels)
                if not kg.is_moving(inst.category))
    measured = sum(len(k.measurements) for k in ds.keyframes)
    assert sum(ds.skipped.values()) > 0 and set(ds.skipped) <= set(SKIP_KINDS)
    assert found == measured + sum(ds.skipped.values())
    acfg = AssociationConfig()
    doc = landmarks_document(associate([ds], acfg), method=acfg.method, measurements="oracle", datasets=[ds],
                             config=acfg)
    assert doc["datasets"][0]["skipped"] == {k: ds.skipped.get(k, 0) for k in SKIP_KINDS}


def test_errors(small: Path, tmp_path: Path) -> None:
    """Missing data set, a poses file that covers no frame, --poses count mismatch."""
    with pytest.raises(DatasetError, match="not found"):
        run_map([tmp_path / "nope"], tmp_path / "o")
    traj = tmp_path / "far.txt"
    traj.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match="covers none"):
        run_map([small], tmp_path / "o", poses=[traj])
    with pytest.raises(WardmapError, match="one trajectory per data set"):
        run_map([small, small], tmp_path / "o", poses=[traj])


def test_model_measurements_take_the_servers_perception_steps(small: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """``--measurements model`` runs each keyframe through ``keyframe.measure_keyframe``: with a
    segmenter that finds a person and, as a cabinet, the largest object of the first frame's
    label image in every image, each person is counted as moving, each cabinet is measured,
    skipped or left out by a floor check once, and measurements carry the simulator id most
    of their mask covers in their own frame."""
    from wardmap.server.perception.instances import gt_instance_of
    from wardmap.server.perception.masks import box_of_mask
    from wardmap.server.perception.types import Instance
    from wardmap.shared.dataset import DatasetReader
    from wardmap.tools import offline_map as offline

    reader = DatasetReader(small)
    first = reader.frame(0).labels
    assert first is not None
    ids, counts = np.unique(first[first > 0], return_counts=True)
    largest = int(ids[np.argmax(counts)])
    cabinet = first == largest
    person = np.zeros_like(cabinet)
    person[:40, :40] = True

    def finds(bgr: np.ndarray, depth_m: np.ndarray | None) -> list[Instance]:
        return [Instance("person", 0.9, person, box_of_mask(person)),
                Instance("cabinet", 0.8, cabinet, box_of_mask(cabinet))]

    monkeypatch.setattr(offline, "_segmenter", lambda source: finds)
    cfg = MapConfig(keyframe_min_translation_m=0.0, keyframe_min_rotation_deg=0.0)
    ds = measure_dataset(small, measurements="model", config=cfg)
    n = len(ds.keyframes)
    assert n == FRAMES and ds.moving_left_out == n
    measured = sum(len(k.measurements) for k in ds.keyframes)
    left_out = ds.floating_left_out + ds.wall_pieces_left_out + ds.floor_pieces_left_out
    assert measured + sum(ds.skipped.values()) + left_out == n
    ids_seen = []
    for i, kf in enumerate(ds.keyframes):
        for m in kf.measurements:
            assert m.category == "cabinet" and m.confidence == 0.8
            assert m.gt_instance == gt_instance_of(cabinet, reader.frame(i).labels)
            ids_seen.append(m.gt_instance)
    assert largest in ids_seen

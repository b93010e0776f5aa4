"""The map writer (``wardmap.server.mapping.writer``) on synthetic measurements with known truth:
two chairs seen from a camera sliding past them. What the writer associates reaches the object map
once, with the mean colour of every measurement; sessions end as the module docstring says; a
writer continued from its state (a checkpoint) ends where an uninterrupted one does."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from wardmap.server.association.associator import AssociationConfig
from wardmap.server.association.geometry import project_box
from wardmap.server.mapping import MappedKeyframe, MapWriter
from wardmap.server.mapping.checkpoint import decode_state, encode_state
from wardmap.server.mapping.writer import WriterState
from wardmap.server.objectmap import ObjectMap
from wardmap.server.perception.measure import mean_rgb
from wardmap.server.perception.types import ObjectMeasurement
from wardmap.server.store import MapStore, open_store
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.se3 import inverse, make_transform

CAMERA = PinholeCamera(640, 480, 525.0, 525.0, 319.5, 239.5)
CHAIR = np.array([0.46, 0.46, 0.93])
BINS = (16, 4, 4)


def _camera(x: float) -> np.ndarray:
    """T_map_camera (4, 4) of a camera at (x, 0, 0.8) looking along map +y."""
    return make_transform(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]), [x, 0.0, 0.8])


def _keyframe(stream: str, seq: int, chairs: dict[int, float], x_camera: float = 0.3,
              far: bool = False) -> MappedKeyframe:
    """Keyframe ``seq`` of ``stream`` measuring the chairs (ground-truth id -> x, 3 m ahead); each
    measurement's colour histogram puts all its weight in bin ``seq % 4`` of the hue axis.
    ``far``: one more chair 40 m ahead (beyond association's range)."""
    T = _camera(x_camera + 0.01 * seq)
    hist = np.zeros(BINS[0] * BINS[1] * BINS[2], np.float32)
    hist[(seq % 4) * BINS[1] * BINS[2] + 15] = 1.0
    spots = [(gid, x, 3.0) for gid, x in chairs.items()] + ([(99, 0.3, 40.0)] if far else [])
    ms = []
    for gid, x, y in spots:
        T_wo = make_transform(np.eye(3), [x, y, CHAIR[2] / 2])
        box = project_box(T_wo, CHAIR, T, CAMERA)
        assert box is not None
        ms.append(ObjectMeasurement(
            keyframe=f"{stream}/{seq}", stamp=1.0 + seq, category="chair", confidence=0.9, box_xyxy=box,
            mask=np.zeros((0, 0), bool), points_camera=np.zeros((0, 3), np.float32),
            T_camera_object=inverse(T) @ T_wo, T_world_camera=T, T_world_object=T_wo, size=CHAIR.copy(),
            color_hist=hist.copy(), gt_instance=gid,
        ))
    return MappedKeyframe(stream, T, CAMERA, ms)


@pytest.fixture
def store(tmp_path: Path) -> Iterator[MapStore]:
    with open_store(f"sqlite:///{tmp_path / 'map.db'}") as s:
        yield s


def test_a_session_reaches_the_map_once_with_its_mean_colour(store: MapStore) -> None:
    """Twelve keyframes of two chairs, then the session is closed: two objects, each with every
    measurement once as an observation, and the mean colour of all their histograms."""
    objects = ObjectMap(store)
    writer = MapWriter(objects, hist_bins=BINS)
    keyframes = [_keyframe("r1/s1", i, {1: 0.0, 2: 1.0}) for i in range(12)]
    writer.add(keyframes)
    writer.close(["r1/s1"])
    landmarks = writer.landmarks()
    assert len(landmarks) == 2 and writer.open_streams == {}
    assert store.observation_counts() == {lm.id: 12 for lm in landmarks}
    hist_sum = sum(np.asarray(kf.measurements[0].color_hist, np.float64) for kf in keyframes)
    sums = writer.colour_sums()
    for lm in landmarks:
        assert np.allclose(sums[lm.id], hist_sum)
        detail = objects.get(lm.id)
        assert detail is not None and detail.record.color_rgb == pytest.approx(mean_rgb([hist_sum], BINS))


def test_a_new_session_closes_the_robots_previous_one(store: MapStore) -> None:
    """A group still filling up waits; the robot's next session associates it, another robot's
    does not."""
    writer = MapWriter(ObjectMap(store), hist_bins=BINS)
    writer.add([_keyframe("r1/s1", i, {1: 0.0}) for i in range(3)])
    assert writer.landmarks() == [] and store.count_objects() == 0
    writer.add([_keyframe("r2/s1", 0, {1: 0.0})])
    assert writer.landmarks() == [] and writer.open_streams == {"r1": "r1/s1", "r2": "r2/s1"}
    writer.add([_keyframe("r1/s2", 0, {1: 0.0})])
    assert len(writer.landmarks()) == 1 and sum(store.observation_counts().values()) == 3
    assert writer.open_streams == {"r1": "r1/s2", "r2": "r2/s1"}


def test_associate_counts_measurements_beyond_range_and_waits_for_write(store: MapStore) -> None:
    objects = ObjectMap(store)
    writer = MapWriter(objects, AssociationConfig(group_size=2, group_overlap=0), hist_bins=BINS)
    assert writer.associate(_keyframe("r1/s1", 0, {1: 0.0}, far=True)) == 1
    assert writer.associate(_keyframe("r1/s1", 1, {1: 0.0})) == 0
    assert len(writer.landmarks()) == 1 and objects.count() == 0  # associated, not written yet
    writer.write()
    assert objects.count() == 1 and store.observation_counts() == {writer.landmarks()[0].id: 2}


def test_a_writer_continued_from_its_state_ends_as_an_uninterrupted_one(tmp_path: Path) -> None:
    """Half the keyframes, then the state through the checkpoint encoding into a new writer, then
    the rest: the same landmarks, colours and map as one writer that saw them all."""
    keyframes = [_keyframe("r1/s1", i, {1: 0.0, 2: 1.0}, x_camera=0.2) for i in range(16)]

    def run(path: Path, split: int | None) -> tuple[list, list]:
        with open_store(f"sqlite:///{path}") as store:
            objects = ObjectMap(store)
            writer = MapWriter(objects, hist_bins=BINS)
            if split is not None:
                writer.add(keyframes[:split])
                s = writer.state()
                blob = encode_state({"associator": s.associator, "hist_sum": s.hist_sum,
                                     "open_stream": s.open_stream})
                d = decode_state(blob)
                writer = MapWriter(objects, hist_bins=BINS,
                                   state=WriterState(d["associator"], d["hist_sum"], d["open_stream"]))
                keyframes_left = keyframes[split:]
            else:
                keyframes_left = keyframes
            writer.add(keyframes_left)
            writer.close(["r1/s1"])
            landmarks = [(lm.id, lm.n_measurements, lm.T_world_object.tobytes()) for lm in writer.landmarks()]
            records = [(h.record.object_id, h.record.n_observations, h.record.color_rgb,
                        h.record.T_world_object.tobytes()) for h in objects.query().hits]
            return landmarks, records

    assert run(tmp_path / "a.db", 7) == run(tmp_path / "b.db", None)

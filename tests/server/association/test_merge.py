"""Landmarks that turn out to be one object are merged (``AssociationConfig.merge_inside``), and
the server's object map follows: the absorbed object is deleted, its observations moved."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wardmap.server.association.associator import AssociationConfig, Associator
from wardmap.server.association.types import LandmarkChange
from wardmap.server.objectmap import ObjectMap
from wardmap.server.pipeline import MapPipeline, _MappedKeyframe
from wardmap.server.store import SqliteKeyframeStore

from .conftest import CAMERA, MeasurementFactory, camera_looking_along_y, object_pose

CART = np.array([0.6, 0.6, 0.9])
WIDE = np.array([1.2, 0.6, 0.9])
PIECE = np.array([0.2, 0.2, 0.3])


def _keyframes(make: MeasurementFactory) -> list[tuple[list, np.ndarray]]:
    """A cart seen first as two disjoint boxes (its left part, and a piece 0.5 m to the right:
    two landmarks), then whole: its landmark grows over the piece."""
    out = []
    for i in range(16):
        T = camera_looking_along_y(0.2 + 0.02 * i)
        key = dict(keyframe=f"r1/s1/{i}", stamp=1.0 + i, category="cart", gt=1)
        if i < 6:
            ms = [make(object_pose(0.0, 3.0, 0.45), T, size=CART, **key),
                  make(object_pose(0.5, 3.0, 0.45), T, size=PIECE, **key)]
        else:
            ms = [make(object_pose(0.3, 3.0, 0.45), T, size=WIDE, **key)]
        out.append((ms, T))
    return out


def _run(assoc: Associator, scene: list) -> list[LandmarkChange]:
    changes = [c for ms, T in scene for c in assoc.add_keyframe(ms, T, CAMERA)]
    return changes + assoc.flush()


def test_a_landmark_grown_over_another_absorbs_it(make_measurement: MeasurementFactory) -> None:
    scene = _keyframes(make_measurement)
    apart = Associator(AssociationConfig(merge_inside=0.0))
    _run(apart, scene)
    assert len(apart.landmarks()) == 2
    assoc = Associator(AssociationConfig())
    changes = _run(assoc, scene)
    (one,) = assoc.landmarks()
    assert one.n_measurements == sum(len(ms) for ms, _ in scene)  # nothing lost
    merged = [c for c in changes if c.kind == "merged"]
    assert len(merged) == 1 and merged[0].into == one.id and merged[0].landmark.id != one.id
    assert merged[0].added == ()
    # Every measurement entered the map exactly once, through some change's ``added``.
    added = [id(m) for c in changes for m in c.added]
    assert sorted(added) == sorted(id(m) for ms, _ in scene for m in ms)
    # Two keyframes' measurements of one object now share a landmark.
    assert len({m.keyframe for m in one.measurements}) < len(one.measurements)


def test_identical_neighbours_are_not_merged(make_measurement: MeasurementFactory) -> None:
    """Two carts side by side (boxes touching) stay two landmarks."""
    assoc = Associator(AssociationConfig())
    for i in range(12):
        T = camera_looking_along_y(0.3 + 0.02 * i)
        key = dict(keyframe=f"r1/s1/{i}", stamp=float(i), category="cart")
        assoc.add_keyframe([make_measurement(object_pose(0.0, 3.0, 0.45), T, size=CART, gt=1, **key),
                            make_measurement(object_pose(0.62, 3.0, 0.45), T, size=CART, gt=2, **key)],
                           T, CAMERA)
    assoc.flush()
    assert sorted(lm.n_measurements for lm in assoc.landmarks()) == [12, 12]


def test_the_object_map_follows_a_merge(tmp_path: Path, make_measurement: MeasurementFactory) -> None:
    """The mapping stage deletes the absorbed object and moves its observations to the survivor."""
    scene = _keyframes(make_measurement)
    with SqliteKeyframeStore.open(tmp_path / "map.db") as store:
        objects = ObjectMap(store)
        pipe = MapPipeline(store, objects)
        seen: set[int] = set()
        for ms, T in scene:
            pipe._associate([_MappedKeyframe("r1/s1", T, CAMERA, ms)])
            seen |= {h.record.object_id for h in objects.query().hits}
        pipe._close(["r1/s1"])
        (survivor,) = pipe._associator.landmarks()
        page = objects.query()
        assert [h.record.object_id for h in page.hits] == [survivor.id]
        assert len(seen) == 2  # the piece was an object of its own before the merge
        with store.reading("test") as conn:
            rows = conn.execute("SELECT object_id, COUNT(*) FROM observations GROUP BY object_id").fetchall()
        assert rows == [(survivor.id, survivor.n_measurements)]
        assert page.hits[0].record.n_observations == survivor.n_measurements

"""After each group, measurements of classes seen whole move to the landmark with the nearest
refined centre (``AssociationConfig.nearest_centre``)."""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

import wardmap.server.association.associator as associator_module
from wardmap.server.association.associator import AssociationConfig, Associator
from wardmap.server.association.mot import GroupLandmark, KeyframeView, track_group
from wardmap.server.mapping import MappedKeyframe, MapWriter
from wardmap.server.objectmap import ObjectMap
from wardmap.server.store import SqliteMapStore

from .conftest import CAMERA, CHAIR_SIZE, MeasurementFactory, camera_looking_along_y, object_pose


def _sliding_tracks(views: Sequence[KeyframeView], *args: object, **kwargs: object) -> list[GroupLandmark]:
    """The real tracker, except that from keyframe 8 on its two chair tracks swap chairs halfway
    through each group, as a track does when a mask slides along a row of chairs."""
    tracks = track_group(views, *args, **kwargs)
    if views[0].index < 8 or len(tracks) != 2:
        return tracks
    half = {v.index for v in views[len(views) // 2:]}
    out = [GroupLandmark("chair"), GroupLandmark("chair")]
    for t, track in enumerate(tracks):
        for mid, m, k in zip(track.mids, track.measurements, track.keyframes, strict=True):
            out[(t + (k in half)) % 2].add(mid, m, k)
    for g in out:
        order = np.argsort(g.keyframes, kind="stable")
        g.mids[:] = [g.mids[i] for i in order]
        g.measurements[:] = [g.measurements[i] for i in order]
        g.keyframes[:] = [g.keyframes[i] for i in order]
    return out


@pytest.mark.parametrize("on", [True, False])
def test_a_sliding_track_is_pulled_back_to_its_chairs(
        on: bool, make_measurement: MeasurementFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two chairs 0.55 m apart, each measured in 20 keyframes; from keyframe 8 the tracker hands
    each group half of the other chair's measurements. With ``nearest_centre`` both landmarks
    hold only their own chair, and every measurement enters the map once; without it the
    landmarks mix the chairs."""
    monkeypatch.setattr(associator_module, "track_group", _sliding_tracks)
    assoc = Associator(AssociationConfig(nearest_centre=on))
    changes = []
    scene = []
    for i in range(20):
        T = camera_looking_along_y(0.27 + 0.005 * i)
        key = dict(keyframe=f"r1/s1/{i}", stamp=float(i))
        ms = [make_measurement(object_pose(0.0, 3.0), T, gt=1, **key),
              make_measurement(object_pose(0.55, 3.0), T, gt=2, **key)]
        scene += ms
        changes += assoc.add_keyframe(ms, T, CAMERA)
    changes += assoc.flush()
    landmarks = assoc.landmarks()
    assert sum(lm.n_measurements for lm in landmarks) == 40
    mixed = [lm.id for lm in landmarks if len(set(lm.gt_instances)) > 1]
    if on:
        assert len(landmarks) == 2 and not mixed
        for lm in landmarks:
            assert len(lm.measurements) == 20
    else:
        assert mixed
    added = sorted(id(m) for c in changes if c.kind != "merged" for m in c.added)
    assert added == sorted(id(m) for m in scene)


def test_the_object_map_follows_the_moves(tmp_path: Path, make_measurement: MeasurementFactory,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """Through the server's mapping stage with the sliding tracker: two objects, each with its
    own chair's 20 observations in the database."""
    monkeypatch.setattr(associator_module, "track_group", _sliding_tracks)
    with SqliteMapStore.open(tmp_path / "map.db") as store:
        objects = ObjectMap(store)
        writer = MapWriter(objects)
        for i in range(20):
            T = camera_looking_along_y(0.27 + 0.005 * i)
            key = dict(keyframe=f"r1/s1/{i}", stamp=1.0 + i)
            ms = [make_measurement(object_pose(0.0, 3.0), T, gt=1, **key),
                  make_measurement(object_pose(0.55, 3.0), T, gt=2, **key)]
            writer.add([MappedKeyframe("r1/s1", T, CAMERA, ms)])
        writer.close(["r1/s1"])
        landmarks = {lm.id: lm for lm in writer.landmarks()}
        assert len(landmarks) == 2 and all(len(set(lm.gt_instances)) == 1 for lm in landmarks.values())
        assert store.observation_counts() == {lid: 20 for lid in landmarks}
        centres = {h.record.object_id: h.record for h in objects.query().hits}
        assert set(centres) == set(landmarks)


def _points_in(T_world_object: np.ndarray, size: np.ndarray, n: int, T_world_camera: np.ndarray,
               rng: np.random.Generator) -> np.ndarray:
    """(n, 3) float32 camera-frame points on the camera-facing face (y = -size/2) of a box."""
    local = rng.uniform(-0.5, 0.5, (n, 3)) * size
    local[:, 1] = -size[1] / 2
    world = local @ T_world_object[:3, :3].T + T_world_object[:3, 3]
    T_cw = np.linalg.inv(T_world_camera)
    return (world @ T_cw[:3, :3].T + T_cw[:3, 3]).astype(np.float32)


@pytest.mark.parametrize("share", [0.5, 0.0])
def test_a_mask_mostly_on_one_chair_joins_that_chair_though_its_centre_is_nearer_the_next(
        share: float, make_measurement: MeasurementFactory) -> None:
    """Two chairs 0.55 m apart, seen whole in 12 keyframes. Then, in 6 keyframes, the network's
    mask covers chair 1 and part of chair 2: 70 % of its points lie on chair 1, but its box
    centre, 0.33 m along the row, is nearer chair 2's. With ``nearest_held_share`` = 0.5 those
    views join chair 1, whose box holds most of their points (the ground truth's rule: the object
    under most of the mask); by centre distance alone they join chair 2."""
    rng = np.random.default_rng(0)
    chair1, chair2 = object_pose(0.0, 3.0), object_pose(0.55, 3.0)
    assoc = Associator(AssociationConfig(nearest_held_share=share))
    straddling = []
    for i in range(18):
        T = camera_looking_along_y(0.27 + 0.005 * i)
        key = dict(keyframe=f"r1/s1/{i}", stamp=float(i))
        if i < 12:
            ms = [make_measurement(chair1, T, gt=1, **key), make_measurement(chair2, T, gt=2, **key)]
        else:
            m = make_measurement(object_pose(0.33, 3.0), T, gt=1, **key)
            points = np.concatenate([_points_in(chair1, CHAIR_SIZE, 70, T, rng),
                                     _points_in(chair2, CHAIR_SIZE, 30, T, rng)])
            ms = [dataclasses.replace(m, points_camera=points)]
            straddling.append(ms[0])
        assoc.add_keyframe(ms, T, CAMERA)
    assoc.flush()
    landmarks = assoc.landmarks()
    assert len(landmarks) == 2
    chair_of = {lm.id: Counter(lm.gt_instances).most_common(1)[0][0] for lm in landmarks}
    assert sorted(chair_of.values()) == [1, 2]
    holder = {id(m): lm.id for lm in landmarks for m in lm.measurements}
    assert {chair_of[holder[id(m)]] for m in straddling} == ({1} if share > 0 else {2})


def test_held_share_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="nearest_held_share"):
        AssociationConfig(nearest_held_share=1.5)
    with pytest.raises(ValueError, match="held_margin_m"):
        AssociationConfig(held_margin_m=-0.1)

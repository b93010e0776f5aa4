"""Protocol tests of the mapping stage's records (:class:`~wardmap.server.store.MappingStore`),
run against every backend (``conftest.BACKENDS``): cursors over the insertion order, measurements
and map poses per keyframe, idle-session closures, the association checkpoint."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from wardmap.server.perception.types import ObjectMeasurement
from wardmap.server.store import (
    Checkpoint,
    ClosedSession,
    GraphChange,
    GraphNodeRow,
    KeyframeKey,
    MappedPose,
    MapStore,
)
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.se3 import yaw_transform

from .conftest import keyframe

CAMERA = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)


def _measurement(key: str, i: int) -> ObjectMeasurement:
    rng = np.random.default_rng(i)
    return ObjectMeasurement(
        keyframe=key, stamp=1.0 + i, category="door", confidence=0.5 + 0.01 * i,
        box_xyxy=np.array([1.0, 2.0, 30.0, 40.0 + i]), mask=np.ones((4, 4), bool),
        points_camera=rng.normal(size=(3, 3)).astype(np.float32), T_camera_object=np.eye(4),
        T_world_camera=np.eye(4), T_world_object=yaw_transform(i, 0.0, 0.1 * i, 1.0),
        size=np.array([1.0, 0.1, 2.0]), color_hist=np.full(8, 0.125, np.float32),
        descriptors=np.zeros((0, 32), np.uint8), gt_instance=i,
    )


def _insert(store: MapStore, *keys: tuple[str, str, int]) -> None:
    for robot, session, seq in keys:
        store.insert(*keyframe(robot, session, seq), 1.0)


def _pose(robot: str, session: str, seq: int, on_map: bool = True) -> MappedPose:
    if not on_map:
        return MappedPose(robot, session, seq, None, None)
    return MappedPose(robot, session, seq, yaw_transform(seq, 1.0, 0.2, 0.5), CAMERA)


def _on_graph(store: MapStore, *keys: tuple[str, str, int]) -> None:
    """Put ``keys`` on the back-end's graph at the pose :func:`_pose` gives them (replay reads the
    back-end's estimate)."""
    nodes = [GraphNodeRow(k, 1.0, np.eye(4), "rgb", _pose(*k).T_map_camera, None, b"") for k in keys]
    store.commit_graph("backend", 0, GraphChange(nodes))


def test_keyframes_in_insertion_order(store: MapStore) -> None:
    """Keyframes are numbered in the order they were stored; the stage reads, counts and asks
    about them after a position."""
    _insert(store, ("r1", "b", 5), ("r2", "a", 0), ("r1", "b", 2))
    got = store.next_keyframes(0, 10)
    assert [(k.rowid, k.key) for k in got] == [(1, "r1/b/5"), (2, "r2/a/0"), (3, "r1/b/2")]
    assert got[1].payload == keyframe("r2", "a", 0)[1]
    assert [k.rowid for k in store.next_keyframes(1, 1)] == [2]
    assert store.next_keyframes(3, 10) == []
    assert [store.count_keyframes_after(i) for i in range(4)] == [3, 2, 1, 0]
    assert store.session_has_keyframes_after("r1", "b", 1)
    assert not store.session_has_keyframes_after("r1", "b", 3)
    assert not store.session_has_keyframes_after("r2", "a", 2)


def test_committed_keyframes_replay_with_their_measurements(store: MapStore) -> None:
    """A commit stores measurements, measured pose and cursor together; replay gives the keyframes
    the back-end put on the map, in order, with their measurements (masks empty), within the range
    and limit."""
    _insert(store, ("r1", "s", 0), ("r1", "s", 1), ("r2", "t", 0), ("r1", "s", 2))
    _on_graph(store, ("r1", "s", 0), ("r1", "s", 1), ("r1", "s", 2))
    assert store.cursor("mapping") == 0
    ms = {i: [_measurement(f"k{i}", 2 * i), _measurement(f"k{i}", 2 * i + 1)] for i in range(4)}
    store.commit_keyframe("mapping", 1, _pose("r1", "s", 0), ms[0], anchored=True)
    store.commit_keyframe("mapping", 2, _pose("r1", "s", 1), [], anchored=True)
    store.commit_keyframe("mapping", 3, _pose("r2", "t", 0, on_map=False), ms[2], anchored=False)
    store.commit_keyframe("mapping", 4, _pose("r1", "s", 2), ms[3], anchored=True)
    assert store.cursor("mapping") == 4 and store.cursor("other") == 0
    assert store.count_measurements() == 6
    replay = store.anchored_keyframes(0, 4, 10)
    assert [(k.rowid, k.robot_id, k.session_id, k.seq) for k in replay] == [
        (1, "r1", "s", 0), (2, "r1", "s", 1), (4, "r1", "s", 2)]
    assert replay[0].camera == CAMERA
    assert np.array_equal(replay[2].T_map_camera, yaw_transform(2, 1.0, 0.2, 0.5))
    assert [[m.gt_instance for m in k.measurements] for k in replay] == [[0, 1], [], [6, 7]]
    assert all(m.mask.shape == (0, 0) for k in replay for m in k.measurements)
    assert np.array_equal(replay[2].measurements[1].T_world_object, ms[3][1].T_world_object)
    assert [k.rowid for k in store.anchored_keyframes(0, 4, 2)] == [1, 2]
    assert [k.rowid for k in store.anchored_keyframes(1, 3, 10)] == [2]
    assert store.anchored_keyframes(4, 10, 10) == []


def test_keyframes_without_a_map_pose_are_found_and_recorded(store: MapStore) -> None:
    """Keyframes processed before map poses were kept have none; recording one makes it replayable."""
    _insert(store, ("r1", "s", 0), ("r1", "s", 1), ("r1", "s", 2))
    _on_graph(store, ("r1", "s", 0), ("r1", "s", 1))
    store.commit_keyframe("mapping", 2, _pose("r1", "s", 1), [], anchored=True)
    assert store.unmapped_keyframes(2, 10) == [KeyframeKey(1, "r1", "s", 0)]
    assert store.unmapped_keyframes(3, 1) == [KeyframeKey(1, "r1", "s", 0)]
    store.record_mapped([_pose("r1", "s", 0), _pose("r1", "s", 2, on_map=False)])
    assert store.unmapped_keyframes(3, 10) == []
    assert [k.rowid for k in store.anchored_keyframes(0, 3, 10)] == [1, 2]


def test_closed_sessions(store: MapStore) -> None:
    """Closures are kept once per session and cursor, and read back by cursor range in order."""
    store.close_sessions([("r2", "a"), ("r1", "b")], 5)
    store.close_sessions([("r1", "b")], 5)
    store.close_sessions([("r1", "c")], 2)
    assert store.closed_sessions() == [ClosedSession(2, "r1", "c"), ClosedSession(5, "r1", "b"),
                                       ClosedSession(5, "r2", "a")]
    assert store.closed_sessions(3) == store.closed_sessions(5, 5) == store.closed_sessions()[1:]
    assert store.closed_sessions(0, 4) == [ClosedSession(2, "r1", "c")]


def test_one_checkpoint_is_kept(store: MapStore) -> None:
    assert store.checkpoint() is None
    first = Checkpoint(4, '{"format": 1}', b"\x00state", 100.0)
    store.save_checkpoint(first)
    got = store.checkpoint()
    assert got is not None and (got.last_rowid, got.config_key, got.state, got.written_s) == (
        4, '{"format": 1}', b"\x00state", 100.0)
    store.save_checkpoint(replace(first, last_rowid=9, state=b"later"))
    got = store.checkpoint()
    assert got is not None and (got.last_rowid, got.state) == (9, b"later")

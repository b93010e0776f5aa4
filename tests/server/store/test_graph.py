"""Protocol tests of the back-end's records (:class:`~wardmap.server.store.GraphStore`), run
against every backend (``conftest.BACKENDS``): nodes with codes and estimates, factors, session
anchoring, pending votes, the graph epoch, map trajectories, and replay reading the back-end's poses."""

from __future__ import annotations

import numpy as np
import pytest

from wardmap.server.store import GraphChange, GraphEdgeRow, GraphNodeRow, MappedPose, MapStore, SessionAnchor
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.se3 import yaw_transform

from .conftest import T0, Backend, keyframe, pose_at

CAMERA = PinholeCamera(64, 48, 50.0, 50.0, 31.5, 23.5)


def _node(robot: str, session: str, seq: int, on_map: bool = True) -> GraphNodeRow:
    T = pose_at(T0 + seq)
    return GraphNodeRow((robot, session, seq), T0 + seq, T, "rgb", yaw_transform(0.5, 1.0, 2.0, 0.0) @ T
                        if on_map else None, None, bytes([seq % 16]) * 8)


def _edge(a: tuple[str, str, int], b: tuple[str, str, int], kind: str = "odometry") -> GraphEdgeRow:
    return GraphEdgeRow(kind, a, b, yaw_transform(0.1, 0.2, 0.0, 0.0), np.arange(1.0, 7.0) / 100,
                        kind == "loop", 40 if kind == "loop" else 0)


def test_a_committed_graph_reads_back_in_order_with_its_cursor(backend: Backend) -> None:
    with backend.open() as store:
        for seq in range(3):
            store.insert(*keyframe("r1", "s1", seq), 1.0)
        nodes = [_node("r1", "s1", seq) for seq in range(3)]
        edges = [_edge(nodes[0].key, nodes[1].key), _edge(nodes[2].key, nodes[0].key, "loop"),
                 GraphEdgeRow("prior", nodes[0].key, None, np.eye(4), np.full(6, 1e-3), False)]
        store.commit_graph("backend", 2, GraphChange(nodes[:2], edges[:1]))
        store.commit_graph("backend", 3, GraphChange(nodes[2:], edges[1:], bump_epoch=True))
        assert store.cursor("backend") == 3 and store.graph_epoch() == 1
    with backend.open() as store:  # committed: a new handle sees it
        got_nodes, got_edges = store.graph_records()
    assert [n.key for n in got_nodes] == [n.key for n in nodes]
    for got, want in zip(got_nodes, nodes, strict=True):
        assert got.stamp == want.stamp and got.pose_source == "rgb" and got.codes == want.codes
        np.testing.assert_array_equal(got.T_odom_camera, want.T_odom_camera)
        assert got.T_map_camera is not None and want.T_map_camera is not None
        np.testing.assert_array_equal(got.T_map_camera, want.T_map_camera)
        assert got.prior_T_map_odom is None
    assert [(e.kind, e.a, e.b, e.robust, e.inliers) for e in got_edges] == [
        (e.kind, e.a, e.b, e.robust, e.inliers) for e in edges]
    np.testing.assert_array_equal(got_edges[0].sigmas, edges[0].sigmas)
    np.testing.assert_array_equal(got_edges[1].T_a_b, edges[1].T_a_b)


def test_pending_votes_are_replaced_with_the_graph_and_kept_when_unchanged(store: MapStore) -> None:
    assert store.graph_pending() is None
    for seq in range(3):
        store.insert(*keyframe("r1", "s1", seq), 1.0)
    store.commit_graph("backend", 1, GraphChange([_node("r1", "s1", 0)], pending=b"first"))
    store.commit_graph("backend", 2, GraphChange([_node("r1", "s1", 1)]))  # None: unchanged
    assert store.graph_pending() == b"first"
    store.commit_graph("backend", 3, GraphChange([_node("r1", "s1", 2)], pending=b""))
    assert store.graph_pending() == b"" and store.cursor("backend") == 3


def test_bundle_edges_are_stored(store: MapStore) -> None:
    for seq in range(2):
        store.insert(*keyframe("r1", "s1", seq), 1.0)
    nodes = [_node("r1", "s1", seq) for seq in range(2)]
    edges = [_edge(nodes[0].key, nodes[1].key), _edge(nodes[0].key, nodes[1].key, "bundle")]
    store.commit_graph("backend", 2, GraphChange(nodes, edges))
    assert [e.kind for e in store.graph_records()[1]] == ["odometry", "bundle"]


def test_estimates_sessions_and_the_latest_node_per_robot(store: MapStore) -> None:
    for seq in range(2):
        store.insert(*keyframe("r1", "s1", seq), 1.0)
    store.insert(*keyframe("r2", "a", 5), 1.0)
    floating = _node("r2", "a", 5, on_map=False)
    store.commit_graph("backend", 3, GraphChange(
        [_node("r1", "s1", 0), _node("r1", "s1", 1), floating],
        sessions=[SessionAnchor("r1", "s1", np.eye(4), 10.0, "r1/s1", 1),
                  SessionAnchor("r2", "a", None, None, "", 0)]))
    assert store.graph_poses([("r2", "a", 5)]) == {("r2", "a", 5): None}
    assert store.graph_poses([("r9", "x", 0)]) == {("r9", "x", 0): None}
    # r2 gets anchored: its estimate and its session row are replaced, the epoch moves
    moved = yaw_transform(0.0, 5.0, 5.0, 0.0)
    store.commit_graph("backend", 3, GraphChange(
        estimates=[(("r2", "a", 5), moved)],
        sessions=[SessionAnchor("r2", "a", moved, 20.0, "r1/s1", 1)], bump_epoch=True))
    pose = store.graph_poses([("r2", "a", 5)])[("r2", "a", 5)]
    assert pose is not None
    np.testing.assert_array_equal(pose, moved)
    anchors = store.session_anchors()
    assert [(a.robot_id, a.session_id, a.anchored_to, a.revision, a.anchored_s) for a in anchors] == [
        ("r1", "s1", "r1/s1", 1, 10.0), ("r2", "a", "r1/s1", 1, 20.0)]
    latest = store.latest_nodes()
    assert latest["r1"].key == ("r1", "s1", 1) and latest["r2"].key == ("r2", "a", 5)
    assert store.graph_epoch() == 1


def test_the_map_trajectory_holds_only_anchored_keyframes(store: MapStore) -> None:
    for seq in range(3):
        store.insert(*keyframe("r1", "s1", seq), 1.0)
    store.commit_graph("backend", 3, GraphChange([_node("r1", "s1", 0), _node("r1", "s1", 1, on_map=False),
                                                  _node("r1", "s1", 2)]))
    stamps, T = store.map_trajectory("r1")
    assert list(stamps) == [T0, T0 + 2] and T.shape == (2, 4, 4)
    assert len(store.map_trajectory("r1", "other")[0]) == 0
    assert len(store.map_trajectory("nobody")[0]) == 0


def test_replay_reads_the_back_ends_pose_and_the_measured_one(store: MapStore) -> None:
    """``anchored_keyframes`` gives keyframes the back-end put on the map, with the pose their
    measurements were computed with; keyframes the back-end has no estimate for wait."""
    for seq in range(2):
        store.insert(*keyframe("r1", "s1", seq), 1.0)
    measured = [pose_at(T0), pose_at(T0 + 1)]
    for seq in range(2):
        store.commit_keyframe("mapping", seq + 1, MappedPose("r1", "s1", seq, measured[seq], CAMERA), [],
                              anchored=False)
    assert store.anchored_keyframes(0, 2, 10) == []  # no graph yet
    store.commit_graph("backend", 2, GraphChange([_node("r1", "s1", 0), _node("r1", "s1", 1, on_map=False)]))
    rows = store.anchored_keyframes(0, 2, 10)
    assert [r.seq for r in rows] == [0]
    assert rows[0].T_measured_camera is not None
    np.testing.assert_array_equal(rows[0].T_measured_camera, measured[0])
    np.testing.assert_array_equal(rows[0].T_map_camera, _node("r1", "s1", 0).T_map_camera)


@pytest.mark.parametrize("bad", ["kind", "sigmas"])
def test_a_bad_graph_row_commits_nothing(store: MapStore, bad: str) -> None:
    store.insert(*keyframe("r1", "s1", 0), 1.0)
    node = _node("r1", "s1", 0)
    edge = _edge(node.key, node.key)
    if bad == "kind":
        edge = GraphEdgeRow("teleport", edge.a, edge.b, edge.T_a_b, edge.sigmas, False)
    else:
        edge = GraphEdgeRow("odometry", edge.a, edge.b, edge.T_a_b, np.ones(5), False)
    from wardmap.server.store import StoreError

    with pytest.raises(StoreError):
        store.commit_graph("backend", 1, GraphChange([node], [edge]))
    assert store.graph_records() == ([], []) and store.cursor("backend") == 0

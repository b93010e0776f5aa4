"""Pose graph on iSAM2: synthetic trajectories with known ground truth and seeded odometry drift.

Camera frame x right, y down, z forward: the robots drive forward along camera z and turn
about camera y (the vertical), so every trajectory lies in a horizontal plane of the map.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from wardmap.server.backend.graph import (
    EdgeRecord,
    GraphConfig,
    GraphError,
    NodeKey,
    NodeRecord,
    OdometrySigmas,
    PoseGraph,
    SessionKey,
)
from wardmap.shared.errors import ConfigError
from wardmap.shared.se3 import inverse, make_transform, rotation_angle, se3_exp

F64 = np.ndarray


def _turn(angle_rad: float) -> F64:
    """Rotation (3, 3) about the camera's y axis (vertical, pointing down)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _forward(step_m: float) -> F64:
    return make_transform(np.eye(3), [0.0, 0.0, step_m])


def _square(side_m: float = 10.0, step_m: float = 0.5, start: F64 | None = None) -> list[F64]:
    """True T_map_camera of keyframes around a square (side_m), ending back at the start."""
    T = np.eye(4) if start is None else start.copy()
    poses = []
    for _ in range(4):
        for _ in range(round(side_m / step_m)):
            poses.append(T.copy())
            T = T @ _forward(step_m)
        for _ in range(3):
            poses.append(T.copy())
            T = T @ make_transform(_turn(math.pi / 6), [0.0, 0.0, 0.0])
    poses.append(T.copy())
    return poses


def _line(n: int, step_m: float = 0.5, start: F64 | None = None) -> list[F64]:
    T = np.eye(4) if start is None else start.copy()
    return [T @ _forward(step_m * i) for i in range(n)]


def _odometry(true: list[F64], rng: np.random.Generator, *, yaw_bias_deg: float = 0.0,
              noise_m: float = 0.001, noise_rad: float = 0.0005, T_odom_map: F64 | None = None) -> list[F64]:
    """Drifting T_odom_camera: the true steps, each turned by ``yaw_bias_deg`` about the
    vertical and perturbed by seeded noise; the first pose is ``T_odom_map @ true[0]``."""
    odom = [(np.eye(4) if T_odom_map is None else T_odom_map) @ true[0]]
    bias = make_transform(_turn(math.radians(yaw_bias_deg)), [0.0, 0.0, 0.0])
    for a, b in itertools.pairwise(true):
        xi = np.concatenate([rng.normal(0.0, noise_m, 3), rng.normal(0.0, noise_rad, 3)])
        odom.append(odom[-1] @ inverse(a) @ b @ bias @ se3_exp(xi))
    return odom


def _ate_m(graph: PoseGraph, keys: list[NodeKey], true: list[F64]) -> float:
    """RMS translation error (m) of the estimates against the truth (same map frame, no alignment)."""
    errors = []
    for key, T_true in zip(keys, true, strict=True):
        est = graph.estimate(key)
        assert est is not None
        errors.append(np.linalg.norm(est[:3, 3] - T_true[:3, 3]))
    return float(np.sqrt(np.mean(np.square(errors))))


def _keys(session: SessionKey, n: int) -> list[NodeKey]:
    return [(session[0], session[1], i) for i in range(n)]


def _run_square(loop_T: F64 | None, config: GraphConfig | None = None) -> tuple[float, PoseGraph]:
    """Drive the square with 0.05 deg/step yaw drift; optionally close it at the last keyframe
    with ``loop_T`` (T_a_b of the first keyframe a to the last keyframe b). Returns ATE, graph."""
    true = _square()
    odom = _odometry(true, np.random.default_rng(0), yaw_bias_deg=0.05)
    keys = _keys(("r1", "s1"), len(true))
    graph = PoseGraph(config)
    for key, T in zip(keys, odom, strict=True):
        graph.add_keyframe(key, T, pose_source="rgb")
        if key == keys[-1] and loop_T is not None:
            assert graph.add_loop(keys[0], key, loop_T, inliers=100) == "loop"
        graph.update()
    return _ate_m(graph, keys, true), graph


def test_loop_closure_reduces_drift() -> None:
    """A 40 m square with yaw drift: one loop edge from the last keyframe to the first (the true
    relative pose) cuts the trajectory error well below odometry alone."""
    true = _square()
    ate_odometry, _ = _run_square(None)
    ate_loop, graph = _run_square(inverse(true[0]) @ true[-1])
    assert ate_odometry > 0.15
    assert ate_loop < 0.6 * ate_odometry
    est_last = graph.estimate(("r1", "s1", len(true) - 1))
    assert est_last is not None and np.linalg.norm(est_last[:3, 3] - true[-1][:3, 3]) < 0.05


def test_wrong_loop_is_downweighted() -> None:
    """A loop edge 2 m off the truth: under the robust kernel the graph keeps the odometry's
    shape (the edge stays violated by more than half its 2 m, the error grows little), while the same
    edge under a practically quadratic kernel (huge Cauchy k) is met and drags the graph away."""
    true = _square()
    wrong = inverse(true[0]) @ true[-1] @ _forward(2.0)
    first, last = ("r1", "s1", 0), ("r1", "s1", len(true) - 1)

    def violation_m(graph: PoseGraph) -> float:
        T_a, T_b = graph.estimate(first), graph.estimate(last)
        assert T_a is not None and T_b is not None
        return float(np.linalg.norm((inverse(T_a) @ T_b)[:3, 3] - wrong[:3, 3]))

    ate_odometry, _ = _run_square(None)
    ate_robust, robust = _run_square(wrong)
    ate_quadratic, quadratic = _run_square(wrong, GraphConfig(robust_param=1e6))
    assert violation_m(robust) > 1.0 and violation_m(quadratic) < 0.5
    assert ate_robust < 1.5 * ate_odometry
    assert ate_quadratic > 2.5 * ate_robust


def test_second_session_floats_until_a_loop_anchors_it() -> None:
    """Session 2 starts in its own odom frame: no estimate until a loop edge to session 1 ties
    it in; then its T_map_odom matches the truth and its new keyframes go straight in."""
    rng = np.random.default_rng(1)
    s1, s2 = ("r1", "s1"), ("r2", "s1")
    true1 = _line(20)
    T_map_odom2 = make_transform(_turn(0.7), [3.0, 0.0, -2.0])
    true2 = _line(12, start=true1[5] @ make_transform(_turn(0.3), [0.4, 0.0, 0.2]))
    odom1 = _odometry(true1, rng)
    odom2 = _odometry(true2, rng, T_odom_map=inverse(T_map_odom2))
    graph = PoseGraph()
    for i, T in enumerate(odom1):
        graph.add_keyframe((*s1, i), T, pose_source="rgb")
    first = graph.update()
    assert first.anchored == (s1,) and set(first.sessions) == {s1}
    for i, T in enumerate(odom2[:10]):
        graph.add_keyframe((*s2, i), T, pose_source="rgb")
        assert graph.update().sessions == {}
    assert not graph.anchored(s2)
    assert graph.estimate((*s2, 3)) is None and graph.T_map_odom(s2) is None
    assert graph.sessions() == [s1, s2]

    loop = inverse(true1[5]) @ true2[0]
    assert graph.add_loop((*s1, 5), (*s2, 0), loop, inliers=150) == "anchored"
    assert graph.anchored(s2)
    up = graph.update()
    assert up.anchored == (s2,)
    assert set(up.sessions) == {s2}
    T = graph.T_map_odom(s2)
    assert T is not None
    assert np.linalg.norm(T[:3, 3] - T_map_odom2[:3, 3]) < 0.01
    assert math.degrees(rotation_angle(T[:3, :3].T @ T_map_odom2[:3, :3])) < 0.2
    assert np.allclose(up.sessions[s2], T)

    graph.add_keyframe((*s2, 10), odom2[10], pose_source="rgb")
    est = graph.estimate((*s2, 10))
    assert est is not None and np.linalg.norm(est[:3, 3] - true2[10][:3, 3]) < 0.02
    assert graph.update().anchored == ()


def test_two_floating_sessions_follow_one_anchor() -> None:
    """Sessions 2 and 3 both float and share a loop edge (kept pending); when session 3 gets a
    loop edge to session 1, session 2 is anchored through the pending edge too."""
    rng = np.random.default_rng(2)
    s1, s2, s3 = ("r1", "a"), ("r2", "b"), ("r3", "c")
    true1 = _line(10)
    true2 = _line(8, start=make_transform(_turn(1.0), [5.0, 0.0, 5.0]))
    true3 = _line(8, start=make_transform(_turn(-0.5), [2.0, 0.0, 1.0]))
    frames = {s2: make_transform(_turn(2.0), [-4.0, 0.0, 1.0]),
              s3: make_transform(_turn(-1.0), [7.0, 0.0, 0.0])}
    graph = PoseGraph()
    for i, T in enumerate(_odometry(true1, rng)):
        graph.add_keyframe((*s1, i), T, pose_source="rgb")
    graph.update()
    for s, true in ((s2, true2), (s3, true3)):
        for i, T in enumerate(_odometry(true, rng, T_odom_map=inverse(frames[s]))):
            graph.add_keyframe((*s, i), T, pose_source="rgb")
    assert graph.add_loop((*s2, 4), (*s3, 6), inverse(true2[4]) @ true3[6], inliers=80) == "floating"
    assert graph.update().anchored == ()
    assert not graph.anchored(s2) and not graph.anchored(s3)

    assert graph.add_loop((*s3, 1), (*s1, 7), inverse(true3[1]) @ true1[7], inliers=120) == "anchored"
    up = graph.update()
    assert up.anchored == (s3, s2)
    assert set(up.sessions) == {s2, s3}
    for s in (s2, s3):
        T = graph.T_map_odom(s)
        assert T is not None and np.linalg.norm(T[:3, 3] - frames[s][:3, 3]) < 0.01


def test_prior_anchors_a_session_at_once() -> None:
    """A session started with a --map-pose prior is anchored at its first keyframe; the first
    session's prior defines the map frame."""
    rng = np.random.default_rng(3)
    T_map_odom1 = make_transform(_turn(0.4), [1.0, 0.0, 2.0])
    T_map_odom2 = make_transform(_turn(-1.2), [-3.0, 0.0, 6.0])
    graph = PoseGraph()
    odom1 = _odometry(_line(5), rng, T_odom_map=inverse(T_map_odom1))
    graph.add_keyframe(("r1", "s", 0), odom1[0], pose_source="rgb", prior_T_map_odom=T_map_odom1)
    graph.add_keyframe(("r1", "s", 1), odom1[1], pose_source="rgb", prior_T_map_odom=T_map_odom1)
    odom2 = _odometry(_line(5, start=make_transform(_turn(0.2), [0.0, 0.0, 4.0])), rng,
                      T_odom_map=inverse(T_map_odom2))
    graph.add_keyframe(("r2", "s", 0), odom2[0], pose_source="odometry", prior_T_map_odom=T_map_odom2)
    assert graph.anchored(("r1", "s")) and graph.anchored(("r2", "s"))
    est = graph.estimate(("r2", "s", 0))
    assert est is not None and np.allclose(est, T_map_odom2 @ odom2[0])
    up = graph.update()
    assert up.anchored == (("r1", "s"), ("r2", "s"))
    for s, T_true in ((("r1", "s"), T_map_odom1), (("r2", "s"), T_map_odom2)):
        T = graph.T_map_odom(s)
        assert T is not None and np.allclose(T, T_true, atol=1e-6)
    priors = [e for e in graph.records()[1] if e.kind == "prior"]
    assert [e.a for e in priors] == [("r1", "s", 0), ("r2", "s", 0)]


def test_late_prior_anchors_a_floating_session() -> None:
    """A floating session whose later keyframe brings a prior is anchored there, all its
    keyframes at once; a prior on an anchored session adds no factor."""
    rng = np.random.default_rng(7)
    graph = PoseGraph()
    graph.add_keyframe(("r1", "s", 0), np.eye(4), pose_source="init")
    T_map_odom = make_transform(_turn(0.9), [4.0, 0.0, -1.0])
    odom = _odometry(_line(6, start=make_transform(np.eye(3), [2.0, 0.0, 0.0])), rng,
                     T_odom_map=inverse(T_map_odom))
    for i in range(3):
        graph.add_keyframe(("r2", "s", i), odom[i], pose_source="rgb")
    assert not graph.anchored(("r2", "s"))
    graph.add_keyframe(("r2", "s", 3), odom[3], pose_source="rgb", prior_T_map_odom=T_map_odom)
    assert graph.anchored(("r2", "s"))
    for i in range(4):
        est = graph.estimate(("r2", "s", i))
        assert est is not None and np.allclose(est, T_map_odom @ odom[i])
    graph.add_keyframe(("r2", "s", 4), odom[4], pose_source="rgb", prior_T_map_odom=np.eye(4))
    priors = [(e.a, e.sigmas[3]) for e in graph.records()[1] if e.kind == "prior"]
    assert priors == [(("r1", "s", 0), graph.config.gauge_sigmas[3]),
                      (("r2", "s", 3), graph.config.prior_sigmas[3])]
    assert graph.update().anchored == (("r1", "s"), ("r2", "s"))


def _busy_graph() -> tuple[PoseGraph, list[tuple[NodeKey, F64]]]:
    """Three sessions: a drifting square closed by a loop, a second session anchored through a
    loop edge, a third floating with its own loop edge and a pending edge to a fourth."""
    rng = np.random.default_rng(4)
    graph = PoseGraph()
    true1 = _square()
    for i, T in enumerate(_odometry(true1, rng, yaw_bias_deg=0.05)):
        graph.add_keyframe(("r1", "s1", i), T, pose_source="rgb" if i % 7 else "odometry")
        if i == len(true1) - 1:
            graph.add_loop(("r1", "s1", 0), ("r1", "s1", i), inverse(true1[0]) @ true1[i], inliers=90)
        if i % 3 == 0:
            graph.update()
    true2 = _line(15, start=true1[30] @ make_transform(_turn(0.5), [0.3, 0.0, 0.0]))
    for i, T in enumerate(_odometry(true2, rng, T_odom_map=make_transform(_turn(1.0), [2.0, 0.0, 0.0]))):
        graph.add_keyframe(("r2", "s1", i), T, pose_source="depth")
        if i == 6:
            graph.add_loop(("r2", "s1", 6), ("r1", "s1", 30), inverse(true2[6]) @ true1[30], inliers=60)
        graph.update()
    true3 = _line(6, start=true1[50])
    for i, T in enumerate(_odometry(true3, rng, T_odom_map=make_transform(_turn(-0.3), [0.0, 0.0, 9.0]))):
        graph.add_keyframe(("r3", "s1", i), T, pose_source="rgb")
    graph.add_loop(("r3", "s1", 0), ("r3", "s1", 5), inverse(true3[0]) @ true3[5], inliers=50)
    graph.add_keyframe(("r4", "s1", 0), np.eye(4), pose_source="init")
    graph.add_loop(("r3", "s1", 2), ("r4", "s1", 0), inverse(true3[2]) @ true3[3], inliers=40)
    graph.update()
    extra = [(("r1", "s1", len(true1) + i), true1[-1] @ _forward(0.5 * (i + 1))) for i in range(5)]
    return graph, extra


def _assert_same_estimates(g1: PoseGraph, g2: PoseGraph, tol: float) -> None:
    nodes1, _ = g1.records()
    for node in nodes1:
        e1, e2 = g1.estimate(node.key), g2.estimate(node.key)
        assert (e1 is None) == (e2 is None), node.key
        if e1 is not None and e2 is not None:
            assert np.abs(e1 - e2).max() < tol, (node.key, np.abs(e1 - e2).max())
    for s in g1.sessions():
        assert g1.anchored(s) == g2.anchored(s)


def test_restore_round_trip_keeps_estimates_and_accepts_more() -> None:
    """records() -> restore() rebuilds the graph: same sessions, anchoring, edges and estimates
    (to 1e-6); both graphs then take the same further keyframes and a loop edge that anchors
    the floating pair, and still agree."""
    graph, extra = _busy_graph()
    nodes, edges = graph.records()
    restored = PoseGraph.restore(graph.config, nodes, edges)
    assert restored.sessions() == graph.sessions()
    assert not restored.anchored(("r3", "s1")) and not restored.anchored(("r4", "s1"))
    restored_edges = restored.records()[1]
    assert ([(e.kind, e.a, e.b, e.robust) for e in restored_edges]
            == [(e.kind, e.a, e.b, e.robust) for e in edges])
    assert all(np.array_equal(r.T_a_b, e.T_a_b) and np.array_equal(r.sigmas, e.sigmas)
               for r, e in zip(restored_edges, edges, strict=True))
    assert restored.new_records() == ([], [])
    _assert_same_estimates(graph, restored, 1e-6)
    for g in (graph, restored):
        for key, T in extra:
            g.add_keyframe(key, T, pose_source="rgb")
        assert g.add_loop(("r1", "s1", 50), ("r3", "s1", 0), np.eye(4), inliers=70) == "anchored"
        up = g.update()
        assert up.anchored == (("r3", "s1"), ("r4", "s1"))
    _assert_same_estimates(graph, restored, 1e-5)


def test_new_records_returns_each_record_once() -> None:
    """Records drained after every keyframe, concatenated, equal records() of the whole graph;
    restoring from them (estimates as they were when emitted) gives the same graph to 1 mm."""
    rng = np.random.default_rng(5)
    graph = PoseGraph()
    nodes: list[NodeRecord] = []
    edges: list[EdgeRecord] = []
    true = _square()
    for i, T in enumerate(_odometry(true, rng, yaw_bias_deg=0.05)):
        graph.add_keyframe(("r1", "s1", i), T, pose_source="rgb")
        if i == len(true) - 1:
            graph.add_loop(("r1", "s1", 0), ("r1", "s1", i), inverse(true[0]) @ true[i], inliers=100)
        graph.update()
        n, e = graph.new_records()
        nodes += n
        edges += e
    assert graph.new_records() == ([], [])
    all_nodes, all_edges = graph.records()
    assert [n.key for n in nodes] == [n.key for n in all_nodes]
    assert len({n.key for n in nodes}) == len(nodes)
    assert [(e.kind, e.a, e.b) for e in edges] == [(e.kind, e.a, e.b) for e in all_edges]
    assert [e.kind for e in edges].count("loop") == 1 and [e.kind for e in edges].count("prior") == 1
    restored = PoseGraph.restore(graph.config, nodes, edges)
    _assert_same_estimates(graph, restored, 1e-3)


def test_update_reports_changed_sessions_only() -> None:
    """GraphUpdate.sessions holds a session when it is anchored or its T_map_odom moves (a loop
    edge between two anchored sessions), not after a plain keyframe."""
    rng = np.random.default_rng(6)
    s1, s2 = ("r1", "s1"), ("r2", "s1")
    true1 = _line(10)
    T_map_odom2 = make_transform(_turn(0.2), [0.0, 0.0, 1.0])
    true2 = _line(10, start=make_transform(np.eye(3), [1.0, 0.0, 0.0]))
    graph = PoseGraph()
    graph.add_keyframe((*s1, 0), true1[0], pose_source="init")
    up = graph.update()
    assert up.anchored == (s1,) and np.allclose(up.sessions[s1], np.eye(4)) and up.moved_m == 0.0
    odom2 = _odometry(true2, rng, T_odom_map=inverse(T_map_odom2))
    off = make_transform(_turn(0.05), [0.2, 0.0, 0.0])  # a 20 cm, 3 deg error in session 2's prior
    graph.add_keyframe((*s2, 0), odom2[0], pose_source="init", prior_T_map_odom=off @ T_map_odom2)
    for i in range(1, 10):
        graph.add_keyframe((*s1, i), true1[i], pose_source="rgb")
        graph.add_keyframe((*s2, i), odom2[i], pose_source="rgb")
        up = graph.update()
        assert up.anchored == (s2,) if i == 1 else up.anchored == ()
        assert set(up.sessions) == ({s2} if i == 1 else set())
    for i in (2, 5, 8):
        graph.add_loop((*s1, i), (*s2, i), inverse(true1[i]) @ true2[i], inliers=200)
    up = graph.update()
    assert up.anchored == ()
    assert s2 in up.sessions and up.moved_m > 0.05
    T = graph.T_map_odom(s2)
    assert T is not None and np.allclose(up.sessions[s2], T)
    assert np.linalg.norm(T[:3, 3] - T_map_odom2[:3, 3]) < 0.05


def test_bad_input_raises() -> None:
    """Duplicate keys, unknown loop ends, bad inlier counts and bad config
    values are refused with the project's errors."""
    graph = PoseGraph()
    graph.add_keyframe(("r", "s", 5), np.eye(4), pose_source="rgb")
    with pytest.raises(GraphError):
        graph.add_keyframe(("r", "s", 5), np.eye(4), pose_source="rgb")
    with pytest.raises(GraphError):
        graph.add_keyframe(("r", "s", 6), np.eye(4), pose_source="sonar")
    graph.add_keyframe(("r", "s", 6), np.eye(4), pose_source="rgb")
    with pytest.raises(GraphError):
        graph.add_loop(("r", "s", 5), ("r", "s", 99), np.eye(4), inliers=50)
    with pytest.raises(GraphError):
        graph.add_loop(("r", "s", 5), ("r", "s", 6), np.eye(4), inliers=0)
    with pytest.raises(ConfigError, match="robust_param"):
        GraphConfig(robust_param=0.0)
    with pytest.raises(ConfigError, match="trans_m"):
        OdometrySigmas(rot_deg=0.1, trans_m=-1.0, rot_deg_per_m=0.0, rot_per_rad=0.0, trans_per_m=0.0)
    with pytest.raises(ConfigError, match="gauge_sigmas"):
        GraphConfig(gauge_sigmas=(1.0, 1.0, 1.0, 1.0, 1.0))


def test_odometry_sigmas_follow_pose_source_and_step() -> None:
    """Odometry edges get the later keyframe's pose-source sigmas, growing with the step; loop
    sigmas shrink with more inliers down to the floor."""
    cfg = GraphConfig()
    graph = PoseGraph(cfg)
    graph.add_keyframe(("r", "s", 0), np.eye(4), pose_source="init")
    graph.add_keyframe(("r", "s", 1), _forward(0.5), pose_source="rgb")
    graph.add_keyframe(("r", "s", 2), _forward(1.5), pose_source="none")
    odo = [e for e in graph.records()[1] if e.kind == "odometry"]
    assert np.allclose(odo[0].sigmas, cfg.odometry.rgb.sigmas(_forward(0.5)))
    assert np.allclose(odo[1].sigmas, cfg.odometry.none.sigmas(_forward(1.0)))
    assert np.all(odo[1].sigmas > odo[0].sigmas)
    assert cfg.odometry.rgb.sigmas(_forward(1.0))[3] > cfg.odometry.rgb.sigmas(_forward(0.1))[3]
    assert np.all(cfg.loop_sigmas(400) < cfg.loop_sigmas(30))
    assert np.allclose(cfg.loop_sigmas(10**8)[3:], cfg.loop_trans_floor_m)


def test_a_resent_keyframe_may_come_after_later_ones() -> None:
    """A robot resends an unacked keyframe after later ones were stored: its node links to the
    session's previous arrival, and every estimate follows the odometry."""
    graph = PoseGraph()
    poses = {seq: np.array([[1, 0, 0, 0.5 * seq], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], float)
             for seq in range(4)}
    for seq in (0, 1, 3, 2):
        graph.add_keyframe(("r", "s", seq), poses[seq], pose_source="rgb")
        graph.update()
    for seq, T in poses.items():
        est = graph.estimate(("r", "s", seq))
        assert est is not None
        np.testing.assert_allclose(est, T, atol=1e-6)


def test_a_long_chain_that_cholesky_cannot_solve_continues_with_qr() -> None:
    graph = PoseGraph(GraphConfig(factorization="cholesky"))
    T = np.eye(4)
    for j in range(1200):  # 600 m straight ahead, no loop: Cholesky gives up near 500 m
        T = T.copy()
        T[0, 3] = 0.5 * j
        graph.add_keyframe(("r", "s", j), T, pose_source="rgb")
        graph.update()
    assert graph.factorization == "qr"
    last = graph.estimate(("r", "s", 1199))
    assert last is not None and np.allclose(last, T, atol=1e-6)

"""The back-end's decisions on real tracked keyframes (``server/backend/core.py``): a simulated
aisle tracked by the edge frontend offline, replayed as sessions the core must place.

- a second session of the same drive, without a map pose, is anchored by verified place
  matches from several keyframes that agree, at the right ``T_map_odom``;
- a planted false loop (the same views again, but the robot's odometry says it is 3 m away, as
  at an identical door elsewhere) passes verification and is rejected by the graph gate;
- a session whose only matches disagree with each other is never anchored.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import msgpack
import numpy as np
import pytest

from wardmap.server.backend.core import BackendConfig, BackendCore
from wardmap.server.backend.graph import PoseGraph
from wardmap.server.backend.stage import BackendStage
from wardmap.server.store import open_store
from wardmap.shared import wire
from wardmap.shared.se3 import yaw_transform
from wardmap.shared.wire import KeyframeMsg

FRAMES = 60


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> list[KeyframeMsg]:
    """The keyframes of 6 s of aisle_slow_1 (seed 0), as the edge would send them."""
    from wardmap.sim.runner import generate
    from wardmap.tools.keyframes import dataset_keyframes

    path = tmp_path_factory.mktemp("core") / "aisle"
    generate("aisle_slow_1", 0, path, frames=FRAMES)
    msgs = list(dataset_keyframes(path, robot_id="r1", session_id="day1", labels="oracle"))
    assert len(msgs) >= 8
    return msgs


def _as(msgs: list[KeyframeMsg], robot: str, session: str, T: np.ndarray | None = None,
        seq0: int = 0, dt: float = 0.0) -> list[KeyframeMsg]:
    """The same keyframes as another session (odometry premultiplied by ``T``)."""
    T = np.eye(4) if T is None else T
    return [replace(m, robot_id=robot, session_id=session, seq=seq0 + i, stamp=m.stamp + dt,
                    T_odom_camera=T @ m.T_odom_camera, T_odom_base=None if m.T_odom_base is None
                    else T @ m.T_odom_base) for i, m in enumerate(msgs)]


def _angle_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1))))


def test_a_second_session_is_anchored_by_agreeing_verified_matches(drive: list[KeyframeMsg]) -> None:
    core = BackendCore(BackendConfig())
    for m in drive:
        res = core.add(m)
    assert core.anchored(("r1", "day1")) and not res.closures  # the first session sets the map
    T_true = yaw_transform(np.radians(30.0), 2.0, -1.0, 0.0)  # where day 2's odom frame started
    second = _as(drive, "r2", "day2", T=np.linalg.inv(T_true), dt=86_400.0)
    anchored_at = None
    votes = 0
    for i, m in enumerate(second):
        res = core.add(m)
        votes += res.rejected["anchor vote"]
        if anchored_at is None and core.anchored(("r2", "day2")):
            anchored_at = i
            assert [c.kind for c in res.closures] == ["anchor"]
            assert res.update.anchored == (("r2", "day2"),) and res.rebuild
    assert anchored_at is not None, "day 2 was never anchored"
    assert votes >= BackendConfig().anchor_votes - 1  # votes came first; the agreeing ones anchored
    T_map_odom = core.T_map_odom(("r2", "day2"))
    assert T_map_odom is not None
    err = np.linalg.inv(T_true) @ T_map_odom
    assert np.linalg.norm(err[:3, 3]) < 0.03 and _angle_deg(err) < 0.5
    # every keyframe of day 2 now has a map pose, on top of day 1's
    for a, b in zip(drive, second, strict=True):
        Ta, Tb = core.estimate(("r1", "day1", a.seq)), core.estimate(("r2", "day2", b.seq))
        assert Ta is not None and Tb is not None
        assert np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]) < 0.05


def test_a_planted_false_loop_passes_verification_and_is_rejected_by_the_graph(
    drive: list[KeyframeMsg]
) -> None:
    """The robot drives on and sees the very same views again, but its odometry (and so the map)
    puts it 3 m further on, like an identical door pair: the matches verify, the graph gate
    refuses them, and nothing moves."""
    core = BackendCore(BackendConfig(recent_s=0.0, recent_path_m=0.0))
    for m in drive:
        core.add(m)
    before = np.stack([core.estimate(("r1", "day1", m.seq)) for m in drive])
    twin = _as(drive, "r1", "day1", T=yaw_transform(0.0, 3.0, 0.0, 0.0), seq0=len(drive), dt=30.0)
    rejected = 0
    for m in twin:
        res = core.add(m)
        assert res.closures == [], res.closures
        rejected += res.rejected["inconsistent with the map"]
    assert rejected >= len(twin) // 2
    after = np.stack([core.estimate(("r1", "day1", m.seq)) for m in drive])
    np.testing.assert_allclose(after, before, atol=1e-6)


def test_matches_that_disagree_never_anchor_a_session(drive: list[KeyframeMsg]) -> None:
    """A floating session whose verified matches imply different ``T_map_odom`` (its keyframes'
    odometry scrambled) is not anchored: no agreeing votes."""
    core = BackendCore(BackendConfig())
    for m in drive:
        core.add(m)
    rng = np.random.default_rng(0)
    scrambled = [replace(m, robot_id="r3", session_id="x", stamp=m.stamp + 1e5,
                         T_odom_camera=yaw_transform(rng.uniform(-3, 3), *rng.uniform(-5, 5, 2), 0.0)
                         @ m.T_odom_camera)
                 for m in drive]
    for m in scrambled:
        core.add(m)
    assert not core.anchored(("r3", "x"))
    assert core.estimate(("r3", "x", scrambled[-1].seq)) is None


def test_a_keyframe_whose_image_cannot_be_read_joins_the_graph_without_recognition(
    drive: list[KeyframeMsg]
) -> None:
    """A valid message whose JPEG does not decode (its header passes the wire check) keeps its
    place in the graph (the odometry chain goes on) and is counted; nothing raises."""
    core = BackendCore(BackendConfig())
    broken = replace(drive[1], rgb_jpeg=drive[1].rgb_jpeg[:400])
    results = [core.add(m) for m in [drive[0], broken, *drive[2:]]]
    assert results[1].rejected["unreadable keyframe"] == 1
    assert set(results[1].codes) == {0xFF}
    for m in drive:
        est = core.estimate(("r1", "day1", m.seq))
        assert est is not None
        np.testing.assert_allclose(est, m.T_odom_camera, atol=1e-6)


def test_a_session_rests_loop_gap_keyframes_after_a_loop_edge(drive: list[KeyframeMsg]) -> None:
    core = BackendCore(BackendConfig(loop_gap=2))
    for m in drive:
        core.add(m)
    second = _as(drive, "r2", "day2", T=yaw_transform(np.radians(-20.0), 1.0, 0.5, 0.0), dt=86_400.0)
    searched = []
    anchored_at = None
    for i, m in enumerate(second):
        res = core.add(m)
        searched.append(res.searched)
        if anchored_at is None and res.closures:
            anchored_at = i
    assert anchored_at is not None and anchored_at + 3 < len(second)
    assert all(searched[: anchored_at + 1])
    # the two keyframes after the anchoring edge are not searched; the third is again
    assert searched[anchored_at + 1: anchored_at + 4] == [False, False, True]


def test_a_loop_between_anchored_sessions_bundle_adjusts_them(drive: list[KeyframeMsg]) -> None:
    """After a loop edge between two anchored sessions, their keyframes are bundle-adjusted
    and each consecutive pair gets one ``bundle`` edge; the edges survive a restore."""
    from wardmap.server.backend.graph import PoseGraph

    config = BackendConfig(loop_gap=0, bundle_enabled=True, bundle_process=False, bundle_min_pairs=3)
    core = BackendCore(config)
    for m in drive:
        core.add(m)
    second = _as(drive, "r2", "day2", T=yaw_transform(np.radians(-20.0), 1.0, 0.5, 0.0), dt=86_400.0)
    bundles = []
    for m in second:
        res = core.add(m)
        if res.bundle is not None:
            bundles.append(res)
            assert any(c.kind == "loop" for c in res.closures)
            assert res.ms["bundle"] > 0
    assert bundles, "no loop between the anchored sessions ran a bundle adjustment"
    nodes, edges = core.graph.records()
    pairs = [(e.a, e.b) for e in edges if e.kind == "bundle"]
    assert len(pairs) == len(set(pairs)) > 0  # once per pair
    assert all(a[:2] == b[:2] and b[2] == a[2] + 1 for a, b in pairs if b is not None)
    # the same views of both sessions stay together (the adjustment did not tear the map)
    for a, b in zip(drive, second, strict=True):
        Ta = core.estimate((a.robot_id, a.session_id, a.seq))
        Tb = core.estimate((b.robot_id, b.session_id, b.seq))
        assert Ta is not None and Tb is not None
        assert np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]) < 0.05
    restored = PoseGraph.restore(core.graph.config, nodes, edges)
    for n in nodes:
        est, got = core.estimate(n.key), restored.estimate(n.key)
        assert est is not None and got is not None
        np.testing.assert_allclose(got[:3, 3], est[:3, 3], atol=2e-3)


def test_the_server_bundle_adjusts_in_a_child_process_while_keyframes_go_on(
        drive: list[KeyframeMsg], tmp_path: Path) -> None:
    """With ``bundle_process`` (the default) the adjustment a loop starts runs in a child
    process: the back-end stage keeps adding keyframes meanwhile, and the result is committed
    when it is there (here: with no keyframe waiting, as its own commit, the cursor unchanged):
    one ``bundle`` edge per consecutive pair, the sessions' views still together."""
    config = BackendConfig(loop_gap=0, bundle_enabled=True, bundle_min_pairs=3)
    second = _as(drive, "r2", "day2", T=yaw_transform(np.radians(-20.0), 1.0, 0.5, 0.0), dt=86_400.0)
    with open_store(f"sqlite:///{tmp_path / 'map.db'}") as store:
        for m in drive + second:
            assert store.insert(m, wire.encode(m), 1.0) == "stored"
        stage = BackendStage(store, config, batch=1)
        try:
            added_while_running = 0
            for _ in drive + second:
                running = stage.core.bundle_running()
                assert stage.step() == 1
                added_while_running += running
            assert added_while_running > 0, "no keyframe went in while an adjustment ran"
            cursor = stage.cursor()
            while stage.core.bundle_running():
                stage.apply_bundle(timeout_s=1.0)
            assert stage.cursor() == cursor == len(drive) + len(second)
            edges = store.graph_records()[1]
        finally:
            stage.stop()
        pairs = [(e.a, e.b) for e in edges if e.kind == "bundle"]
        assert len(pairs) == len(set(pairs)) > 0
        for a, b in zip(drive, second, strict=True):
            keys = [(a.robot_id, a.session_id, a.seq), (b.robot_id, b.session_id, b.seq)]
            Ta, Tb = store.graph_poses(keys).values()
            assert Ta is not None and Tb is not None
            assert np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]) < 0.05


def test_ground_robot_sessions_are_told_from_handheld_ones(drive: list[KeyframeMsg]) -> None:
    """The level prior of the bundle adjustment goes to sessions whose odom frame is z up (the
    simulated robot's); the same keyframes in their first camera's frame (a tracker without
    odometry, e.g. TUM's handheld camera) get none."""
    core = BackendCore(BackendConfig(enabled=False))
    T0_inv = np.linalg.inv(drive[0].T_odom_camera)
    handheld = [replace(m, robot_id="hand", T_odom_camera=T0_inv @ m.T_odom_camera, T_odom_base=None)
                for m in drive[:3]]
    for m in [*drive[:3], *handheld]:
        core.add(m)
    assert core._on_floor((drive[0].robot_id, drive[0].session_id))
    assert not core._on_floor(("hand", drive[0].session_id))


def test_pending_votes_survive_a_restart_of_the_back_end(drive: list[KeyframeMsg], tmp_path: Path) -> None:
    """Anchoring votes and loops waiting for confirmation are committed with the graph, so a
    back-end restored from the store one keyframe before the second session's anchoring one
    anchors it at the same keyframe and ``T_map_odom`` as one that never stopped (without the
    votes it starts counting again, and this drive ends before they span enough to anchor)."""
    T_true = yaw_transform(np.radians(30.0), 2.0, -1.0, 0.0)
    msgs = drive + _as(drive, "r2", "day2", T=np.linalg.inv(T_true), dt=86_400.0)
    session = ("r2", "day2")

    def run(db: Path, restart_at: int | None) -> tuple[int | None, int | None, np.ndarray | None]:
        """(keyframes processed when the first vote was pending, when anchored, T_map_odom)."""
        first_vote = anchored_at = None
        with open_store(f"sqlite:///{db}") as store:
            for m in msgs:
                assert store.insert(m, wire.encode(m), 1.0) == "stored"
            stage = BackendStage(store, batch=1)
            for done in range(1, len(msgs) + 1):
                assert stage.step() == 1
                if first_vote is None and stage.counters().rejected.get("anchor vote"):
                    first_vote = done
                if anchored_at is None and stage.core.anchored(session):
                    anchored_at = done
                if done == restart_at:
                    assert not stage.core.anchored(session) and store.graph_pending() is not None
                    stage = BackendStage(store, batch=1)  # what a restart or a takeover builds
            return first_vote, anchored_at, stage.core.T_map_odom(session)

    first_vote, anchored_at, T_once = run(tmp_path / "once.db", None)
    assert first_vote is not None and anchored_at is not None and anchored_at > first_vote
    # restarted one keyframe before the anchoring one: the votes then span the most driving
    _, anchored_restarted, T_restarted = run(tmp_path / "restarted.db", anchored_at - 1)
    assert anchored_restarted == anchored_at
    assert T_once is not None and T_restarted is not None
    assert np.allclose(T_restarted, T_once, atol=1e-6)


def test_a_pending_state_this_build_cannot_read_starts_the_votes_over(drive: list[KeyframeMsg]) -> None:
    """A stored pending state of another version, or naming keyframes the graph lacks, is
    dropped with a log line (the votes start over: anchoring is delayed, nothing is wrong)."""
    core = BackendCore(BackendConfig())
    for m in drive[:3]:
        core.add(m)
    nodes, edges = core.graph.records()
    rows = [(n.key, m.stamp, m.T_odom_camera, core.encode(m).tobytes())
            for n, m in zip(nodes, drive, strict=False)]
    good = core.pending_state()
    restored = BackendCore.restore(core.cfg, rows, PoseGraph.restore(core.graph.config, nodes, edges),
                                   pending=good)
    assert restored.pending_state() == good
    fmt, version, *rest = msgpack.unpackb(good)
    vote = [["r9", "s9", np.eye(4).tobytes(), [["r9", "s9", 0], ["r1", "day1", 0], np.eye(4).tobytes(), 30,
                                                "anchor", None], 0.0, 0.0]]
    for blob in (msgpack.packb([fmt, version + 1, *rest]), b"\x00garbage",
                 msgpack.packb([fmt, version, vote, [], []])):
        restored = BackendCore.restore(core.cfg, rows, PoseGraph.restore(core.graph.config, nodes, edges),
                                       pending=blob)
        assert restored.pending_state() == msgpack.packb([fmt, version, [], [], []])

"""Corrections from the server's publisher to an edge agent over real zenoh, in this process.

A zenoh router on a thread (free loopback port, shared memory and multicast scouting off), the
server's :class:`~wardmap.server.corrections.CorrectionPublisher` on its own session, an acker
standing in for ingest (``peers.Acker``) and an :class:`~wardmap.edge.agent.EdgeAgent` over four
simulated frames. The test waits on heartbeats, zenoh matching status and events, never on sleeps.
"""

from __future__ import annotations

import contextlib
import math
import queue
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from peers import Acker, matched_publisher, open_client, router_on_thread

from wardmap.edge.agent import AgentConfig, EdgeAgent
from wardmap.server.corrections import CorrectionPublisher
from wardmap.server.zenoh_session import open_session
from wardmap.shared.robotwire import CorrectionMsg, encode_correction
from wardmap.shared.se3 import yaw_transform
from wardmap.shared.wire import HeartbeatMsg, decode_heartbeat
from wardmap.shared.zenoh_config import correction_key, heartbeat_key

pytest.importorskip("zenoh")

pytestmark = pytest.mark.timeout(120)

EVENT_TIMEOUT_S = 20.0
T_MAP_ODOM = yaw_transform(5.0, -2.0, math.radians(30.0), 0.0)


def _wait_heartbeat(heartbeats: queue.Queue[bytes], ok: Any) -> HeartbeatMsg:
    """The first heartbeat from ``heartbeats`` for which ``ok(stats)`` holds (fails after a timeout)."""
    while True:
        try:
            hb = decode_heartbeat(heartbeats.get(timeout=EVENT_TIMEOUT_S))
        except queue.Empty:
            pytest.fail(f"no matching heartbeat within {EVENT_TIMEOUT_S} s")
        if ok(hb.stats):
            return hb


def test_edge_applies_the_servers_correction_and_counts_bad_ones(tmp_path: Path) -> None:
    """Once the agent is ready, the server publishes revision 2 of its session's T_map_odom and the
    test puts garbage and a correction for another robot on the robot's key: a heartbeat reports
    anchored 1 with those two refused; a stale revision 1 is refused next. After four frames the
    summary is anchored, counts the three refusals by reason, and its map pose, like the last
    heartbeat's, is T_map_odom @ the last keyframe's base pose; keyframes still carry no map pose."""
    from wardmap.sim.live import LiveRun

    heartbeats: queue.Queue[bytes] = queue.Queue()
    config = AgentConfig(max_frames=4, flush_timeout_s=20.0, heartbeat_period_s=0.2, correction_query_s=0.5,
                         privacy="off")
    with contextlib.ExitStack() as stack:
        endpoint = stack.enter_context(router_on_thread())
        acker = stack.enter_context(Acker(endpoint))
        server = stack.enter_context(open_session([endpoint]))
        corrections = stack.enter_context(CorrectionPublisher(server))
        test = stack.enter_context(open_client(endpoint))
        stack.enter_context(test.declare_subscriber(heartbeat_key("r1"), lambda s: heartbeats.put(
            s.payload.to_bytes())))

        def on_ready(session_id: str, _pending: int) -> None:
            raw = matched_publisher(test, correction_key("r1"), EVENT_TIMEOUT_S)  # the agent subscribes
            corrections.publish("r1", session_id, T_MAP_ODOM, revision=2, anchored_to="r0/s0")
            raw.put(b"\x93not a correction")
            raw.put(encode_correction(CorrectionMsg("r2", session_id, 9, 1.0, np.eye(4))))
            _wait_heartbeat(heartbeats, lambda s: s["anchored"] == 1 and s["bad_corrections"] == 2)
            raw.put(encode_correction(CorrectionMsg("r1", session_id, 1, 1.0, np.eye(4))))
            _wait_heartbeat(heartbeats, lambda s: s["bad_corrections"] == 3)
            raw.undeclare()

        summary = EdgeAgent("r1", LiveRun("aisle_slow_1", 0), [endpoint], tmp_path / "outbox.sqlite",
                            config=config).run(on_ready)
        n = summary["keyframes"]
        last = _wait_heartbeat(heartbeats, lambda s: s["keyframes"] == n and "map_x" in s)
    sid = summary["session_id"]
    assert n >= 1 and summary["pending"] == 0
    assert summary["anchored"] is True and summary["correction_revision"] == 2
    assert summary["anchored_to"] == "r0/s0" and summary["corrections"] == 1
    assert summary["bad_corrections"] == {"undecodable": 1, "other_robot": 1, "stale": 1}
    T_odom_base, _, _ = acker.poses[(sid, n - 1)]
    assert T_odom_base is not None  # the simulator has wheel odometry
    assert all(acker.poses[(sid, i)][2] is None for i in range(n))  # no correction goes back
    T_map_base = T_MAP_ODOM @ T_odom_base
    want = {"x": T_map_base[0, 3], "y": T_map_base[1, 3], "z": T_map_base[2, 3],
            "yaw_deg": math.degrees(math.atan2(T_map_base[1, 0], T_map_base[0, 0]))}
    assert summary["map_pose"] == pytest.approx(want, abs=6e-3)  # rounded to 1 mm and 0.01 deg
    got = {k: last.stats[f"map_{k}"] for k in want}
    assert got == pytest.approx(want, abs=6e-3)  # rounded to 1 mm and 0.01 deg
    assert (last.stats["anchored"], last.stats["corrections"], last.stats["bad_corrections"]) == (1, 1, 3)


def test_an_edge_that_missed_the_put_learns_its_correction_by_query(tmp_path: Path) -> None:
    """The agent's subscription drops every put (a robot that was offline when the server
    published): its periodic query of the server's queryable still brings revision 0, so a
    heartbeat reports anchored 1 and the summary holds it."""
    from wardmap.sim.live import LiveRun

    heartbeats: queue.Queue[bytes] = queue.Queue()
    config = AgentConfig(max_frames=2, flush_timeout_s=20.0, heartbeat_period_s=0.2, correction_query_s=0.3,
                         privacy="off")
    with contextlib.ExitStack() as stack:
        endpoint = stack.enter_context(router_on_thread())
        stack.enter_context(Acker(endpoint))
        server = stack.enter_context(open_session([endpoint]))
        corrections = stack.enter_context(CorrectionPublisher(server))
        test = stack.enter_context(open_client(endpoint))
        stack.enter_context(test.declare_subscriber(heartbeat_key("r1"), lambda s: heartbeats.put(
            s.payload.to_bytes())))
        agent = EdgeAgent("r1", LiveRun("aisle_slow_1", 0), [endpoint], tmp_path / "outbox.sqlite",
                          config=config)
        agent._on_correction = lambda sample: None  # every put is missed

        def on_ready(session_id: str, _pending: int) -> None:
            corrections.publish("r1", "an-older-session", np.eye(4), revision=5)  # never answered to r1 now
            corrections.publish("r1", session_id, T_MAP_ODOM, revision=0)
            _wait_heartbeat(heartbeats, lambda s: s["anchored"] == 1)

        summary = agent.run(on_ready)
    assert summary["anchored"] is True and summary["correction_revision"] == 0
    assert summary["bad_corrections"] == {}
    assert corrections.counters().queries >= 1

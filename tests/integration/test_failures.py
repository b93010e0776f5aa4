"""Failure injection across the real processes: a server SIGKILLed mid-stream, a router restarted
under running agents, and 1000 malformed or mutated payloads on the keyframe key.

Every process is a subprocess of ``wardmap`` (router, server, edge) on free loopback ports; the
test process is a zenoh client with shared memory and multicast scouting off. The tests
synchronise on ready lines, process exits, zenoh matching events, acks and HTTP polls with a
deadline, never on sleeps. Agent restart (SIGTERM, resume from the outbox) is covered by
``test_edge_cmd.py``.
"""

from __future__ import annotations

import contextlib
import queue
import signal
import sqlite3
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from factories import FUZZ_LEAVES, keyframe, mutate, raster_bomb, walk
from peers import ALL_ACKS, matched_publisher, open_client
from procs import (
    Proc,
    assert_stops_cleanly,
    edge_summary,
    kill_proc,
    prometheus_samples,
    spawn_logged,
    stop_proc,
    wardmap_cmd,
)
from procs import free_port as _free_port
from procs import read_line as _read_line

pytest.importorskip("zenoh")


from wardmap.edge.outbox import Outbox
from wardmap.shared import wire
from wardmap.shared.errors import WireError
from wardmap.shared.wire import decode_heartbeat
from wardmap.shared.zenoh_config import heartbeat_key, keyframe_key

pytestmark = [pytest.mark.integration, pytest.mark.timeout(90)]

READY_TIMEOUT_S = 20.0
EVENT_TIMEOUT_S = 20.0
RUN_TIMEOUT_S = 60.0
FRAMES = 60
OUTBOX_FILE = "outbox.sqlite"
# The agent gives up on an unacked item only after this (not reached: a safety net for slow CI).
EDGE_CONFIG = "[agent]\nflush_timeout_s = 40.0\nresend_after_s = 1.0\n"


# --------------------------------------------------------------------------- processes


def _start(cmd: list[str], expect: str, log_dir: Path, name: str) -> Proc:
    """Start ``cmd``, wait for its ready line ``expect``; fail with its stderr otherwise."""
    proc = spawn_logged(cmd, log_dir, name)
    assert proc.popen.stdout is not None
    line = _read_line(proc.popen.stdout, READY_TIMEOUT_S)
    if line is None or line.strip() != expect:
        kill_proc(proc)
        pytest.fail(f"{name} not ready ({line!r}); stderr: {proc.stderr()[-2000:]!r}")
    return proc


def _start_router(endpoint: str, log_dir: Path) -> Proc:
    cmd = wardmap_cmd("router", "--listen", endpoint)
    return _start(cmd, f"router listening on {endpoint}", log_dir, "router")


def _start_server(endpoint: str, db: Path, port: int, log_dir: Path) -> Proc:
    cmd = wardmap_cmd("server", "--connect", endpoint, "--db", f"sqlite:///{db}",
                      "--http", f"127.0.0.1:{port}", "--insecure-loopback")
    return _start(cmd, f"server ready: http://127.0.0.1:{port}", log_dir, "server")


@dataclass
class Stack:
    """A router and a server (sqlite in tmp) on free ports; the test may replace either."""

    endpoint: str
    port: int
    db: Path
    log_dir: Path
    router: Proc
    server: Proc

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"


@pytest.fixture
def stack(tmp_path: Path) -> Iterator[Stack]:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    port = _free_port()
    db = tmp_path / "map.db"
    router = _start_router(endpoint, tmp_path)
    try:
        server = _start_server(endpoint, db, port, tmp_path)
    except BaseException:
        stop_proc(router)
        raise
    s = Stack(endpoint, port, db, tmp_path, router, server)
    try:
        yield s
    finally:
        stop_proc(s.server)  # whichever instance is current
        stop_proc(s.router)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 60-frame simulated sequence (aisle_slow_1, seed 0), generated once."""
    from wardmap.sim.runner import generate

    path = tmp_path_factory.mktemp("failures") / "aisle"
    generate("aisle_slow_1", 0, path, frames=FRAMES)
    return path


# --------------------------------------------------------------------------- edge helpers


def _start_edge(robot: str, dataset: Path, stack: Stack, tmp_path: Path) -> tuple[Proc, Path]:
    """``wardmap edge`` at 10 Hz after its ready line; returns it and its outbox file."""
    config = tmp_path / "edge.toml"
    config.write_text(EDGE_CONFIG)
    outbox_dir = tmp_path / "outbox"
    cmd = wardmap_cmd("edge", "--robot", robot, "--source", str(dataset), "--connect", stack.endpoint,
                      "--outbox", str(outbox_dir), "--rate", "10", "--config", str(config),
                      "--privacy", "off")
    proc = spawn_logged(cmd, tmp_path, "edge")
    assert proc.popen.stdout is not None
    ready = _read_line(proc.popen.stdout, READY_TIMEOUT_S)
    if ready is None or " ready: session " not in ready:
        kill_proc(proc)
        pytest.fail(f"edge not ready ({ready!r}); stderr: {proc.stderr()[-2000:]!r}")
    return proc, outbox_dir / OUTBOX_FILE


def _wait_stored(url: str, robot: str, at_least: int) -> int:
    """Poll GET /v1/robots until ``robot`` has ``at_least`` keyframes (deadline EVENT_TIMEOUT_S)."""
    deadline = time.monotonic() + EVENT_TIMEOUT_S
    with httpx.Client(base_url=url, timeout=5) as http:
        while time.monotonic() < deadline:
            robots = {r["robot_id"]: r["keyframes"] for r in http.get("/v1/robots").json()["robots"]}
            if robots.get(robot, 0) >= at_least:
                return int(robots[robot])
            time.sleep(0.05)  # poll period, not synchronisation: the deadline bounds the wait
    pytest.fail(f"{robot} never reached {at_least} stored keyframes")


def _db_counts(db: Path, robot: str) -> tuple[int, int, set[str]]:
    """(rows, distinct (session, seq), sessions) of ``robot`` in the store, read directly."""
    with contextlib.closing(sqlite3.connect(db)) as con:
        rows = con.execute("SELECT COUNT(*) FROM keyframes WHERE robot_id = ?", (robot,)).fetchone()[0]
        distinct = con.execute(
            "SELECT COUNT(*) FROM (SELECT DISTINCT session_id, seq FROM keyframes WHERE robot_id = ?)",
            (robot,),
        ).fetchone()[0]
        sessions = {
            r[0]
            for r in con.execute("SELECT DISTINCT session_id FROM keyframes WHERE robot_id = ?", (robot,))
        }
    return int(rows), int(distinct), sessions


def _assert_delivered_exactly_once(stack: Stack, robot: str, summary: dict[str, Any], outbox: Path) -> None:
    """Every keyframe the agent produced is stored once; its outbox ends empty."""
    n = summary["keyframes"]
    assert summary["frames"] == FRAMES
    assert n >= 4, summary
    assert summary["acked"] == n, summary
    assert summary["pending"] == 0 and summary["flushed"] is True, summary
    assert summary["rejected"] == {}, summary
    with httpx.Client(base_url=stack.url, timeout=5) as http:
        robots = {r["robot_id"]: r["keyframes"] for r in http.get("/v1/robots").json()["robots"]}
        assert http.get("/healthz").json() == {"status": "ok"}
    assert robots == {robot: n}
    rows, distinct, sessions = _db_counts(stack.db, robot)
    assert rows == distinct == n
    assert sessions == {summary["session_id"]}
    with Outbox.open(outbox) as box:
        assert len(box) == 0
        assert box.pending(10_000) == []


# --------------------------------------------------------------------------- 1. server SIGKILL


def test_server_sigkill_mid_stream_loses_and_duplicates_nothing(
    dataset: Path, stack: Stack, tmp_path: Path
) -> None:
    """Router + server + one agent streaming 60 frames at 10 Hz. Once the server stored 3
    keyframes it is SIGKILLed (no shutdown, no flush, possibly mid-insert or before an ack);
    a new server opens the same sqlite file on the same HTTP port. The agent re-sends what
    was not acked; at the end the store holds exactly the agent's keyframes, each once, and
    the agent's outbox is empty."""
    robot = "r-kill"
    heartbeats: queue.Queue[bytes] = queue.Queue(maxsize=64)

    def on_heartbeat(sample: Any) -> None:
        with contextlib.suppress(queue.Full):  # drop-newest: only a recent one is needed
            heartbeats.put_nowait(sample.payload.to_bytes())

    with (
        open_client(stack.endpoint) as watcher,
        watcher.declare_subscriber(heartbeat_key(robot), on_heartbeat),
    ):
        edge, outbox = _start_edge(robot, dataset, stack, tmp_path)
        try:
            _wait_stored(stack.url, robot, 3)
            stack.server.popen.send_signal(signal.SIGKILL)
            assert stack.server.popen.wait(timeout=10) == -signal.SIGKILL
            kill_proc(stack.server)
            stored_at_kill, _, _ = _db_counts(stack.db, robot)  # nobody writes the file now
            # Restart only once the agent produced a keyframe the dead server never stored (so
            # never acked): it was published to nobody and must be re-sent to the new server.
            produced = 0
            while produced <= stored_at_kill:
                produced = decode_heartbeat(heartbeats.get(timeout=EVENT_TIMEOUT_S)).stats["keyframes"]
            stack.server = _start_server(stack.endpoint, stack.db, stack.port, stack.log_dir)
            summary = edge_summary(edge, RUN_TIMEOUT_S)
        finally:
            kill_proc(edge)
    assert stored_at_kill >= 3
    assert summary["frames"] == FRAMES  # the kill happened mid-stream, not after the last frame
    assert summary["resent"] >= 1, summary
    _assert_delivered_exactly_once(stack, robot, summary, outbox)
    assert_stops_cleanly(stack.server)
    assert "Traceback" not in stack.server.stderr()


def _backend_settled(url: str, keyframes: int) -> dict[str, float]:
    """Poll /metrics until the back-end's graph holds ``keyframes`` nodes and the mapping stage has
    no backlog (deadline EVENT_TIMEOUT_S); the samples."""
    deadline = time.monotonic() + EVENT_TIMEOUT_S
    with httpx.Client(base_url=url, timeout=5) as http:
        while time.monotonic() < deadline:
            samples = prometheus_samples(http.get("/metrics").text)
            if (samples.get("wardmap_backend_graph_nodes") == keyframes
                    and samples.get("wardmap_mapping_backlog") == 0):
                return samples
            time.sleep(0.1)  # poll period; the deadline bounds the wait
    pytest.fail(f"the back-end never held {keyframes} keyframes")


def _map_trajectory(url: str, robot: str) -> np.ndarray:
    with httpx.Client(base_url=url, timeout=5) as http:
        poses = http.get(f"/v1/robots/{robot}/trajectory").json()["poses"]
    return np.array([[p["stamp"], *p["t"], *p["q_xyzw"]] for p in poses])


def test_the_pose_graph_survives_a_sigkill_and_a_new_session_relocalises(
    dataset: Path, stack: Stack, tmp_path: Path
) -> None:
    """A robot's session sets the map; the server is SIGKILLed after the back-end put every
    keyframe in the graph. The restarted server restores the graph from the store (no keyframe
    is added again, the map trajectory is the same), and the robot's next session, driving the
    same aisle without a map pose, is anchored through the first by place recognition against
    the restored index."""
    robot = "r-graph"
    for day in ("day1", "day2"):
        (tmp_path / day).mkdir()
    edge, _ = _start_edge(robot, dataset, stack, tmp_path / "day1")
    first = edge_summary(edge, RUN_TIMEOUT_S)
    n = first["keyframes"]
    before = _backend_settled(stack.url, n)
    assert before["wardmap_backend_keyframes_total"] == n
    trajectory = _map_trajectory(stack.url, robot)
    assert len(trajectory) == n  # the first session sets the map: all on it
    stack.server.popen.send_signal(signal.SIGKILL)
    assert stack.server.popen.wait(timeout=10) == -signal.SIGKILL
    kill_proc(stack.server)
    stack.server = _start_server(stack.endpoint, stack.db, stack.port, stack.log_dir)
    after = _backend_settled(stack.url, n)
    assert after["wardmap_backend_keyframes_total"] == 0  # restored, not rebuilt
    np.testing.assert_allclose(_map_trajectory(stack.url, robot), trajectory, atol=1e-6)

    edge, _ = _start_edge(robot, dataset, stack, tmp_path / "day2")
    second = edge_summary(edge, RUN_TIMEOUT_S)
    _backend_settled(stack.url, n + second["keyframes"])
    with httpx.Client(base_url=stack.url, timeout=5) as http:
        (row,) = http.get("/v1/robots").json()["robots"]
    assert row["session_id"] == second["session_id"] and row["anchored"] is True, row
    assert row["anchored_to"] == f"{robot}/{first['session_id']}", row
    # Both days drove the same aisle from the same start: the second odom frame is the first's.
    t, q = np.array(row["T_map_odom"]["t"]), np.array(row["T_map_odom"]["q_xyzw"])
    assert np.linalg.norm(t) < 0.05 and abs(abs(q[3]) - 1.0) < 1e-3, row
    assert second["anchored"] is True, second  # the edge applied the server's correction


# --------------------------------------------------------------------------- 2. router restart


def test_router_restart_agents_reconnect_and_deliver_exactly_once(
    dataset: Path, stack: Stack, tmp_path: Path
) -> None:
    """Router + server + one agent streaming 60 frames at 10 Hz. Once the server stored 3
    keyframes the router is SIGTERMed and a new one started on the same port. The server's
    and the agent's zenoh client sessions reconnect by themselves (zenoh's default client
    behaviour, no extra config) and re-declare their subscribers; keyframes published while
    no router ran are re-sent from the outbox. Every keyframe is stored exactly once."""
    robot = "r-router"
    edge, outbox = _start_edge(robot, dataset, stack, tmp_path)
    try:
        stored_before = _wait_stored(stack.url, robot, 3)
        assert_stops_cleanly(stack.router)
        stack.router = _start_router(stack.endpoint, stack.log_dir)
        summary = edge_summary(edge, RUN_TIMEOUT_S)
    finally:
        kill_proc(edge)
    assert stored_before < summary["keyframes"]  # some keyframes had to cross the new router
    _assert_delivered_exactly_once(stack, robot, summary, outbox)
    assert stack.server.popen.poll() is None, "the server must survive a router restart"
    assert_stops_cleanly(stack.server)
    assert "Traceback" not in stack.server.stderr()


# --------------------------------------------------------------------------- 4. malformed payloads

FUZZ_ROBOT = "fz"
N_FUZZ = 1000
# The fuzz values plus another robot's id among the strings: edits that make a robot_id mismatch.
_LEAVES = (*FUZZ_LEAVES[:16], "r2", *FUZZ_LEAVES[16:])


def _base_keyframes(n: int) -> list[bytes]:
    """``n`` small valid keyframes of robot ``fz`` (seq 0..n-1)."""
    base = keyframe(np.random.default_rng(3), robot_id=FUZZ_ROBOT, n_keypoints=8)
    return [wire.encode(m) for m in walk(base, n)]


def _expected_outcome(payload: bytes) -> str:
    """What the server must do with ``payload`` on robot fz's key: ``rejected`` or ``accepted``."""
    try:
        msg = wire.decode_keyframe(payload)
    except WireError:
        return "rejected"
    return "accepted" if msg.robot_id == FUZZ_ROBOT else "rejected"  # else: robot_id mismatch


class AckCounter:
    """Counts acks by status (the zenoh callback decodes and counts under a condition)."""

    def __init__(self) -> None:
        self.statuses: list[str] = []
        self._cond = threading.Condition()

    def on_ack(self, sample: Any) -> None:
        status = wire.decode_ack(sample.payload.to_bytes()).status
        with self._cond:
            self.statuses.append(status)
            self._cond.notify_all()

    def wait_for(self, n: int, timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: len(self.statuses) >= n, timeout=timeout_s)


def test_malformed_and_mutated_payloads_are_rejected_and_counted(stack: Stack) -> None:
    """1000 seeded payloads on robot fz's keyframe key: bit flips, truncations, insertions,
    random bytes and structural edits (replace/delete/add a field) of valid keyframes. Each
    one is decoded here too: the invalid ones (and valid ones whose robot_id is not fz) must
    each be counted once in GET /metrics' rejections, the still-valid ones stored or
    duplicate. Every sample is acked; the server stays healthy, exits 0 on SIGTERM, and the
    sqlite file passes ``PRAGMA integrity_check``."""
    rng = np.random.default_rng(20240501)
    bases = _base_keyframes(4)
    payloads = [mutate(bases[i % len(bases)], rng, leaves=_LEAVES, random_payloads=True)
                for i in range(N_FUZZ)]
    expected = [_expected_outcome(p) for p in payloads]
    n_rejected = expected.count("rejected")
    assert 500 < n_rejected < N_FUZZ  # the mix exercises both outcomes

    acks = AckCounter()
    with (
        open_client(stack.endpoint) as session,
        session.declare_subscriber(ALL_ACKS, acks.on_ack),
        httpx.Client(base_url=stack.url, timeout=10) as http,
    ):
        pub = matched_publisher(session, keyframe_key(FUZZ_ROBOT), EVENT_TIMEOUT_S)
        for p in payloads:
            pub.put(p)
        assert acks.wait_for(N_FUZZ, EVENT_TIMEOUT_S), f"only {len(acks.statuses)} of {N_FUZZ} acks"

        assert stack.server.popen.poll() is None
        assert http.get("/healthz").json() == {"status": "ok"}
        metrics = prometheus_samples(http.get("/metrics").text)
        reasons = {k: v for k, v in metrics.items() if k.startswith("wardmap_rejections_total")}
        assert sum(reasons.values()) == n_rejected, reasons
        assert 'wardmap_rejections_total{reason="internal"}' not in reasons, reasons
        assert metrics["wardmap_keyframes_received_total"] == N_FUZZ
        assert metrics["wardmap_keyframes_stored_total"] + metrics["wardmap_keyframes_duplicates_total"] == (
            N_FUZZ - n_rejected
        )
        assert acks.statuses.count("rejected") == n_rejected
        robots = {r["robot_id"]: r["keyframes"] for r in http.get("/v1/robots").json()["robots"]}
        assert set(robots) <= {FUZZ_ROBOT}
        assert robots.get(FUZZ_ROBOT, 0) == metrics["wardmap_keyframes_stored_total"]

    assert_stops_cleanly(stack.server)
    assert "Traceback" not in stack.server.stderr()
    with contextlib.closing(sqlite3.connect(stack.db)) as con:
        assert con.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
        rows, distinct, _ = _db_counts(stack.db, FUZZ_ROBOT)
    assert rows == distinct


def _peak_rss_mb(pid: int) -> float:
    """The process's peak resident set (``VmHWM``) in MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM in /proc")


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="needs /proc for the peak RSS")
def test_raster_bombs_and_a_50mb_flood_keep_the_server_small(stack: Stack) -> None:
    """Ten 300 KB keyframes declaring 8192x8192 images and forty 50 MB payloads, interleaved
    with 20 valid keyframes, on one robot's key: every valid keyframe is acked ``stored`` and
    listed, every bomb acked ``rejected`` and counted as ``wire: rgb_jpeg``, the 50 MB payloads
    are dropped by zenoh before reassembly (the wire's limit is 4 MiB), and the server's peak
    RSS stays under 600 MiB (bombs once took 0.9 GB each to decode, the flood 3.2 GB)."""
    valid = _base_keyframes(20)
    bomb = raster_bomb(np.random.default_rng(5))
    flood = bytes(50 * 2**20)
    acks = AckCounter()
    with (
        open_client(stack.endpoint) as session,
        session.declare_subscriber(ALL_ACKS, acks.on_ack),
        httpx.Client(base_url=stack.url, timeout=10) as http,
    ):
        pub = matched_publisher(session, keyframe_key(FUZZ_ROBOT), EVENT_TIMEOUT_S)
        for i in range(40):
            pub.put(flood)
            if i % 4 == 0:
                pub.put(bomb)
            if i % 2 == 0:
                pub.put(valid[i // 2])
        assert acks.wait_for(30, EVENT_TIMEOUT_S * 3), f"only {len(acks.statuses)} of 30 acks"
        assert sorted(acks.statuses) == ["rejected"] * 10 + ["stored"] * 20
        metrics = prometheus_samples(http.get("/metrics").text)
        assert metrics['wardmap_rejections_total{reason="wire: rgb_jpeg"}'] == 10
        assert metrics["wardmap_keyframes_received_total"] == 30  # the 50 MB never reached ingest
        robots = {r["robot_id"]: r["keyframes"] for r in http.get("/v1/robots").json()["robots"]}
        assert robots == {FUZZ_ROBOT: 20}
        peak = _peak_rss_mb(stack.server.popen.pid)
        assert peak <= 600, f"server peak RSS {peak:.0f} MiB"
    assert_stops_cleanly(stack.server)

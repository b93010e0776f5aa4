"""A stuck subscriber on ``wardmap/**`` during a keyframe burst: the edge's outbox still delivers
every keyframe, each stored exactly once, and none is acked before its commit (issue 39, "a
stuck subscriber"; docs/outbox.md, "A stuck subscriber").

Router, server (without the mapping stage), edge and the stuck peer (``tests/stuck_peer.py``: a
zenoh client whose callback never returns while the test runs) are real processes on free
loopback ports. The burst is an outbox the edge finds at its start: BURST keyframes of about
370 KB each from an earlier session (the size the issue measured), which the agent sends before
its own few. The test process watches the acks and, while the edge runs, checks that every key
acked ``stored`` or ``duplicate`` is already in the database. Waits are bounded by deadlines.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from factories import keyframe
from peers import ALL_ACKS, open_client
from procs import (
    Proc,
    assert_stops_cleanly,
    child_env,
    edge_summary,
    free_port,
    kill_proc,
    read_line,
    spawn_logged,
    stop_proc,
    wardmap_cmd,
)

pytest.importorskip("zenoh")

from wardmap.edge.outbox import Outbox, new_session_id
from wardmap.shared import wire

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

log = logging.getLogger(__name__)

ROBOT = "r-stuck"
BURST = 300
KEYPOINTS = 7500  # a ~370 KB keyframe
SOURCE_FRAMES = 3
READY_TIMEOUT_S = 20.0
RUN_TIMEOUT_S = 75.0
SERVER_CONFIG = "[pipeline]\nenabled = false\n"
EDGE_CONFIG = "[agent]\nflush_timeout_s = 60.0\nresend_after_s = 1.0\n"
STUCK_PEER = Path(__file__).resolve().parents[1] / "stuck_peer.py"

Key = tuple[str, str, int]


def _start(cmd: list[str], ready: str, log_dir: Path, name: str) -> Proc:
    proc = spawn_logged(cmd, log_dir, name)
    assert proc.popen.stdout is not None
    line = read_line(proc.popen.stdout, READY_TIMEOUT_S)
    if line is None or ready not in line:
        kill_proc(proc)
        pytest.fail(f"{name} not ready ({line!r}); stderr: {proc.stderr()[-2000:]!r}")
    return proc


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3-frame simulated sequence: the edge's own keyframes after the burst."""
    from wardmap.sim.runner import generate

    path = tmp_path_factory.mktemp("stuck") / "aisle"
    generate("aisle_slow_1", 0, path, frames=SOURCE_FRAMES)
    return path


def _fill_outbox(path: Path) -> set[Key]:
    """BURST ~370 KB keyframes of ROBOT from an earlier session, unsent; their keys."""
    rng = np.random.default_rng(0)
    base = keyframe(rng, robot_id=ROBOT, session_id=new_session_id(), n_keypoints=KEYPOINTS)
    with Outbox.open(path, max_items=BURST + 100) as box:
        ids = box.start_session(ROBOT, session_id=base.session_id)
        for i in range(BURST):
            ids.put(base.stamp + i, wire.encode(_numbered(base, i)))
    return {(ROBOT, base.session_id, i) for i in range(BURST)}


def _numbered(base: wire.KeyframeMsg, seq: int) -> wire.KeyframeMsg:
    return replace(base, seq=seq, stamp=base.stamp + seq)


class Acks:
    """Every ack to any robot, recorded by a zenoh callback."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.acks: list[tuple[Key, str]] = []
        self.times: list[float] = []  # time.monotonic() of each ack

    def on_ack(self, sample: Any) -> None:
        ack = wire.decode_ack(sample.payload.to_bytes())
        with self._lock:
            self.acks.append(((ack.robot_id, ack.session_id, ack.seq), ack.status))
            self.times.append(time.monotonic())

    def committed(self) -> set[Key]:
        """Keys acked ``stored`` or ``duplicate``: the ones the server says are in the database."""
        with self._lock:
            return {key for key, status in self.acks if status in ("stored", "duplicate")}

    def rejected(self) -> set[Key]:
        """Keys acked ``rejected``."""
        with self._lock:
            return {key for key, status in self.acks if status == "rejected"}

    def statuses(self) -> Counter[str]:
        with self._lock:
            return Counter(status for _, status in self.acks)

    def longest_gap_s(self) -> float:
        """The longest time between two consecutive acks, seconds (0 with fewer than two)."""
        with self._lock:
            return float(np.diff(self.times).max()) if len(self.times) > 1 else 0.0


def _db_rows(db: Path) -> list[Key]:
    """Every stored keyframe key of ROBOT, one per row (a duplicate would appear twice)."""
    with contextlib.closing(sqlite3.connect(db)) as con:
        rows = con.execute("SELECT robot_id, session_id, seq FROM keyframes WHERE robot_id = ?", (ROBOT,))
        return [(str(r), str(s), int(q)) for r, s, q in rows]


@contextlib.contextmanager
def _stuck_peer(endpoint: str, log_dir: Path) -> Iterator[list[int]]:
    """The stuck subscriber process, ready; on exit it is released (stdin closed) and must end
    on its own; yields a list that then holds how many samples reached its callback."""
    err = log_dir / "stuck_peer.stderr"
    with err.open("w") as err_file:
        proc = subprocess.Popen([sys.executable, str(STUCK_PEER), endpoint], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=err_file, text=True, env=child_env())
    assert proc.stdout is not None and proc.stdin is not None
    seen: list[int] = []
    try:
        line = read_line(proc.stdout, READY_TIMEOUT_S)
        if line != "stuck peer ready\n":
            pytest.fail(f"stuck peer not ready ({line!r}); stderr: {err.read_text()[-2000:]!r}")
        yield seen
        out, _ = proc.communicate(timeout=30)  # closes stdin: the callback returns
        assert proc.returncode == 0, err.read_text()[-2000:]
        seen.append(int(out.split()[-1]))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)


def test_a_stuck_subscriber_on_every_key_loses_no_keyframe(
    dataset: Path, tmp_path: Path, record_property: Any
) -> None:
    """With the stuck peer subscribed to ``wardmap/**`` the edge sends a BURST-keyframe burst of
    ~370 KB keyframes: every keyframe it produced (the burst and its own) ends up stored exactly
    once, its outbox ends empty, none of them is rejected, and no key is acked before it is in the
    database. The longest gap between acks is reported, not bounded: the router may hold every
    robot's traffic while it waits on the stuck peer (docs/outbox.md, "A stuck subscriber").
    The peer did receive a keyframe (so it was in the path) and did not return until the end."""
    outbox_dir = tmp_path / "outbox"
    burst = _fill_outbox(outbox_dir / "outbox.sqlite")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    port = free_port()
    db = tmp_path / "map.db"
    (tmp_path / "server.toml").write_text(SERVER_CONFIG)
    (tmp_path / "edge.toml").write_text(EDGE_CONFIG)
    router = _start(wardmap_cmd("router", "--listen", endpoint), "router listening", tmp_path, "router")
    server: Proc | None = None
    try:
        server = _start(wardmap_cmd("server", "--connect", endpoint, "--db", f"sqlite:///{db}", "--http",
                                    f"127.0.0.1:{port}", "--config", str(tmp_path / "server.toml"),
                                    "--insecure-loopback"), "server ready", tmp_path, "server")
        acks = Acks()
        with (
            _stuck_peer(endpoint, tmp_path) as stuck_seen,
            open_client(endpoint) as watcher,
            watcher.declare_subscriber(ALL_ACKS, acks.on_ack),
        ):
            t0 = time.monotonic()
            edge_cmd = wardmap_cmd("edge", "--robot", ROBOT, "--source", str(dataset), "--connect", endpoint,
                                   "--outbox", str(outbox_dir), "--rate", "10",
                                   "--config", str(tmp_path / "edge.toml"), "--privacy", "off")
            edge = _start(edge_cmd, " ready: session ", tmp_path, "edge")
            try:
                checks = 0
                while edge.popen.poll() is None and time.monotonic() - t0 < RUN_TIMEOUT_S:
                    committed = acks.committed()  # before reading the database: acked => stored
                    assert committed <= set(_db_rows(db)), "a keyframe was acked before its commit"
                    checks += 1
                    time.sleep(0.5)  # sampling period; the loop is bounded by RUN_TIMEOUT_S
                summary = edge_summary(edge, 5.0)
            finally:
                kill_proc(edge)
            seconds = time.monotonic() - t0
        assert_stops_cleanly(server)
    finally:
        if server is not None:
            stop_proc(server)
        stop_proc(router)
    rows = _db_rows(db)
    own = {(ROBOT, summary["session_id"], seq) for seq in range(summary["keyframes"])}
    produced = burst | own
    figures = {"produced": len(produced), "stored": len(set(rows) & produced),
               "duplicated": len(rows) - len(set(rows)), "resent": summary["resent"],
               "acks": dict(acks.statuses()), "stuck_peer_samples": stuck_seen[0],
               "seconds": round(seconds, 1), "longest_ack_gap_s": round(acks.longest_gap_s(), 2),
               "ack_checks": checks}
    log.warning("stuck subscriber: %s", figures)
    for name, value in figures.items():
        record_property(name, value)
    assert stuck_seen[0] >= 1  # the peer was in the path and stuck on its first sample
    assert set(rows) == produced, figures
    assert len(rows) == len(produced), figures
    assert summary["pending"] == 0 and summary["flushed"] is True, summary
    assert summary["rejected"] == {}, summary
    # No keyframe it produced was refused. A payload that reached the server garbled (seen once
    # before, under `block`) is acked `rejected` under no produced key and is only reported.
    assert not acks.rejected() & produced, figures
    assert acks.committed() == produced
    with Outbox.open(outbox_dir / "outbox.sqlite") as box:
        assert len(box) == 0
    assert "Traceback" not in server.stderr()

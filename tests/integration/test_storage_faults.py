"""The server's storage fails under a running robot: a full disk (the store's ``max_pages``
cap), the database's write lock held by another process past the busy timeout, a corrupted index
page. An ack means stored, and only then: in each case every keyframe the edge produced ends up
stored exactly once, no keyframe is acked ``stored`` before its commit, none is acked
``rejected``, and the edge keeps what the server could not store (acked ``retry``) until it can.

Router, server and edge are real ``wardmap`` subprocesses on free loopback ports; the test
process is a zenoh client that watches acks and heartbeats. The last test runs the ingest in the
test process (router and publisher real) to check :meth:`Ingest.ready` and the rejection counts
through a lock and a damaged index. The server runs without the mapping stage
(``[pipeline] enabled = false``): these tests are about what ingest stores and acks. Everything
waits on ready lines, acks, heartbeats and HTTP polls with deadlines, never on sleeps.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sqlite3
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from faults import garble_index_page, repair_by_dump, small_keyframes
from procs import Proc, assert_stops_cleanly, edge_summary, kill_proc, spawn_logged, stop_proc
from procs import free_port as _free_port
from procs import read_line as _read_line

zenoh = pytest.importorskip("zenoh")

from wardmap.server.ingest import Ingest  # noqa: E402  (after the importorskip guard)
from wardmap.server.store import open_store  # noqa: E402
from wardmap.server.zenoh_session import open_session  # noqa: E402
from wardmap.shared import wire  # noqa: E402
from wardmap.shared.zenoh_config import client_config, heartbeat_key, keyframe_key  # noqa: E402

pytestmark = [pytest.mark.integration, pytest.mark.timeout(300)]

log = logging.getLogger(__name__)

READY_TIMEOUT_S = 20.0
EVENT_TIMEOUT_S = 60.0
RUN_TIMEOUT_S = 120.0
FRAMES = 60
ROBOT = "r-fault"
OUTBOX_FILE = "outbox.sqlite"
ALL_ACKS = "wardmap/v1/robot/*/ack"
SERVER_CONFIG = "[pipeline]\nenabled = false\n"
# flush_timeout_s only bounds the wait at the end; every test frees the store well before it.
EDGE_CONFIG = "[agent]\nflush_timeout_s = 60.0\nresend_after_s = 1.0\n"
CAP_PAGES = 40
"""Pages the full-disk test lets the store grow beyond its empty schema (~160 KB: 1-2 keyframes)."""
BUSY_TIMEOUT_S = 1.0

Key = tuple[str, str, int]


# --------------------------------------------------------------------------- processes




def _start(cmd: list[str], ready: Callable[[str], bool], log_dir: Path, name: str) -> Proc:
    proc = spawn_logged(cmd, log_dir, name)
    assert proc.popen.stdout is not None
    line = _read_line(proc.popen.stdout, READY_TIMEOUT_S)
    if line is None or not ready(line.strip()):
        kill_proc(proc)
        pytest.fail(f"{name} not ready ({line!r}); stderr: {proc.stderr()[-2000:]!r}")
    return proc


def _wardmap(*args: str) -> list[str]:
    return [sys.executable, "-m", "wardmap.cli", *args]


@pytest.fixture
def router(tmp_path: Path) -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    expect = f"router listening on {endpoint}"
    proc = _start(_wardmap("router", "--listen", endpoint), lambda ln: ln == expect, tmp_path, "router")
    try:
        yield endpoint
    finally:
        stop_proc(proc)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 60-frame simulated sequence (aisle_slow_1, seed 0), generated once."""
    from wardmap.sim.runner import generate

    path = tmp_path_factory.mktemp("storage_faults") / "aisle"
    generate("aisle_slow_1", 0, path, frames=FRAMES)
    return path


def _start_server(endpoint: str, db_url: str, port: int, log_dir: Path) -> Proc:
    config = log_dir / "server.toml"
    config.write_text(SERVER_CONFIG)
    cmd = _wardmap("server", "--connect", endpoint, "--db", db_url, "--http", f"127.0.0.1:{port}",
                   "--config", str(config), "--insecure-loopback")
    expect = f"server ready: http://127.0.0.1:{port}"
    return _start(cmd, lambda ln: ln == expect, log_dir, "server")


def _start_edge(endpoint: str, dataset: Path, tmp_path: Path) -> Proc:
    """``wardmap edge`` at 10 Hz after its ready line; its outbox is ``tmp_path/outbox``."""
    config = tmp_path / "edge.toml"
    config.write_text(EDGE_CONFIG)
    cmd = _wardmap("edge", "--robot", ROBOT, "--source", str(dataset), "--connect", endpoint,
                   "--outbox", str(tmp_path / "outbox"), "--rate", "10", "--config", str(config),
                   "--privacy", "off")
    return _start(cmd, lambda ln: " ready: session " in ln, tmp_path, "edge")


# --------------------------------------------------------------------------- watching


class Watch:
    """Acks (every robot) and the robot's heartbeats, as zenoh callbacks that only record."""

    def __init__(self) -> None:
        self.acks: list[tuple[Key, str]] = []
        self.heartbeats: list[dict[str, int | float]] = []
        self._cond = threading.Condition()

    def on_ack(self, sample: Any) -> None:
        ack = wire.decode_ack(sample.payload.to_bytes())
        with self._cond:
            self.acks.append(((ack.robot_id, ack.session_id, ack.seq), ack.status))
            self._cond.notify_all()

    def on_heartbeat(self, sample: Any) -> None:
        stats = dict(wire.decode_heartbeat(sample.payload.to_bytes()).stats)
        with self._cond:
            self.heartbeats.append(stats)
            self._cond.notify_all()

    def wait(self, what: str, pred: Callable[[Watch], bool], timeout_s: float = EVENT_TIMEOUT_S) -> None:
        with self._cond:
            if not self._cond.wait_for(lambda: pred(self), timeout=timeout_s):
                pytest.fail(f"timed out waiting for {what}: acks {self.statuses()}")

    def statuses(self) -> Counter[str]:
        with self._cond:
            return Counter(status for _, status in self.acks)

    def acked_stored(self) -> set[Key]:
        """Keys acked ``stored`` or ``duplicate``: the ones the server claims are committed."""
        with self._cond:
            return {key for key, status in self.acks if status in ("stored", "duplicate")}


@contextlib.contextmanager
def _watching(endpoint: str) -> Iterator[Watch]:
    watch = Watch()
    conf = zenoh.Config.from_json5(json.dumps(client_config([endpoint])))
    with (
        zenoh.open(conf) as session,
        session.declare_subscriber(ALL_ACKS, watch.on_ack),
        session.declare_subscriber(heartbeat_key(ROBOT), watch.on_heartbeat),
    ):
        yield watch


def _db_keys(db: Path, robot: str = ROBOT) -> tuple[int, set[Key]]:
    """(rows, distinct keys) of ``robot`` in the store, read directly."""
    with contextlib.closing(sqlite3.connect(db)) as con:
        rows = con.execute(
            "SELECT robot_id, session_id, seq FROM keyframes WHERE robot_id = ?", (robot,)
        ).fetchall()
    return len(rows), {(str(r), str(s), int(q)) for r, s, q in rows}


def _wait_stored(url: str, at_least: int) -> None:
    """Poll GET /v1/robots until the robot has ``at_least`` keyframes (deadline EVENT_TIMEOUT_S)."""
    deadline = time.monotonic() + EVENT_TIMEOUT_S
    with httpx.Client(base_url=url, timeout=5) as http:
        while time.monotonic() < deadline:
            robots = {r["robot_id"]: r["keyframes"] for r in http.get("/v1/robots").json()["robots"]}
            if robots.get(ROBOT, 0) >= at_least:
                return
            time.sleep(0.05)  # poll period, not synchronisation: the deadline bounds the wait
    pytest.fail(f"{ROBOT} never reached {at_least} stored keyframes")


def _report(
    record: Callable[[str, object], None], scenario: str, summary: dict[str, Any], db: Path, watch: Watch
) -> None:
    """Every keyframe the agent produced is stored once, its outbox ended empty, nothing was
    rejected; record produced / stored / duplicated for the scenario's table (docs/deploy.md)."""
    n = summary["keyframes"]
    rows, keys = _db_keys(db)
    assert summary["frames"] == FRAMES, summary
    assert n >= 4, summary
    assert summary["acked"] == n, summary
    assert summary["pending"] == 0 and summary["flushed"] is True, summary
    assert summary["rejected"] == {}, summary
    assert summary["retry_later"] >= 1, summary
    assert rows == len(keys) == n
    assert {s for _, s, _ in keys} == {summary["session_id"]}
    assert watch.statuses()["rejected"] == 0
    figures = {"produced": n, "stored": len(keys), "duplicated": rows - len(keys),
               "retry_acks": watch.statuses()["retry"], "duplicate_acks": watch.statuses()["duplicate"],
               "resent": summary["resent"]}
    for name, value in figures.items():
        record(name, value)
    log.warning("%s: %s", scenario, figures)


# --------------------------------------------------------------------------- 1. disk full


def test_disk_full_keeps_keyframes_on_the_robot_until_the_store_has_room(
    dataset: Path, router: str, tmp_path: Path, record_property: Callable[[str, object], None]
) -> None:
    """The store may grow only CAP_PAGES pages beyond its empty schema (``?max_pages=``), room
    for a keyframe or two. The edge streams 60 frames at 10 Hz; once the server has acked
    ``retry`` 3 times (the file is full: "database or disk is full") it is stopped: every key
    it acked stored is in the file, nothing was acked rejected. The server restarts on the same
    file without the cap (the space freed); the edge resends what it kept and every keyframe it
    produced is stored exactly once."""
    db = tmp_path / "map.db"
    open_store(f"sqlite:///{db}").close()
    with contextlib.closing(sqlite3.connect(db)) as con:
        empty_pages = int(con.execute("PRAGMA page_count").fetchone()[0])
    port = _free_port()
    server = _start_server(router, f"sqlite:///{db}?max_pages={empty_pages + CAP_PAGES}", port, tmp_path)
    try:
        with _watching(router) as watch:
            edge = _start_edge(router, dataset, tmp_path)
            try:
                watch.wait("3 retry acks", lambda w: w.statuses()["retry"] >= 3)
                assert_stops_cleanly(server)
                assert "Traceback" not in server.stderr()
                assert "cannot store" in server.stderr()
                rows, in_db = _db_keys(db)
                assert watch.acked_stored() <= in_db  # nothing acked before its commit
                assert rows < 20  # the cap held; the rest waits on the robot
                record_property("stored_while_full", rows)
                server = _start_server(router, f"sqlite:///{db}", port, tmp_path)
                summary = edge_summary(edge, RUN_TIMEOUT_S)
            finally:
                kill_proc(edge)
        _report(record_property, "disk full", summary, db, watch)
    finally:
        assert_stops_cleanly(server)
    assert "Traceback" not in server.stderr()


# --------------------------------------------------------------------------- 2. database locked


def test_database_locked_past_the_busy_timeout_loses_nothing(
    dataset: Path, router: str, tmp_path: Path, record_property: Callable[[str, object], None]
) -> None:
    """The server's busy timeout is 1 s (``?busy_timeout_s=1``). Once it stored 2 keyframes
    another process (this one) takes ``BEGIN EXCLUSIVE`` on the database and holds it until the
    server has acked ``retry`` (its insert waited the busy timeout and failed "database is
    locked"), i.e. just over the busy timeout. Reads go on meanwhile (WAL). Every keyframe is
    stored exactly once; none is acked rejected or dropped by the edge."""
    db = tmp_path / "map.db"
    port = _free_port()
    server = _start_server(router, f"sqlite:///{db}?busy_timeout_s={BUSY_TIMEOUT_S}", port, tmp_path)
    try:
        with _watching(router) as watch:
            edge = _start_edge(router, dataset, tmp_path)
            try:
                _wait_stored(f"http://127.0.0.1:{port}", 2)
                with contextlib.closing(sqlite3.connect(db, isolation_level=None, timeout=10)) as holder:
                    holder.execute("BEGIN EXCLUSIVE")
                    t_locked = time.monotonic()
                    watch.wait("a retry ack", lambda w: w.statuses()["retry"] >= 1)
                    _, in_db = _db_keys(db)  # a WAL reader is not blocked by the lock
                    assert watch.acked_stored() <= in_db
                    held_s = time.monotonic() - t_locked
                    holder.execute("ROLLBACK")
                assert held_s >= BUSY_TIMEOUT_S
                record_property("lock_held_s", round(held_s, 2))
                summary = edge_summary(edge, RUN_TIMEOUT_S)
            finally:
                kill_proc(edge)
        _report(record_property, "database locked", summary, db, watch)
        assert "database is locked" in server.stderr()
    finally:
        assert_stops_cleanly(server)
    assert "Traceback" not in server.stderr()


# --------------------------------------------------------------------------- 3. corrupted index


def test_corrupted_index_page_is_never_acked_rejected_and_the_edge_keeps_its_keyframes(
    dataset: Path, router: str, tmp_path: Path, record_property: Callable[[str, object], None]
) -> None:
    """The store holds 5 keyframes of another robot; then an index page of
    ``keyframes_robot_stamp`` is overwritten with noise. The server starts and answers
    ``/healthz``; every keyframe of the edge is acked ``retry`` (its insert hits the damaged
    index), never ``rejected`` or ``stored``, and the edge's heartbeats show it keeps every one.
    The server logs the damage once, with how to repair it. After the repair the docs give
    (``.dump`` into a new file) and a restart, every keyframe is stored exactly once and the
    5 old ones are intact."""
    db = tmp_path / "map.db"
    with open_store(f"sqlite:///{db}") as st:
        for payload in small_keyframes("seed", 5):
            st.insert(wire.decode_keyframe(payload), payload, 1.0)
    garble_index_page(db)
    port = _free_port()
    server = _start_server(router, f"sqlite:///{db}", port, tmp_path)
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=5) as http:
            assert http.get("/healthz").status_code == 200
        with _watching(router) as watch:
            edge = _start_edge(router, dataset, tmp_path)
            try:
                watch.wait("3 retry acks", lambda w: w.statuses()["retry"] >= 3)
                watch.wait("a heartbeat with 3 keyframes", lambda w: any(
                    h["keyframes"] >= 3 for h in w.heartbeats))
                kept = [h for h in watch.heartbeats if h["keyframes"] >= 3]
                assert all(h["pending"] == h["keyframes"] and h["acked"] == 0 for h in kept), kept
                assert set(watch.statuses()) == {"retry"}
                assert_stops_cleanly(server)
                damage_lines = [ln for ln in server.stderr().splitlines() if "database file is damaged" in ln]
                assert len(damage_lines) == 1, damage_lines
                assert ".recover" in damage_lines[0] and "backup" in damage_lines[0]
                repair_by_dump(db)
                server = _start_server(router, f"sqlite:///{db}", port, tmp_path)
                summary = edge_summary(edge, RUN_TIMEOUT_S)
            finally:
                kill_proc(edge)
        _report(record_property, "corrupted index", summary, db, watch)
        assert _db_keys(db, "seed")[0] == 5
    finally:
        assert_stops_cleanly(server)
    assert "Traceback" not in server.stderr()


# --------------------------------------------------------------------------- 4. readiness


def _matched_publisher(session: Any, robot: str) -> Any:
    pub = session.declare_publisher(
        keyframe_key(robot),
        reliability=zenoh.Reliability.RELIABLE,
        congestion_control=zenoh.CongestionControl.BLOCK,
    )
    matched = threading.Event()
    with pub.declare_matching_listener(lambda s: matched.set() if s.matching else None):
        if pub.matching_status.matching:
            matched.set()
        assert matched.wait(EVENT_TIMEOUT_S), "the ingest's subscriber never matched"
    return pub


@contextlib.contextmanager
def _ingest(router: str, store: Any) -> Iterator[Ingest]:
    """An ingest started on its own session to ``router``; stopped, then the session closed."""
    session = open_session([router])
    try:
        with Ingest(session, store) as ingest:
            yield ingest
    finally:
        session.close()


def test_ingest_ready_and_rejection_counts_through_a_lock_and_a_damaged_index(
    router: str, tmp_path: Path
) -> None:
    """The ingest runs in this process (router and zenoh real). While another connection holds
    the write lock: ready() is False naming the lock; 3 garbage payloads are acked ``rejected``
    and counted in memory (IngestCounters.unpersisted_rejections, Ingest.rejections()); 2 valid
    keyframes are acked ``retry``. Released: ready() is True, the 2 keyframes resent are stored
    and the 3 rejections reach the store exactly once. Then an index page is damaged: a keyframe
    is acked ``retry`` and ready() reports the damage."""
    db = tmp_path / "map.db"
    valid = small_keyframes("r1", 3)
    garbage = [b"\x00", valid[0][:50], valid[1] + b"junk"]
    store = open_store(f"sqlite:///{db}?busy_timeout_s=0.3")
    try:
        with _ingest(router, store) as ingest, _watching(router) as watch:
            assert ingest.ready() == (True, "ok")
            conf = zenoh.Config.from_json5(json.dumps(client_config([router])))
            with zenoh.open(conf) as session:
                pub = _matched_publisher(session, "r1")
                with contextlib.closing(sqlite3.connect(db, isolation_level=None, timeout=10)) as holder:
                    holder.execute("BEGIN EXCLUSIVE")
                    ok, why = ingest.ready()
                    assert not ok and "locked" in why, why
                    for p in [*garbage, *valid[:2]]:
                        pub.put(p)
                    watch.wait("5 acks", lambda w: len(w.acks) >= 5)
                    assert watch.statuses() == Counter({"rejected": 3, "retry": 2})
                    c = ingest.counters()
                    assert (c.rejected, c.retry_later, c.stored) == (3, 2, 0)
                    assert sum(c.unpersisted_rejections.values()) == 3
                    assert sum(ingest.rejections().values()) == 3  # WAL: readable while locked
                    holder.execute("ROLLBACK")
                assert ingest.ready() == (True, "ok")
                for p in valid[:2]:
                    pub.put(p)
                watch.wait("2 stored acks", lambda w: w.statuses()["stored"] >= 2)
                c = ingest.counters()
                assert c.unpersisted_rejections == {}
                assert sum(store.rejections().values()) == 3
                assert sum(ingest.rejections().values()) == 3
                pub.undeclare()
    finally:
        store.close()

    garble_index_page(db)
    store = open_store(f"sqlite:///{db}")
    try:
        with _ingest(router, store) as ingest, _watching(router) as watch:
            conf = zenoh.Config.from_json5(json.dumps(client_config([router])))
            with zenoh.open(conf) as session:
                pub = _matched_publisher(session, "r1")
                pub.put(valid[2])
                watch.wait("a retry ack", lambda w: w.statuses()["retry"] >= 1)
                ok, why = ingest.ready()
                assert not ok and "damaged" in why, why
                assert set(watch.statuses()) == {"retry"}
                pub.undeclare()
    finally:
        store.close()

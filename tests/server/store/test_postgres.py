"""What only the PostgreSQL store does: concurrent idempotent inserts, a stopped server, the
password rules and connection errors, its migrations and its object index. Protocol behaviour
shared with SQLite is tested by the other modules of this package over every backend.

Every test runs against the session's real cluster (tests/pgcluster.py), skipped where the
PostgreSQL 15 binaries are absent.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pgcluster
import pytest

from wardmap.server.store import (
    PASSWORD_ENV,
    GraphChange,
    PostgresMapStore,
    StoreDamagedError,
    StoreError,
    StoreUnavailableError,
    open_store,
    read_password_file,
)
from wardmap.server.store.postgres import APPLICATION_ID, classify_postgres_error
from wardmap.server.store.rows import find_sql
from wardmap.server.store.schema import LATEST, migrations

from .conftest import keyframe

psycopg = pytest.importorskip("psycopg")

RECOVERY_TIMEOUT_S = 30.0
LEASE_MOVE_S = 5.0


@pytest.fixture
def url(pg_cluster: pgcluster.Cluster) -> str:
    """A new, empty database of the session's cluster (the store creates its schema)."""
    return pg_cluster.url(pg_cluster.new_database())


def test_two_writers_store_each_keyframe_once(url: str) -> None:
    """Two threads, each with its own store (as two servers), insert the same 40 keyframes at the
    same moment: every key is stored exactly once, the other writer is told "duplicate", and the
    insertion order (rowid) has no gaps."""
    frames = [keyframe("r1", "s1", seq) for seq in range(40)]
    barrier = threading.Barrier(2)
    answers: list[list[str]] = [[], []]
    errors: list[BaseException] = []

    def write(i: int) -> None:
        try:
            with open_store(url) as store:
                for msg, data in frames:
                    barrier.wait(timeout=10)
                    answers[i].append(store.insert(msg, data, 1000.0 + msg.seq))
        except BaseException as exc:  # reported below, with the thread's answers
            errors.append(exc)
            barrier.abort()

    threads = [threading.Thread(target=write, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors, errors
    assert all(sorted((a, b)) == ["duplicate", "stored"] for a, b in zip(*answers, strict=True))
    with open_store(url) as store:
        assert store.stats().keyframes == 40
        stored = store.next_keyframes(0, 100)
        assert [k.rowid for k in stored] == list(range(1, 41))
        assert sorted(k.seq for k in stored) == list(range(40))


def test_a_stopped_server_is_unavailable_then_recovers(pg_cluster: pgcluster.Cluster, url: str) -> None:
    """With the database server stopped, an insert raises StoreUnavailableError (ingest acks
    ``retry``) and writable() is False with the reason; once it is back, both recover on the
    same store object within RECOVERY_TIMEOUT_S (the pool replaces its dead connections)."""
    msg, data = keyframe("r1", "s1", 0)
    with open_store(url) as store:
        assert store.writable() == (True, "ok")
        pg_cluster.stop()
        try:
            with pytest.raises(StoreUnavailableError, match="insert failed"):
                store.insert(msg, data, 1000.0)
            ok, why = store.writable()
            assert not ok and "readiness probe failed" in why
        finally:
            pg_cluster.start()
        # The pool reconnects in the background with exponential back-off (1 s, 2 s, ...).
        deadline = time.monotonic() + RECOVERY_TIMEOUT_S
        while not store.writable()[0] and time.monotonic() < deadline:
            pass  # writable() itself waits up to PROBE_TIMEOUT_S for a connection
        assert store.writable() == (True, "ok")
        assert store.insert(msg, data, 1000.0) == "stored"
        assert store.payload("r1", "s1", 0) == data


@pytest.mark.parametrize(
    "bad",
    ["postgresql://wardmap_pw:hunter2@127.0.0.1/db", "postgres://u:hunter2@h:5432/db?sslmode=require",
     "postgresql://u@h/db?password=hunter2"],
)
def test_a_password_in_the_url_is_refused(bad: str) -> None:
    """A password in the URL (user:pass@ or ?password=) is refused with one line naming where it
    should come from, and the password is not echoed."""
    with pytest.raises(StoreError) as info:
        open_store(bad)
    text = str(info.value)
    assert "hunter2" not in text and "\n" not in text
    assert "--db-password-file" in text and PASSWORD_ENV in text and ".pgpass" in text


def test_password_sources(
    pg_cluster: pgcluster.Cluster, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A role that must authenticate: no or a wrong password is "authentication failed" (one line);
    the right one works from the argument (--db-password-file), WARDMAP_DB_PASSWORD and PGPASSFILE."""
    url = pg_cluster.url(pg_cluster.new_database(), user=pgcluster.PASSWORD_ROLE)
    monkeypatch.delenv(PASSWORD_ENV, raising=False)
    monkeypatch.setenv("PGPASSFILE", str(tmp_path / "none"))
    for password in (None, "wrong"):
        with pytest.raises(StoreError, match="authentication failed for user wardmap_pw") as info:
            open_store(url, password=password)
        assert "\n" not in str(info.value) and not isinstance(info.value, StoreUnavailableError)
    secret = tmp_path / "db-password"
    secret.write_text(pgcluster.PASSWORD + "\n")
    open_store(url, password=read_password_file(secret)).close()
    monkeypatch.setenv(PASSWORD_ENV, pgcluster.PASSWORD)
    open_store(url).close()
    monkeypatch.delenv(PASSWORD_ENV)
    passfile = tmp_path / "pgpass"
    passfile.write_text(f"127.0.0.1:{pg_cluster.port}:*:{pgcluster.PASSWORD_ROLE}:{pgcluster.PASSWORD}\n")
    passfile.chmod(0o600)
    monkeypatch.setenv("PGPASSFILE", str(passfile))
    open_store(url).close()


def test_password_file_errors(tmp_path: Path) -> None:
    """A missing or empty password file is a one-line StoreError naming it."""
    with pytest.raises(StoreError, match="cannot read the database password file"):
        read_password_file(tmp_path / "missing")
    (tmp_path / "empty").write_text("")
    with pytest.raises(StoreError, match="is empty"):
        read_password_file(tmp_path / "empty")


def test_connection_errors_are_one_line(pg_cluster: pgcluster.Cluster) -> None:
    """No server at the port: StoreUnavailableError "cannot reach"; a database that does not exist:
    StoreError naming it and how to create it."""
    with pytest.raises(StoreUnavailableError, match="cannot reach the PostgreSQL server") as info:
        open_store(f"postgresql://postgres@127.0.0.1:{pgcluster.free_port()}/x?connect_timeout=2")
    assert "\n" not in str(info.value)
    with pytest.raises(StoreError, match="database nowhere does not exist; create it first"):
        open_store(pg_cluster.url("nowhere"))


def test_an_older_schema_is_migrated(pg_cluster: pgcluster.Cluster) -> None:
    """A database left at schema version 5 by an older wardmap (its tables, one keyframe) opens,
    is migrated to the latest version in place, and keeps its keyframe."""
    db = pg_cluster.new_database()
    steps = migrations("postgres")
    pg_cluster.psql(
        "CREATE TABLE wardmap_schema (id INTEGER PRIMARY KEY CHECK (id = 1), "
        "application_id BIGINT NOT NULL, version INTEGER NOT NULL, "
        "object_index TEXT NOT NULL CHECK (object_index IN ('postgres', 'postgis'))); "
        f"INSERT INTO wardmap_schema VALUES (1, {APPLICATION_ID}, 5, 'postgres'); "
        + "; ".join(s for step in steps[:5] for s in step),
        db,
    )
    pg_cluster.psql(
        "INSERT INTO keyframes (robot_id, session_id, seq, stamp, received_s, pose_source, "
        "payload_bytes, T_odom_camera, payload) VALUES ('r1', 's1', 0, 1.0, 2.0, 'rgb', 1, "
        "decode(repeat('00', 128), 'hex'), '\\x01')", db)
    with open_store(pg_cluster.url(db)) as store:
        assert store.stats().schema_version == LATEST == len(steps)
        assert store.stats().keyframes == 1
        assert store.tokens() == []  # the last step's table exists
    assert pg_cluster.psql("SELECT version FROM wardmap_schema", db).strip() == str(LATEST)


def test_foreign_and_newer_databases_are_refused(pg_cluster: pgcluster.Cluster) -> None:
    """A database with another program's tables, or with a schema newer than this build, is
    refused with one line and left untouched."""
    foreign = pg_cluster.new_database()
    pg_cluster.psql("CREATE TABLE patients (id INT)", foreign)
    with pytest.raises(StoreError, match=r"has tables \(patients\) but is not a wardmap keyframe store"):
        open_store(pg_cluster.url(foreign))
    assert pg_cluster.psql("SELECT to_regclass('keyframes') IS NULL", foreign).strip() == "t"
    newer = pg_cluster.new_database()
    open_store(pg_cluster.url(newer)).close()
    pg_cluster.psql(f"UPDATE wardmap_schema SET version = {LATEST + 1}", newer)
    with pytest.raises(StoreError, match="written by a newer wardmap; upgrade wardmap"):
        open_store(pg_cluster.url(newer))


@pytest.mark.parametrize(
    ("query", "index"), [("?postgis=off", "objects_bounds_xy"), ("", "objects_bounds_3d")]
)
def test_radius_queries_use_the_object_index(pg_cluster: pgcluster.Cluster, query: str, index: str) -> None:
    """The radius query's plan searches the object index of the database (the GiST box fallback, or
    PostGIS's n-D index), with sequential scans disabled so the tiny table cannot hide it."""
    if index == "objects_bounds_3d" and not pg_cluster.postgis:
        pytest.skip("PostGIS is not installed for PostgreSQL 15 (Debian: postgresql-15-postgis-3)")
    db = pg_cluster.new_database()
    with open_store(pg_cluster.url(db) + query) as store:
        assert isinstance(store, PostgresMapStore)
        assert store.object_index == ("postgres" if query else "postgis")
        sql, params = find_sql(
            store.object_index, category=None, near=(1.0, 2.0, 0.5), radius_m=3.0, min_confidence=None,
            robot=None, include_unconfirmed=False, limit=10, offset=0,
        )
    for name, value in params.items():
        sql = sql.replace(f":{name}", repr(value))
    plan = pg_cluster.psql(f"SET enable_seqscan = off; EXPLAIN {sql}", db)
    assert index in plan, plan


@pytest.mark.parametrize(
    ("error", "kind"),
    [
        ("DataCorrupted", StoreDamagedError), ("IndexCorrupted", StoreDamagedError),
        ("ReadOnlySqlTransaction", StoreUnavailableError), ("DiskFull", StoreUnavailableError),
        ("AdminShutdown", StoreUnavailableError), ("TooManyConnections", StoreUnavailableError),
        ("SerializationFailure", StoreUnavailableError), ("LockNotAvailable", StoreUnavailableError),
        ("QueryCanceled", StoreUnavailableError), ("UniqueViolation", StoreError),
        ("SyntaxError", StoreError),
    ],
)
def test_error_classification(error: str, kind: type[StoreError]) -> None:
    """PostgreSQL's error states map to the store's kinds as SQLite's do: corruption is damage (no
    retry heals it), "cannot now" states are unavailable (ingest acks retry), a bug is a StoreError."""
    assert classify_postgres_error(getattr(psycopg.errors, error)("x")) is kind
    assert classify_postgres_error(psycopg.OperationalError("connection lost")) is StoreUnavailableError


def test_one_server_holds_the_writer_lease_at_a_time(url: str) -> None:
    """Two stores on one database (as two servers): the first to ask gets the writer lease, the
    second does not, both name the same holder; once the holder gives it back the second gets
    it; a bad holder name is refused."""
    with open_store(url) as a_store, open_store(url) as b_store:
        a, b = a_store.writer_lease("server-a"), b_store.writer_lease("server-b")
        assert a_store.writer_lease("server-a").current_holder() is None
        assert a.acquire() and a.acquire()  # asking again while holding it keeps it
        assert not b.acquire()
        assert a.held() and not b.held()
        assert a.current_holder() == b.current_holder() == "server-a"
        a.release()
        assert not a.held()
        assert b.acquire() and b.held()
        assert a.current_holder() == "server-b"
        assert not a.acquire()
        b.release()
        with pytest.raises(StoreError, match="printable ASCII"):
            a_store.writer_lease("")
        with pytest.raises(StoreError, match="printable ASCII"):
            a_store.writer_lease("x" * 41)


def test_the_writer_lease_moves_when_its_holder_is_killed(pg_cluster: pgcluster.Cluster, url: str) -> None:
    """A process holding the writer lease is SIGKILLed: the database releases it with the dead
    process's connection and a standby store acquires it within LEASE_MOVE_S; a holder whose
    lease connection the database ends (``pg_terminate_backend``) sees ``held()`` False."""
    code = ("import sys, time; from wardmap.server.store import open_store\n"
            "s = open_store(sys.argv[1]); l = s.writer_lease('doomed')\n"
            "print('held' if l.acquire() else 'refused', flush=True); time.sleep(600)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, url], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
        with open_store(url) as store:
            lease = store.writer_lease("standby")
            assert not lease.acquire()
            assert lease.current_holder() == "doomed"
            proc.kill()
            killed = time.monotonic()
            while not lease.acquire():
                assert time.monotonic() - killed < LEASE_MOVE_S, "the lease did not move"
                time.sleep(0.05)  # polling the database, bounded by LEASE_MOVE_S
            assert lease.current_holder() == "standby"
            pg_cluster.psql("SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                            "WHERE application_name = 'wardmap writer lease: standby'")
            assert not lease.held()
            assert lease.current_holder() is None
            assert lease.acquire()  # a new connection takes it again
    finally:
        proc.kill()
        proc.wait(timeout=30)


def test_a_former_writer_cannot_write_the_map(pg_cluster: pgcluster.Cluster, url: str) -> None:
    """The writer fence: server A holds the lease and writes; its lease connection ends (the
    database released the lock) and B takes the lease; A's next map writes (graph, cursor,
    checkpoint) are refused and change nothing, while B writes. A store that never held the
    lease is not fenced."""
    with open_store(url) as a_store, open_store(url) as b_store:
        a = a_store.writer_lease("server-a")
        assert a.acquire()
        a_store.commit_graph("backend", 1, GraphChange(bump_epoch=True))
        pg_cluster.psql("SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                        "WHERE application_name = 'wardmap writer lease: server-a'")
        assert b_store.writer_lease("server-b").acquire()
        with pytest.raises(StoreError, match="writer lease moved"):
            a_store.commit_graph("backend", 2, GraphChange(bump_epoch=True))
        with pytest.raises(StoreError, match="writer lease moved"):
            a_store.close_sessions([("r1", "s1")], 2)
        assert a_store.cursor("backend") == 1 and a_store.graph_epoch() == 1
        assert a_store.closed_sessions() == []
        b_store.commit_graph("backend", 2, GraphChange(bump_epoch=True))
        assert b_store.graph_epoch() == 2
        with open_store(url) as unfenced:
            unfenced.close_sessions([("r1", "s1")], 2)
            assert len(unfenced.closed_sessions()) == 1

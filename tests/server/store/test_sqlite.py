"""Tests of the SQLite backend (``wardmap.server.store.sqlite``): URLs, the file and its
migrations, refusing other files, crash safety, and the R*Tree behind radius queries.

The crash test SIGKILLs a real child process that is inserting; it synchronises on the lines
the child writes after each committed insert, never on sleeps.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import sqlite3
import sys
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest
from procs import sigkill_after

from wardmap.server.objectmap import ObjectMap, ObjectState
from wardmap.server.store import (
    MIGRATIONS,
    GraphChange,
    GraphEdgeRow,
    GraphNodeRow,
    SqliteMapStore,
    StoreError,
    open_store,
)
from wardmap.server.store import sqlite as sqlite_backend
from wardmap.server.store.rows import find_sql
from wardmap.shared.se3 import yaw_transform

from .conftest import T0, keyframe


def _user_version(path: Path) -> int:
    with sqlite3.connect(path) as conn:
        return int(conn.execute("PRAGMA user_version").fetchone()[0])


def _integrity(path: Path) -> str:
    with sqlite3.connect(path) as conn:
        return str(conn.execute("PRAGMA integrity_check").fetchone()[0])


def test_migration_from_empty_v0_file(tmp_path: Path) -> None:
    """A zero-byte file and an empty SQLite file at user_version 0 are migrated to the latest version
    in WAL mode and then accept inserts."""
    for name, make in (
        ("zero.db", lambda p: p.write_bytes(b"")),
        ("v0.db", lambda p: sqlite3.connect(p).close()),
    ):
        path = tmp_path / name
        make(path)
        with SqliteMapStore.open(path) as st:
            assert st.insert(*keyframe(), 1.0) == "stored"
        assert _user_version(path) == len(MIGRATIONS)
        with sqlite3.connect(path) as conn:
            tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
            assert {"robots", "sessions", "keyframes", "rejections"} <= tables
            assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
            indexes = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'index'")}
            assert "keyframes_robot_stamp" in indexes


def test_a_version_9_store_keeps_its_graph_edges(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """v10 copies ``graph_edges`` to widen its kind CHECK: the stored edges survive it."""
    path = tmp_path / "map.db"
    with monkeypatch.context() as m:
        v9 = dataclasses.replace(sqlite_backend.STORE_DB, migrations=MIGRATIONS[:9])
        m.setattr(sqlite_backend, "STORE_DB", v9)
        with SqliteMapStore.open(path) as st:
            st.insert(*keyframe("r1", "s1", 0), 1.0)
            st.insert(*keyframe("r1", "s1", 1), 1.0)
            key0, key1 = ("r1", "s1", 0), ("r1", "s1", 1)
            nodes = [GraphNodeRow(k, T0 + k[2], np.eye(4), "rgb", np.eye(4), None, b"\x00" * 8)
                     for k in (key0, key1)]
            st.commit_graph("backend", 2, GraphChange(nodes, [GraphEdgeRow("odometry", key0, key1, np.eye(4),
                                                                           np.full(6, 0.01), False)]))
    assert _user_version(path) == 9
    with SqliteMapStore.open(path) as st:
        assert _user_version(path) == len(MIGRATIONS)
        assert [e.kind for e in st.graph_records()[1]] == ["odometry"]
        st.commit_graph("backend", 2, GraphChange((), [GraphEdgeRow("bundle", key0, key1, np.eye(4),
                                                                    np.full(6, 0.001), False)]))
        assert [e.kind for e in st.graph_records()[1]] == ["odometry", "bundle"]


def test_failed_migration_rolls_back(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A migration that fails half-way leaves the file at version 0 with no tables (one transaction)."""
    path = tmp_path / "map.db"
    broken = ((*MIGRATIONS[0], "CREATE TABLE robots (x)"),)  # the second CREATE of robots fails
    monkeypatch.setattr(sqlite_backend, "STORE_DB",
                        dataclasses.replace(sqlite_backend.STORE_DB, migrations=broken))
    with pytest.raises(StoreError, match="cannot prepare"):
        SqliteMapStore.open(path)
    assert _user_version(path) == 0
    with sqlite3.connect(path) as conn:
        assert conn.execute("SELECT COUNT(*) FROM sqlite_master").fetchone()[0] == 0


def test_future_version_asks_to_upgrade(tmp_path: Path) -> None:
    """A store written by a newer wardmap (user_version above ours) is refused: "upgrade wardmap"."""
    path = tmp_path / "map.db"
    open_store(f"sqlite:///{path}").close()
    with sqlite3.connect(path) as conn:
        conn.execute(f"PRAGMA user_version = {len(MIGRATIONS) + 1}")
    with pytest.raises(StoreError, match="upgrade wardmap"):
        open_store(f"sqlite:///{path}")


def test_corrupt_file(tmp_path: Path) -> None:
    """A file of random bytes raises StoreError saying so and is left untouched."""
    path = tmp_path / "map.db"
    data = np.random.default_rng(7).integers(0, 256, 8192, dtype=np.uint8).tobytes()
    path.write_bytes(data)
    with pytest.raises(StoreError, match="not a wardmap keyframe store or it is corrupt"):
        open_store(f"sqlite:///{path}")
    assert path.read_bytes() == data


def test_foreign_sqlite_file(tmp_path: Path) -> None:
    """A valid SQLite file of some other program is refused, not migrated into."""
    path = tmp_path / "other.db"
    with sqlite3.connect(path) as conn:
        conn.execute("CREATE TABLE patients (name TEXT)")
    with pytest.raises(StoreError, match="not a wardmap keyframe store"):
        open_store(f"sqlite:///{path}")


def test_unwritable_path(tmp_path: Path) -> None:
    """A path under a regular file, or a path that is a directory, raises StoreError."""
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(StoreError, match="cannot create the store folder"):
        open_store(f"sqlite:///{blocker / 'sub' / 'map.db'}")
    (tmp_path / "dir.db").mkdir()
    with pytest.raises(StoreError, match="directory"):
        open_store(f"sqlite:///{tmp_path / 'dir.db'}")


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores file permissions")
def test_read_only_folder(tmp_path: Path) -> None:
    """A folder without write permission raises StoreError (skipped as root)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        with pytest.raises(StoreError, match="cannot"):
            open_store(f"sqlite:///{folder / 'map.db'}")
    finally:
        folder.chmod(0o700)


@pytest.mark.parametrize(
    ("url", "match"),
    [
        ("postgresql://u:secret@host/db", "carries a password"),
        ("postgres://u:secret@host/db?sslmode=require", "carries a password"),
        ("postgresql+psycopg://u@host/db", "expected postgresql://"),
        ("mysql://host/db", "unknown store URL"),
        ("map.db", "unknown store URL"),
        ("sqlite:///", "no file path"),
        ("sqlite:///:memory:", "plain file path"),
    ],
)
def test_bad_urls(url: str, match: str) -> None:
    """Unknown schemes, an empty path and in-memory databases raise StoreError (no password echoed)."""
    with pytest.raises(StoreError, match=match) as info:
        open_store(url)
    assert "secret" not in str(info.value)


def test_relative_url(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``sqlite:///x/map.db`` is relative to the working folder; the parent folder is created."""
    monkeypatch.chdir(tmp_path)
    open_store("sqlite:///x/map.db").close()
    assert (tmp_path / "x" / "map.db").is_file()


_CHILD = """
import sys
from contextlib import closing
sys.path[:0] = [sys.argv[2], sys.argv[3]]
from conftest import keyframe
from wardmap.server.store import open_store
with open_store("sqlite:///" + sys.argv[1]) as st:
    for seq in range(1_000_000):
        msg, data = keyframe(session="crash", seq=seq)
        assert st.insert(msg, data, 1.0 + seq) == "stored"
        sys.stdout.write(f"{seq}\\n")
        sys.stdout.flush()
"""


@pytest.mark.timeout(60)
def test_crash_safety_sigkill(tmp_path: Path) -> None:
    """A child inserting keyframes is SIGKILLed mid-stream; every insert it reported as committed is
    on disk with intact bytes, and integrity_check is ok.

    The child prints each seq after insert() returned. We kill it after 50 reports, then read every
    line it managed to write before dying. At most the one insert in flight may be there unreported.
    """
    path = tmp_path / "map.db"
    tests_dir = Path(__file__).parents[2]  # tests/: factories.py, which the store's conftest imports
    reported, returncode = sigkill_after(
        [sys.executable, "-c", _CHILD, str(path), str(Path(__file__).parent), str(tests_dir)], 50)
    assert returncode == -signal.SIGKILL
    assert reported == list(range(len(reported)))

    assert _integrity(path) == "ok"
    with open_store(f"sqlite:///{path}") as st:
        rows = st.keyframes("r1", limit=1000).rows
        seqs = [r.seq for r in rows]
        assert seqs[: len(reported)] == reported
        assert len(seqs) - len(reported) in (0, 1)
        for seq in seqs:
            assert st.payload("r1", "crash", seq) == keyframe(session="crash", seq=seq)[1]
    assert _integrity(path) == "ok"


def _door(oid: int, x: float) -> ObjectState:
    return ObjectState(oid, "door", 0.9, yaw_transform(x, 0.0, 0.0, 1.0), np.array([1.0, 0.5, 2.0]))


def test_radius_queries_search_the_rtree(tmp_path: Path) -> None:
    """The SELECT of a radius query searches the R*Tree by its constraints (not a scan of it), and
    deleting an object removes its R*Tree row with it."""
    path = tmp_path / "map.db"
    with open_store(f"sqlite:///{path}") as store:
        om = ObjectMap(store)
        om.upsert([_door(1, 0.0), _door(2, 0.5), _door(3, 10.0)])
        om.delete(1, merged_into=2)
        om.delete(3)
    sql, params = find_sql(
        "sqlite", category="door", near=(10.0, 10.0, 1.0), radius_m=3.0, min_confidence=None, robot=None,
        include_unconfirmed=False, limit=10, offset=0,
    )
    with closing(sqlite3.connect(path)) as conn:
        plan = " ".join(str(row[-1]) for row in conn.execute(f"EXPLAIN QUERY PLAN {sql}", params))
        rtree = [int(r[0]) for r in conn.execute("SELECT object_id FROM objects_rtree")]
    assert "VIRTUAL TABLE INDEX 2:" in plan  # rtree constraint search, not a scan
    assert rtree == [2]


def test_postgres_url_without_psycopg_says_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where psycopg is not installed, a postgresql:// URL is one StoreError naming the extra."""
    monkeypatch.setitem(sys.modules, "psycopg", None)  # import psycopg raises ImportError
    with pytest.raises(StoreError, match=r"pip install 'wardmap\[postgres\]'") as info:
        open_store("postgresql://wardmap@127.0.0.1:5432/wardmap")
    assert "\n" not in str(info.value)


def test_the_writer_lease_of_a_sqlite_store_is_its_one_servers(tmp_path: Path) -> None:
    """SQLite serves one server: its writer lease is granted at once, names that server, and is
    no longer held once given back or once the store is closed."""
    store = SqliteMapStore.open(tmp_path / "map.db")
    lease = store.writer_lease("solo")
    assert not lease.held() and lease.current_holder() is None
    assert lease.acquire() and lease.held() and lease.current_holder() == "solo"
    lease.release()
    assert not lease.held()
    assert lease.acquire()
    store.close()
    assert not lease.held() and not lease.acquire()
    with pytest.raises(StoreError, match="printable ASCII"):
        store.writer_lease("two\nlines")

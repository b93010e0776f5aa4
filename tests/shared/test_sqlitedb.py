"""Shared SQLite plumbing: file marking, migrations, WAL/FULL, transactions, errors."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from wardmap.shared import sqlitedb
from wardmap.shared.errors import WardmapError


class DemoError(WardmapError):
    pass


KIND = sqlitedb.SqliteKind("demo file", 0x64656D6F, (("CREATE TABLE t (x INTEGER)",),), DemoError)


def _open(path: Path, kind: sqlitedb.SqliteKind = KIND) -> sqlite3.Connection:
    conn = sqlitedb.connect(path, kind)
    sqlitedb.check_and_migrate(conn, path, kind)
    return conn


def test_new_file_is_marked_migrated_and_durable(tmp_path: Path) -> None:
    """A new file gets the kind's application_id, the latest version, WAL and synchronous FULL."""
    conn = _open(tmp_path / "d.db")
    try:
        assert conn.execute("PRAGMA application_id").fetchone()[0] == KIND.application_id
        assert conn.execute("PRAGMA user_version").fetchone()[0] == 1
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert conn.execute("PRAGMA synchronous").fetchone()[0] == 2  # FULL
    finally:
        conn.close()


def test_transaction_rolls_back_on_error(tmp_path: Path) -> None:
    """An exception inside ``transaction`` leaves nothing behind."""
    conn = _open(tmp_path / "d.db")
    try:
        with pytest.raises(RuntimeError), sqlitedb.transaction(conn):
            conn.execute("INSERT INTO t VALUES (1)")
            raise RuntimeError("boom")
        assert conn.execute("SELECT COUNT(*) FROM t").fetchone()[0] == 0
        with sqlitedb.transaction(conn):
            conn.execute("INSERT INTO t VALUES (2)")
        assert conn.execute("SELECT COUNT(*) FROM t").fetchone()[0] == 1
    finally:
        conn.close()


def test_foreign_future_and_corrupt_files_are_refused(tmp_path: Path) -> None:
    """Another program's database, a newer schema and random bytes each raise the kind's error."""
    foreign = tmp_path / "foreign.db"
    with sqlite3.connect(foreign) as c:
        c.execute("CREATE TABLE other (y)")
    with pytest.raises(DemoError, match="not a wardmap demo file"):
        _open(foreign)
    future = tmp_path / "future.db"
    _open(future).close()
    with sqlite3.connect(future) as c:
        c.execute("PRAGMA user_version = 9")
    with pytest.raises(DemoError, match="upgrade wardmap"):
        _open(future)
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"\x00not sqlite at all" * 100)
    with pytest.raises(DemoError, match="corrupt"):
        _open(junk)
    with pytest.raises(DemoError, match="directory"):
        _open(tmp_path)

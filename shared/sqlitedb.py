"""Common plumbing of wardmap's SQLite files (the edge outbox, the server's store).

Each kind of file is marked with its own ``PRAGMA application_id`` (so another program's
database is never migrated into), carries its schema version in ``PRAGMA user_version``
and is upgraded by an ordered list of migrations inside one transaction. Connections
run in autocommit mode with explicit ``BEGIN IMMEDIATE`` transactions, WAL, and
``synchronous = FULL`` (a committed transaction survives power loss). Every SQLite
failure becomes the kind's own :class:`~wardmap.shared.errors.WardmapError` subclass.
This module touches only the file it is asked to open.
"""

from __future__ import annotations

import logging
import sqlite3
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from wardmap.shared.errors import WardmapError

log = logging.getLogger(__name__)

Migration = tuple[str, ...]


@dataclass(frozen=True)
class SqliteKind:
    """What kind of wardmap database a file is.

    Attributes:
        label: how messages name it ("outbox database", "keyframe store").
        application_id: the 32-bit mark in the file header.
        migrations: SQL statement groups; group ``i`` upgrades version ``i`` to ``i + 1``.
        error: the exception class raised for this kind.
        busy_timeout_s: how long a connection waits for another writer.
        on_migrated: called inside the migration transaction with the new version.
    """

    label: str
    application_id: int
    migrations: tuple[Migration, ...]
    error: type[WardmapError]
    busy_timeout_s: float = 5.0
    on_migrated: Callable[[sqlite3.Connection, int], None] | None = None

    @property
    def latest(self) -> int:
        return len(self.migrations)


def connect(path: Path, kind: SqliteKind) -> sqlite3.Connection:
    """Open ``path`` in autocommit mode with the busy timeout and ``synchronous = FULL``.

    ``check_same_thread`` is off so an owner may close it from another thread; callers
    keep one connection per thread (or serialise access) as their docstrings state.
    """
    if path.is_dir():
        raise kind.error(f"cannot open the {kind.label} {path}: it is a directory")
    try:
        conn = sqlite3.connect(
            path, timeout=kind.busy_timeout_s, isolation_level=None, check_same_thread=False
        )
    except sqlite3.Error as exc:
        raise kind.error(f"cannot open the {kind.label} {path}: {exc}") from exc
    try:
        conn.execute(f"PRAGMA busy_timeout = {int(kind.busy_timeout_s * 1000)}")
        conn.execute("PRAGMA schema_version").fetchone()  # a file that is not SQLite fails here
        conn.execute("PRAGMA synchronous = FULL")  # per connection, not stored in the file
    except sqlite3.DatabaseError as exc:
        conn.close()
        raise kind.error(f"{path} is not a wardmap {kind.label} or it is corrupt ({exc})") from exc
    return conn


def check_and_migrate(conn: sqlite3.Connection, path: Path, kind: SqliteKind) -> None:
    """Check the file is this kind at a version this build knows, switch to WAL, migrate."""
    try:
        app_id, version, tables = _header(conn)
    except sqlite3.DatabaseError as exc:
        raise kind.error(f"{path} is not a wardmap {kind.label} or it is corrupt ({exc})") from exc
    _check_header(path, kind, app_id, version, tables)
    try:
        mode = str(conn.execute("PRAGMA journal_mode = WAL").fetchone()[0]).lower()
        if mode != "wal":
            raise kind.error(f"{kind.label} {path}: cannot switch to WAL mode (journal_mode is {mode!r})")
        if version < kind.latest:
            with transaction(conn):
                # Read again under the write lock: another process may have migrated meanwhile.
                app_id, version, tables = _header(conn)
                _check_header(path, kind, app_id, version, tables)
                for i in range(version, kind.latest):
                    for statement in kind.migrations[i]:
                        conn.execute(statement)
                conn.execute(f"PRAGMA application_id = {kind.application_id}")
                conn.execute(f"PRAGMA user_version = {kind.latest}")
                if kind.on_migrated is not None:
                    kind.on_migrated(conn, kind.latest)
            log.info("%s %s: schema migrated from version %d to %d", kind.label, path, version, kind.latest)
    except sqlite3.Error as exc:
        raise kind.error(f"{kind.label} {path}: cannot prepare the database: {exc}") from exc


@contextmanager
def transaction(conn: sqlite3.Connection) -> Iterator[None]:
    """``BEGIN IMMEDIATE`` .. ``COMMIT``; rolled back on any exception (also a failed commit)."""
    conn.execute("BEGIN IMMEDIATE")
    try:
        yield
    except BaseException:
        if conn.in_transaction:
            conn.execute("ROLLBACK")
        raise
    try:
        conn.execute("COMMIT")
    except BaseException:
        if conn.in_transaction:
            conn.execute("ROLLBACK")
        raise


class GuardedAccess:
    """Mixin for a class over one SQLite file: ``_read`` and ``_write`` blocks on
    ``self._connection()`` whose sqlite3 errors become ``_DB_ERROR`` naming the file and what
    failed (``"<_DB_LABEL> <path>: <what> failed: ..."``). ``_write`` is one :func:`transaction`.
    """

    _DB_LABEL: str
    _DB_ERROR: type[WardmapError]
    path: Path

    def _connection(self) -> sqlite3.Connection:
        raise NotImplementedError

    @contextmanager
    def _db_errors(self, what: str) -> Iterator[None]:
        try:
            yield
        except sqlite3.Error as exc:
            raise self._DB_ERROR(f"{self._DB_LABEL} {self.path}: {what} failed: {exc}") from exc

    @contextmanager
    def _read(self, what: str) -> Iterator[sqlite3.Connection]:
        with self._db_errors(what):
            yield self._connection()

    @contextmanager
    def _write(self, what: str) -> Iterator[sqlite3.Connection]:
        """One ``BEGIN IMMEDIATE`` .. ``COMMIT`` transaction; rolled back on any exception."""
        with self._db_errors(what):
            conn = self._connection()
            with transaction(conn):
                yield conn


def _header(conn: sqlite3.Connection) -> tuple[int, int, list[str]]:
    app_id = int(conn.execute("PRAGMA application_id").fetchone()[0])
    version = int(conn.execute("PRAGMA user_version").fetchone()[0])
    tables = [str(r[0]) for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
    return app_id, version, tables


def _check_header(path: Path, kind: SqliteKind, app_id: int, version: int, tables: list[str]) -> None:
    if app_id != kind.application_id and (app_id != 0 or version != 0 or tables):
        raise kind.error(
            f"{path} is an SQLite file but not a wardmap {kind.label} (application_id={app_id:#x}, "
            f"user_version={version}, tables={tables}); refusing to touch it"
        )
    if version > kind.latest:
        raise kind.error(
            f"{kind.label} {path} has schema version {version} but this wardmap knows up to "
            f"{kind.latest}: it was written by a newer wardmap; upgrade wardmap to open it"
        )

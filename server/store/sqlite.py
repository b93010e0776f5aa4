"""The SQLite map store: the embedded default backend (stdlib ``sqlite3``).

Guarantees:

- An :meth:`~SqliteMapStore.insert` that returned is committed in WAL mode with
  ``synchronous=FULL``: it survives a crash of the process and a power loss, so acking
  after it returns never acks a keyframe that could be lost. Every other write is one
  transaction too.
- Idempotent on ``(robot_id, session_id, seq)``: a key already stored returns
  ``"duplicate"`` and changes nothing (see :meth:`~SqliteMapStore.insert` for why the
  first copy wins even when the bytes differ).
- Keyframes are never deleted or rewritten (object-map rows on the same file are).

Failures: a SQLite error becomes :class:`StoreUnavailableError` when the store cannot write
*now* (disk or ``max_pages`` cap full, locked past the busy timeout, I/O error, read-only),
:class:`StoreDamagedError` when the file is damaged (logged once with :data:`REPAIR_HINT`), or
a plain :class:`StoreError`; none of them means the keyframe was bad. :meth:`SqliteMapStore.writable`
is the readiness probe. Options (busy timeout, page cap) come from the URL's query
(:class:`StoreOptions`).

Threads: one SQLite connection per thread (``threading.local``), opened on the thread's
first call, so the ingest thread writes while HTTP threads read concurrently (WAL lets
readers proceed during a write; each read sees the last committed state). Writers are
serialised by SQLite (``BEGIN IMMEDIATE`` with a busy timeout). Connections of threads that
have ended are closed when the next thread opens one; :meth:`~SqliteMapStore.close`
closes them all and must be called after the other threads stopped using the store.
Several processes may open the same file (e.g. a CLI reading while the server runs); the
file must be on a local disk (WAL needs shared memory).

Storage: ``PRAGMA application_id`` marks the file as a wardmap keyframe store and
``PRAGMA user_version`` holds the schema version; :data:`MIGRATIONS` are applied in order,
inside one transaction, when an older file (including a new, empty one) is opened. A file
from a newer wardmap is refused with "upgrade wardmap". Poses are 16 little-endian float64,
row-major; measurements and cameras are encoded by ``codec.py``. The object map's radius
query uses an SQLite R*Tree over the objects' world bounds (:func:`find_sql`).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import shutil
import sqlite3
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, NoReturn
from urllib.parse import unquote

from wardmap.server.store import schema
from wardmap.server.store.records import (
    StoreDamagedError,
    StoreError,
    StoreUnavailableError,
)
from wardmap.server.store.schema import Dialect
from wardmap.server.store.sqlbase import SqlMapStore, check_lease_holder
from wardmap.shared import sqlitedb

log = logging.getLogger(__name__)

APPLICATION_ID: Final = 0x77726D73  # "wrms": marks the SQLite file as a wardmap keyframe store
BUSY_TIMEOUT_S: Final = 10.0

MIGRATIONS: Final[tuple[sqlitedb.Migration, ...]] = schema.migrations("sqlite")
"""SQL statements that take the schema from version ``i`` to ``i + 1`` (``MIGRATIONS[i]``; ``schema.py``)."""

# SQLite primary result codes (``sqlite3.Error.sqlite_errorcode & 0xFF``).
_UNAVAILABLE_CODES: Final = frozenset({
    sqlite3.SQLITE_BUSY, sqlite3.SQLITE_LOCKED, sqlite3.SQLITE_NOMEM, sqlite3.SQLITE_READONLY,
    sqlite3.SQLITE_IOERR, sqlite3.SQLITE_FULL, sqlite3.SQLITE_CANTOPEN, sqlite3.SQLITE_PROTOCOL,
})
_DAMAGED_CODES: Final = frozenset({sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB})
REPAIR_HINT: Final = (
    "stop the server and repair the file: sqlite3 DB '.recover' | sqlite3 NEW (where .recover is "
    "missing: sqlite3 DB .dump | sqlite3 NEW, then sqlite3 NEW 'PRAGMA application_id = "
    f"{APPLICATION_ID}; PRAGMA user_version = {len(MIGRATIONS)}'), check sqlite3 NEW "
    "'PRAGMA integrity_check', move NEW over DB and delete DB-wal and DB-shm; or restore DB from a "
    "backup. Robots keep their unacked keyframes meanwhile"
)
"""How to repair a damaged store (in :class:`StoreDamagedError` messages and the server log)."""
PROBE_BUSY_TIMEOUT_S: Final = 1.0
"""Longest :meth:`SqliteMapStore.writable` waits for another writer's lock."""


def classify_sqlite_error(exc: sqlite3.Error) -> type[StoreError]:
    """Which :class:`StoreError` a SQLite failure is: :class:`StoreUnavailableError` (cannot store
    now: full, locked/busy, I/O error, read-only, cannot open), :class:`StoreDamagedError` (malformed,
    corrupt, not a database) or plain :class:`StoreError` (anything else: a bug or bad use)."""
    code = getattr(exc, "sqlite_errorcode", None)
    if isinstance(code, int):
        primary = code & 0xFF
        if primary in _DAMAGED_CODES:
            return StoreDamagedError
        if primary in _UNAVAILABLE_CODES:
            return StoreUnavailableError
        return StoreError
    text = str(exc).lower()  # raised without a code (rare): fall back on SQLite's fixed messages
    if "malformed" in text or "not a database" in text or "corrupt" in text:
        return StoreDamagedError
    if any(w in text for w in ("disk is full", "locked", "busy", "disk i/o", "readonly", "unable to open")):
        return StoreUnavailableError
    return StoreError


@dataclass(frozen=True, slots=True)
class StoreOptions:
    """Settings of the SQLite store, given as the URL's query:
    ``sqlite:///map.db?busy_timeout_s=2&max_pages=250000`` (docs/deploy.md, "Storage faults").

    Attributes:
        busy_timeout_s: how long a statement waits for another connection's write lock (another
            process holding ``BEGIN EXCLUSIVE``, a backup) before it fails as
            :class:`StoreUnavailableError`; > 0 and <= 600 seconds.
        max_pages: cap on the file's size in database pages (``PRAGMA max_page_count``; a page is
            4096 bytes unless the file says otherwise); a write beyond it fails as "database or
            disk is full" (:class:`StoreUnavailableError`). None: SQLite's own limit. Keeps the
            server from filling a disk it shares, and lets a fault drill fill "the disk".
    """

    busy_timeout_s: float = BUSY_TIMEOUT_S
    max_pages: int | None = None

    def __post_init__(self) -> None:
        t = self.busy_timeout_s
        if isinstance(t, bool) or not isinstance(t, int | float) or not (math.isfinite(t) and 0 < t <= 600):
            raise StoreError(f"store option busy_timeout_s must be a number in (0, 600] s, got {t!r}")
        m = self.max_pages
        if m is not None and (isinstance(m, bool) or not isinstance(m, int) or not 1 <= m < 2**32):
            raise StoreError(f"store option max_pages must be an int in [1, 2**32), got {m!r}")

    @classmethod
    def from_query(cls, query: str) -> StoreOptions:
        """Parse a URL query ``busy_timeout_s=2&max_pages=1000``; StoreError names a bad or unknown key."""
        values: dict[str, float | int] = {}
        for part in query.split("&") if query else ():
            key, _, text = (unquote(x) for x in part.partition("="))
            try:
                if key == "busy_timeout_s":
                    values[key] = float(text)
                elif key == "max_pages":
                    values[key] = int(text)
                else:
                    raise StoreError(
                        f"unknown store option {key!r:.40}: expected busy_timeout_s or max_pages"
                    )
            except ValueError as exc:
                raise StoreError(f"store option {key} must be a number, got {text!r:.40}") from exc
        return cls(**values)  # type: ignore[arg-type]  # keys checked above


STORE_DB: Final = sqlitedb.SqliteKind(
    "keyframe store", APPLICATION_ID, MIGRATIONS, StoreError, BUSY_TIMEOUT_S
)



class SqliteMapStore(sqlitedb.GuardedAccess, SqlMapStore):
    """The SQLite map store: implements :class:`~wardmap.server.store.protocol.MapStore`.
    Create with :func:`~wardmap.server.store.open_store` or :meth:`open`. The queries it shares
    with the PostgreSQL store are in :class:`~wardmap.server.store.sqlbase.SqlMapStore`.

    Thread safe with one connection per thread; see the module docstring.
    """

    _DB_LABEL = "keyframe store"
    _DB_ERROR = StoreError
    dialect: Dialect = "sqlite"
    _IN_IDS = "IN (SELECT value FROM json_each(?))"
    """A list of ids as one JSON parameter (no limit on the number of SQL variables)."""

    def __init__(self, path: Path, options: StoreOptions | None = None) -> None:
        """Internal: use :meth:`open`."""
        self.path = path
        self.options = options or StoreOptions()
        self._kind = dataclasses.replace(STORE_DB, busy_timeout_s=self.options.busy_timeout_s)
        self._health_lock = threading.Lock()  # guards the two fields below
        # what -> (why its last write failed as unavailable, whether a passing probe clears it)
        self._write_faults: dict[str, tuple[str, bool]] = {}
        self._damage: str | None = None  # first damage seen; sticky until the file is repaired
        self._local = threading.local()
        self._conns: list[tuple[threading.Thread, sqlite3.Connection]] = []
        self._conns_lock = threading.Lock()
        self._closed = False

    # ------------------------------------------------------------------ life cycle

    @classmethod
    def open(cls, path: str | Path, options: StoreOptions | None = None) -> SqliteMapStore:
        """Open (or create) the store file at ``path``; its parent folder is created.

        Raises:
            StoreError: the path is unwritable or a directory, the file is not a wardmap
                keyframe store or is corrupt, or it was written by a newer wardmap.
        """
        path = Path(path)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StoreError(f"cannot create the store folder {path.parent}: {exc}") from exc
        store = cls(path, options)
        try:
            conn = store._connection()  # this thread's connection; checks and migrates the file
            sqlitedb.check_and_migrate(conn, path, store._kind)
        except BaseException:
            store.close()
            raise
        log.info("keyframe store %s open", path)
        return store

    def close(self) -> None:
        """Close every connection (idempotent). Every committed insert stays on disk."""
        with self._conns_lock:
            if self._closed:
                return
            self._closed = True
            conns, self._conns = self._conns, []
        for _, conn in conns:
            conn.close()

    # ------------------------------------------------------------------ readiness

    def writable(self) -> tuple[bool, str]:
        """Whether a write can commit now: ``(True, "ok")`` or ``(False, why)``.

        Not writable when: the store is closed; damage was seen (sticky: a damaged file does
        not heal; :data:`REPAIR_HINT`); a probe transaction on this thread's connection fails
        (``BEGIN IMMEDIATE``, a one-row insert, ``ROLLBACK``: catches a write lock held by
        another process past :data:`PROBE_BUSY_TIMEOUT_S`, a read-only or vanished file, I/O
        errors); the file is at its ``max_pages`` cap or its disk has no free space; or the
        last write of some kind (``insert``, ``count_rejection``, a ``writing(what)`` block)
        failed as :class:`StoreUnavailableError` and no write of that kind succeeded since (a
        rolled-back probe never needs new space, so only a real write finds a disk too full
        for a keyframe; a small write that fits must not hide it), unless that failure was only
        a lock (busy/locked), which a passing probe clears. Never raises. Thread safe
        (not from inside a transaction of the same thread); may take up to
        :data:`PROBE_BUSY_TIMEOUT_S` while another connection holds the write lock.
        """
        with self._health_lock:
            damage = self._damage
        if self._closed:
            return False, "closed"
        if damage is not None:
            return False, f"damaged: {damage}"
        try:
            conn = self._connection()
        except StoreError as exc:
            return False, str(exc)
        probe_ms = int(min(self.options.busy_timeout_s, PROBE_BUSY_TIMEOUT_S) * 1000)
        try:
            with self._db_errors("readiness probe"):
                conn.execute(f"PRAGMA busy_timeout = {probe_ms}")
                try:
                    conn.execute("BEGIN IMMEDIATE")
                    try:
                        conn.execute(
                            "INSERT INTO rejections (reason, count) VALUES ('readiness probe', 0) "
                            "ON CONFLICT (reason) DO NOTHING"
                        )
                    finally:
                        if conn.in_transaction:
                            conn.execute("ROLLBACK")
                    full = self._space_left_pages(conn) <= 0
                finally:
                    conn.execute(f"PRAGMA busy_timeout = {int(self.options.busy_timeout_s * 1000)}")
        except StoreError as exc:
            return False, str(exc)
        if full:
            return False, f"keyframe store {self.path}: no space left (disk or max_pages cap full)"
        with self._health_lock:
            # The probe took the write lock: a failure that was only a lock is over.
            self._write_faults = {w: f for w, f in self._write_faults.items() if not f[1]}
            faults = sorted(why for why, _ in self._write_faults.values())
        if faults:
            return False, f"last write failed: {faults[0]}"
        return True, "ok"

    def writer_lease(self, holder: str) -> SoleLease:
        """The writer lease of a store only one server uses: always granted (see :class:`SoleLease`)."""
        return SoleLease(check_lease_holder(holder), self)

    def _space_left_pages(self, conn: sqlite3.Connection) -> int:
        """Free pages the file may still use: under ``max_page_count`` and on its disk."""
        page_size, pages, free, cap = (
            int(conn.execute(f"PRAGMA {p}").fetchone()[0])
            for p in ("page_size", "page_count", "freelist_count", "max_page_count")
        )
        try:
            disk = shutil.disk_usage(self.path.parent).free // page_size
        except OSError:
            disk = 0
        return free + min(cap - pages, disk)

    # ------------------------------------------------------------------ objects

    # ------------------------------------------------------------------ the mapping stage

    # ------------------------------------------------------------------ the back-end's pose graph

    # ------------------------------------------------------------------ internals

    # ------------------------------------------------------------------ dialect hooks (sqlbase.py)

    def _ids(self, ids: Sequence[int]) -> object:
        return json.dumps([int(i) for i in ids])

    @contextmanager
    def _snapshot(self, what: str) -> Iterator[sqlite3.Connection]:
        with self._read(what) as conn:
            conn.execute("BEGIN")  # a deferred read transaction: one snapshot until COMMIT
            try:
                yield conn
            finally:
                conn.execute("COMMIT")

    def _schema_version(self, conn: sqlite3.Connection) -> int:
        return int(conn.execute("PRAGMA user_version").fetchone()[0])

    def _index_objects(self, conn: sqlite3.Connection, rows: Sequence[dict[str, Any]]) -> None:
        conn.executemany(
            "INSERT OR REPLACE INTO objects_rtree (object_id, min_x, max_x, min_y, max_y, min_z, max_z) "
            "VALUES (:object_id, :min_x, :max_x, :min_y, :max_y, :min_z, :max_z)",
            rows,
        )

    def _unindex_object(self, conn: sqlite3.Connection, object_id: int) -> None:
        conn.execute("DELETE FROM objects_rtree WHERE object_id = ?", (object_id,))

    # ------------------------------------------------------------------ error classification

    @contextmanager
    def _db_errors(self, what: str) -> Iterator[None]:
        """SQLite errors become :class:`StoreUnavailableError`, :class:`StoreDamagedError` (logged once,
        with :data:`REPAIR_HINT`) or :class:`StoreError`, naming the file and ``what`` failed."""
        try:
            yield
        except sqlite3.Error as exc:
            self._raise_classified(what, exc)

    def _raise_classified(self, what: str, exc: sqlite3.Error) -> NoReturn:
        kind = classify_sqlite_error(exc)
        detail = f"keyframe store {self.path}: {what} failed: {exc}"
        if kind is StoreDamagedError:
            if self._first_damage(detail):
                log.error("%s: the database file is damaged; %s", detail, REPAIR_HINT)
            raise StoreDamagedError(f"{detail}: the database file is damaged; {REPAIR_HINT}") from exc
        raise kind(detail) from exc

    @contextmanager
    def _write(self, what: str) -> Iterator[sqlite3.Connection]:
        """One ``BEGIN IMMEDIATE`` .. ``COMMIT`` transaction; its outcome feeds :meth:`writable`."""
        try:
            with super()._write(what) as conn:
                yield conn
        except StoreUnavailableError as exc:
            code = getattr(exc.__cause__, "sqlite_errorcode", 0)
            lock_only = isinstance(code, int) and code & 0xFF in (sqlite3.SQLITE_BUSY, sqlite3.SQLITE_LOCKED)
            with self._health_lock:
                self._write_faults[what] = (str(exc), lock_only)
            raise
        with self._health_lock:
            self._write_faults.pop(what, None)

    def _connection(self) -> sqlite3.Connection:
        """This thread's connection, opened on first use."""
        if self._closed:
            raise StoreError(f"keyframe store {self.path} is closed")
        conn: sqlite3.Connection | None = getattr(self._local, "conn", None)
        if conn is not None:
            return conn
        conn = sqlitedb.connect(self.path, self._kind)
        if self.options.max_pages is not None:
            try:
                conn.execute(f"PRAGMA max_page_count = {int(self.options.max_pages)}")
            except sqlite3.Error as exc:
                conn.close()
                raise StoreError(f"keyframe store {self.path}: cannot set max_pages: {exc}") from exc
        with self._conns_lock:
            if self._closed:
                conn.close()
                raise StoreError(f"keyframe store {self.path} is closed")
            # Connections of ended threads can never be used again: close them now.
            alive = []
            for thread, old in self._conns:
                if thread.is_alive():
                    alive.append((thread, old))
                else:
                    old.close()
            alive.append((threading.current_thread(), conn))
            self._conns = alive
        self._local.conn = conn
        return conn


class SoleLease:
    """The writer lease of an SQLite store (:class:`~wardmap.server.store.protocol.WriterLease`):
    one server owns the file, so the lease is granted at once (taking the writer fence, as on
    PostgreSQL) and held until released or the store is closed."""

    def __init__(self, holder: str, store: SqliteMapStore) -> None:
        self.holder = holder
        self._store = store
        self._held = False

    def acquire(self) -> bool:
        if not self._held and not self._store._closed:
            try:
                self._store.take_writer_fence()
            except StoreError as exc:  # acquire never raises: not granted now
                log.warning("writer lease: cannot take the writer fence: %s", exc)
                return False
            self._held = True
        return self.held()

    def held(self) -> bool:
        return self._held and not self._store._closed

    def current_holder(self) -> str | None:
        return self.holder if self.held() else None

    def release(self) -> None:
        self._held = False

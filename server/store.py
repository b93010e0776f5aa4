"""The map server's persistent keyframe store.

Ingest calls :meth:`KeyframeStore.insert` for every decoded keyframe and acks the robot
only after it returned; the REST API reads through the query methods. :class:`KeyframeStore`
is the Protocol every backend implements; :class:`SqliteKeyframeStore` (stdlib ``sqlite3``)
is the embedded default and a PostgreSQL backend will sit behind the same Protocol.
Choose one with :func:`open_store` and a URL.

Guarantees (SQLite backend):

- An :meth:`~SqliteKeyframeStore.insert` that returned is committed in WAL mode with
  ``synchronous=FULL``: it survives a crash of the process and a power loss, so acking
  after it returns never acks a keyframe that could be lost.
- Idempotent on ``(robot_id, session_id, seq)``: a key already stored returns
  ``"duplicate"`` and changes nothing (see :meth:`~SqliteKeyframeStore.insert` for why the
  first copy wins even when the bytes differ).
- Keyframes are never deleted or rewritten (object-map rows on the same file are: see
  `server/objectmap.py`).

Failures: a SQLite error becomes :class:`StoreUnavailableError` when the store cannot write
*now* (disk or ``max_pages`` cap full, locked past the busy timeout, I/O error, read-only),
:class:`StoreDamagedError` when the file is damaged (logged once with :data:`REPAIR_HINT`), or
a plain :class:`StoreError`; none of them means the keyframe was bad. :meth:`~SqliteKeyframeStore.writable`
is the readiness probe. Options (busy timeout, page cap) come from the URL's query
(:class:`StoreOptions`).

Threads: one SQLite connection per thread (``threading.local``), opened on the thread's
first call, so the ingest thread writes while HTTP threads read concurrently (WAL lets
readers proceed during a write; each read sees the last committed state). Writers are
serialised by SQLite (``BEGIN IMMEDIATE`` with a busy timeout). Connections of threads that
have ended are closed when the next thread opens one; :meth:`~SqliteKeyframeStore.close`
closes them all and must be called after the other threads stopped using the store.
Several processes may open the same file (e.g. a CLI reading while the server runs); the
file must be on a local disk (WAL needs shared memory).

Storage: ``PRAGMA application_id`` marks the file as a wardmap keyframe store and
``PRAGMA user_version`` holds the schema version; :data:`MIGRATIONS` are applied in order,
inside one transaction, when an older file (including a new, empty one) is opened. A file
from a newer wardmap is refused with "upgrade wardmap". Clock values ending in ``_s``
(``received_s``, ``first_seen_s``, ...) are the server's wall-clock seconds
(``time.time()``) when a keyframe was received; ``stamp`` is the robot's capture time.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import shutil
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Final, Literal, NoReturn, Protocol, TypeAlias
from urllib.parse import unquote

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.shared import sqlitedb
from wardmap.shared.errors import WardmapError
from wardmap.shared.wire import KeyframeMsg

log = logging.getLogger(__name__)

APPLICATION_ID: Final = 0x77726D73  # "wrms": marks the SQLite file as a wardmap keyframe store
BUSY_TIMEOUT_S: Final = 10.0
MAX_PAGE: Final = 1000
"""Largest ``limit`` :meth:`KeyframeStore.keyframes` accepts."""
MAX_REASON_LEN: Final = 200
"""Longest rejection reason, in characters."""
SQLITE_SCHEME: Final = "sqlite:///"
_POSE_DTYPE: Final = np.dtype("<f8")
_POSE_BYTES: Final = 16 * 8


def pose_blob(T: ArrayLike) -> bytes:
    """A (4, 4) pose as this file's tables store it: 16 little-endian float64, row-major."""
    return np.ascontiguousarray(T, dtype=_POSE_DTYPE).tobytes()


def pose_from_blob(blob: bytes) -> NDArray[np.float64]:
    """Inverse of :func:`pose_blob`: a read-only (4, 4) float64 array."""
    T = np.frombuffer(bytes(blob), dtype=_POSE_DTYPE).astype(np.float64).reshape(4, 4)
    T.flags.writeable = False
    return T

"""SQL statements that take the schema from version ``i`` to ``i + 1`` (``MIGRATIONS[i]``)."""

MIGRATIONS: Final[tuple[sqlitedb.Migration, ...]] = (
    # v1: robots, sessions, keyframes, rejection counters.
    (
        """CREATE TABLE robots (
            robot_id TEXT PRIMARY KEY,
            first_seen_s REAL NOT NULL,
            last_seen_s REAL NOT NULL)""",
        """CREATE TABLE sessions (
            robot_id TEXT NOT NULL,
            session_id TEXT NOT NULL,
            started_s REAL NOT NULL,
            PRIMARY KEY (robot_id, session_id))""",
        # payload last: reading the small columns never walks the blob's overflow pages.
        # T_odom_camera: 16 little-endian float64, row-major (128 bytes).
        """CREATE TABLE keyframes (
            robot_id TEXT NOT NULL,
            session_id TEXT NOT NULL,
            seq INTEGER NOT NULL,
            stamp REAL NOT NULL,
            received_s REAL NOT NULL,
            pose_source TEXT NOT NULL,
            payload_bytes INTEGER NOT NULL,
            T_odom_camera BLOB NOT NULL CHECK (length(T_odom_camera) = 128),
            payload BLOB NOT NULL,
            PRIMARY KEY (robot_id, session_id, seq))""",
        # The page and trajectory order (stamp, session_id, seq) per robot.
        "CREATE INDEX keyframes_robot_stamp ON keyframes (robot_id, stamp, session_id, seq)",
        "CREATE TABLE rejections (reason TEXT PRIMARY KEY, count INTEGER NOT NULL)",
    ),
    # v2: the object map (server/objectmap.py). Poses are 16 little-endian float64, row-major.
    (
        """CREATE TABLE objects (
            object_id INTEGER PRIMARY KEY,
            category TEXT NOT NULL,
            confidence REAL NOT NULL CHECK (confidence >= 0 AND confidence <= 1),
            T_world_object BLOB NOT NULL CHECK (length(T_world_object) = 128),
            x REAL NOT NULL, y REAL NOT NULL, z REAL NOT NULL, yaw REAL NOT NULL,
            qx REAL NOT NULL, qy REAL NOT NULL, qz REAL NOT NULL, qw REAL NOT NULL,
            size_x REAL NOT NULL, size_y REAL NOT NULL, size_z REAL NOT NULL,
            min_x REAL NOT NULL, min_y REAL NOT NULL, min_z REAL NOT NULL,
            max_x REAL NOT NULL, max_y REAL NOT NULL, max_z REAL NOT NULL,
            color_r REAL, color_g REAL, color_b REAL,
            n_observations INTEGER NOT NULL,
            first_seen_s REAL NOT NULL,
            last_seen_s REAL NOT NULL)""",
        # Rows of one category come out in object_id (rowid) order, the default result order.
        "CREATE INDEX objects_category ON objects (category)",
        """CREATE TABLE object_robots (
            object_id INTEGER NOT NULL,
            robot_id TEXT NOT NULL,
            PRIMARY KEY (object_id, robot_id)) WITHOUT ROWID""",
        "CREATE INDEX object_robots_robot ON object_robots (robot_id, object_id)",
        # One row per measurement of an object in a keyframe, keyed by keyframe and box.
        """CREATE TABLE observations (
            observation_id INTEGER PRIMARY KEY,
            object_id INTEGER NOT NULL,
            robot_id TEXT NOT NULL,
            session_id TEXT NOT NULL,
            seq INTEGER NOT NULL,
            stamp REAL NOT NULL,
            added_s REAL NOT NULL,
            category TEXT NOT NULL,
            confidence REAL NOT NULL,
            box_x1 REAL NOT NULL, box_y1 REAL NOT NULL, box_x2 REAL NOT NULL, box_y2 REAL NOT NULL,
            T_world_object BLOB NOT NULL CHECK (length(T_world_object) = 128),
            size_x REAL NOT NULL, size_y REAL NOT NULL, size_z REAL NOT NULL,
            UNIQUE (robot_id, session_id, seq, box_x1, box_y1, box_x2, box_y2))""",
        "CREATE INDEX observations_object ON observations (object_id, added_s)",
        # Axis-aligned world bounds of each object (float32, rounded outwards by SQLite).
        "CREATE VIRTUAL TABLE objects_rtree USING rtree(object_id, min_x, max_x, min_y, max_y, min_z, max_z)",
    ),
    # v3: the mapping stage (server/pipeline.py): object measurements per keyframe and how far
    # the stage got (the keyframes' rowid, i.e. insertion order).
    (
        """CREATE TABLE measurements (
            measurement_id INTEGER PRIMARY KEY,
            robot_id TEXT NOT NULL,
            session_id TEXT NOT NULL,
            seq INTEGER NOT NULL,
            anchored INTEGER NOT NULL,
            payload BLOB NOT NULL)""",
        "CREATE INDEX measurements_keyframe ON measurements (robot_id, session_id, seq)",
        "CREATE TABLE pipeline_cursor (name TEXT PRIMARY KEY, last_rowid INTEGER NOT NULL)",
    ),
    # v4: what association needs of each keyframe the mapping stage has processed, so a restart
    # replays without reading keyframe payloads. T_map_camera is NULL for a keyframe that is not
    # on the map (unanchored session, undecodable payload); camera is the colour camera as JSON.
    (
        """CREATE TABLE mapped_keyframes (
            robot_id TEXT NOT NULL,
            session_id TEXT NOT NULL,
            seq INTEGER NOT NULL,
            T_map_camera BLOB CHECK (T_map_camera IS NULL OR length(T_map_camera) = 128),
            camera TEXT,
            PRIMARY KEY (robot_id, session_id, seq)) WITHOUT ROWID""",
    ),
    # v5: sessions whose last, incomplete keyframe group the mapping stage associated because
    # no keyframe came for a while (pipeline.close_idle_s), with the stage's cursor at that
    # moment, so a restart replays the closure at the same point.
    (
        """CREATE TABLE closed_sessions (
            robot_id TEXT NOT NULL,
            session_id TEXT NOT NULL,
            at_rowid INTEGER NOT NULL,
            PRIMARY KEY (at_rowid, robot_id, session_id)) WITHOUT ROWID""",
    ),
    # v6: the mapping stage's association state at a settled cursor (pickled; one row), so a
    # restart replays only the keyframes after it (server/pipeline.py, "Restart").
    (
        """CREATE TABLE association_checkpoint (
            id INTEGER PRIMARY KEY CHECK (id = 1),
            last_rowid INTEGER NOT NULL,
            config_key TEXT NOT NULL,
            state BLOB NOT NULL,
            written_s REAL NOT NULL)""",
    ),
    # v7: objects association has not confirmed (AssociationConfig.confirm_classes: seen only as
    # flat slivers at the side of the view); the map's queries leave them out by default.
    (
        "ALTER TABLE objects ADD COLUMN confirmed INTEGER NOT NULL DEFAULT 1 CHECK (confirmed IN (0, 1))",
    ),
)

InsertResult: TypeAlias = Literal["stored", "duplicate"]
KeyCursor: TypeAlias = tuple[str, int]
"""``(session_id, seq)`` of a keyframe of the queried robot: the page starts after it."""
Cursor: TypeAlias = KeyCursor | float
"""A :data:`KeyCursor`, or a stamp in seconds: the page starts at the first stamp above it."""


class StoreError(WardmapError):
    """The keyframe store cannot be opened or used (bad URL, bad file, bad argument, I/O failure)."""


class StoreUnavailableError(StoreError):
    """The store cannot write (or read) *now*: the disk or the file's page cap is full, another
    process holds the database's write lock past the busy timeout, an I/O error, a read-only
    file. Nothing is wrong with the data asked to be stored: try again later (ingest acks
    ``retry``; HTTP answers 503)."""


class StoreDamagedError(StoreError):
    """The database file is damaged (malformed page, corrupt index, not a database). It will not
    heal by itself: the message says how to repair it (:data:`REPAIR_HINT`); ingest acks
    ``retry`` so robots keep their keyframes until it is repaired; HTTP answers 503."""


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
"""Longest :meth:`SqliteKeyframeStore.writable` waits for another writer's lock."""


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


@dataclass(frozen=True, slots=True)
class RobotSummary:
    """One robot as the store knows it.

    Attributes:
        robot_id: the robot.
        keyframes: keyframes stored for it (all sessions).
        sessions: sessions with at least one stored keyframe.
        first_seen_s, last_seen_s: server wall-clock seconds of its first and last stored
            keyframe (duplicates do not count).
    """

    robot_id: str
    keyframes: int
    sessions: int
    first_seen_s: float
    last_seen_s: float


@dataclass(frozen=True, slots=True)
class KeyframeRow:
    """A stored keyframe's index entry (fetch the bytes with :meth:`KeyframeStore.payload`).

    Attributes:
        robot_id, session_id, seq: the key.
        stamp: capture time, robot clock, seconds since the Unix epoch.
        received_s: server wall-clock seconds when it was stored.
        pose_source: the message's ``pose_source``.
        payload_bytes: size of the stored wire message.
    """

    robot_id: str
    session_id: str
    seq: int
    stamp: float
    received_s: float
    pose_source: str
    payload_bytes: int


@dataclass(frozen=True, slots=True)
class KeyframePage:
    """One page of :meth:`KeyframeStore.keyframes`.

    Attributes:
        rows: up to ``limit`` rows ordered by ``(stamp, session_id, seq)``.
        next_cursor: pass as ``after`` for the next page; None when this page is the last.
    """

    rows: list[KeyframeRow]
    next_cursor: KeyCursor | None


@dataclass(frozen=True, slots=True)
class StoreStats:
    """Totals over the whole store.

    Attributes:
        robots, sessions, keyframes: row counts.
        payload_bytes: total size of the stored wire messages.
        rejections: sum of all rejection counters.
        schema_version: the file's ``user_version``.
    """

    robots: int
    sessions: int
    keyframes: int
    payload_bytes: int
    rejections: int
    schema_version: int


Trajectory: TypeAlias = tuple[NDArray[np.float64], NDArray[np.float64]]
"""``(stamps (N,) seconds, T_odom_camera (N, 4, 4))``."""


class KeyframeStore(Protocol):
    """What the server needs from a keyframe store; see the module docstring for the contract."""

    def insert(self, msg: KeyframeMsg, payload: bytes, received_s: float) -> InsertResult:
        """Store ``msg`` (encoded as ``payload``) durably; see :meth:`SqliteKeyframeStore.insert`."""
        ...

    def count_rejection(self, reason: str, n: int = 1) -> None:
        """Add ``n`` to the counter of ``reason``, all or nothing."""
        ...

    def writable(self) -> tuple[bool, str]:
        """Whether a write can commit now: ``(True, "ok")`` or ``(False, why)``."""
        ...

    def rejections(self) -> dict[str, int]:
        """Every rejection reason with its count."""
        ...

    def robots(self) -> list[RobotSummary]:
        """Every robot with at least one keyframe, by ``robot_id``."""
        ...

    def keyframes(self, robot_id: str, *, after: Cursor | None = None, limit: int = 100) -> KeyframePage:
        """One page of a robot's keyframes by ``(stamp, session_id, seq)``."""
        ...

    def trajectory(self, robot_id: str, session_id: str | None = None) -> Trajectory:
        """Stamps and camera poses of a robot's keyframes ordered by stamp."""
        ...

    def payload(self, robot_id: str, session_id: str, seq: int) -> bytes | None:
        """The stored wire bytes of one keyframe, None if absent."""
        ...

    def stats(self) -> StoreStats:
        """Totals over the whole store."""
        ...

    def close(self) -> None:
        """Release the store (idempotent)."""
        ...


def open_store(url: str) -> SqliteKeyframeStore:
    """Open (or create) the keyframe store that ``url`` names.

    Args:
        url: ``sqlite:///PATH`` as in SQLAlchemy: ``sqlite:///map.db`` is relative to the
            working folder, ``sqlite:////var/lib/wardmap/map.db`` is absolute. The parent
            folder is created. In-memory databases are not supported (every thread opens its
            own connection). A query sets :class:`StoreOptions`:
            ``sqlite:///map.db?busy_timeout_s=2&max_pages=250000``.

    Raises:
        StoreError: an unknown or unsupported scheme, an empty path, or any failure of
            :meth:`SqliteKeyframeStore.open`.
    """
    if not isinstance(url, str):
        raise StoreError(f"store URL must be a str, got {type(url).__name__}")
    scheme = url.split(":", 1)[0] if ":" in url else ""
    if scheme in ("postgres", "postgresql") or scheme.startswith("postgresql+"):
        raise StoreError(
            f"store URL {url.split('@')[-1]!r}: the PostgreSQL store is not available yet; "
            f"use {SQLITE_SCHEME}PATH"
        )
    if not url.startswith(SQLITE_SCHEME):
        raise StoreError(
            f"unknown store URL {url!r}: expected {SQLITE_SCHEME}PATH "
            f"(e.g. {SQLITE_SCHEME}wardmap.db or {SQLITE_SCHEME}/var/lib/wardmap/map.db)"
        )
    path, _, query = url[len(SQLITE_SCHEME) :].partition("?")
    if not path:
        raise StoreError(f"store URL {url!r} has no file path: expected {SQLITE_SCHEME}PATH")
    if path == ":memory:" or path.startswith("file:"):
        raise StoreError(f"store URL {url!r}: only a plain file path is supported after {SQLITE_SCHEME}")
    return SqliteKeyframeStore.open(Path(path), StoreOptions.from_query(query))


class SqliteKeyframeStore(sqlitedb.GuardedAccess):
    """The SQLite keyframe store. Create with :func:`open_store` or :meth:`open`.

    Thread safe with one connection per thread; see the module docstring.
    """

    _DB_LABEL = "keyframe store"
    _DB_ERROR = StoreError

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
    def open(cls, path: str | Path, options: StoreOptions | None = None) -> SqliteKeyframeStore:
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

    def __enter__(self) -> SqliteKeyframeStore:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # ------------------------------------------------------------------ writes

    def insert(self, msg: KeyframeMsg, payload: bytes, received_s: float) -> InsertResult:
        """Store one keyframe in one transaction, committed before this returns.

        Args:
            msg: the decoded, validated message.
            payload: its wire bytes as received (stored verbatim; not re-checked against ``msg``).
            received_s: server wall-clock seconds of its arrival.

        Returns:
            ``"stored"``, or ``"duplicate"`` when ``(robot_id, session_id, seq)`` is already
            stored; then nothing changes. If the stored bytes differ from ``payload`` a
            warning is logged and the first copy is kept anyway: it may already have been
            acked and consumed by perception and the map, so replacing it would silently
            rewrite history that others built on; the edge outbox never sends two payloads
            under one key, so different bytes mean a robot bug (e.g. a reused session id)
            that an operator should see, not data to trust over the first copy. Answering
            ``"duplicate"`` (rather than rejecting) lets the robot drop it from its outbox.

        Raises:
            StoreUnavailableError: the database cannot write now (full, locked past the busy timeout,
                I/O error, read-only); nothing was stored, the same call may succeed later.
            StoreDamagedError: the file is damaged (e.g. a corrupt index page); nothing was stored.
            StoreError: bad arguments or another database failure (nothing was stored).
        """
        if not isinstance(msg, KeyframeMsg):
            raise StoreError(f"msg must be a KeyframeMsg, got {type(msg).__name__}")
        if not isinstance(payload, bytes | bytearray | memoryview):
            raise StoreError(f"payload must be bytes, got {type(payload).__name__}")
        data = bytes(payload)
        if not data:
            raise StoreError("payload is empty")
        t = _check_seconds(received_s, "received_s")
        key = (msg.robot_id, msg.session_id, int(msg.seq))
        pose = pose_blob(msg.T_odom_camera)
        with self._write("insert") as conn:
            cur = conn.execute(
                "INSERT INTO keyframes (robot_id, session_id, seq, stamp, received_s, pose_source, "
                "payload_bytes, T_odom_camera, payload) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?) "
                "ON CONFLICT (robot_id, session_id, seq) DO NOTHING",
                (*key, float(msg.stamp), t, str(msg.pose_source), len(data), pose, data),
            )
            if cur.rowcount == 0:
                (same,) = conn.execute(
                    "SELECT payload = ? FROM keyframes WHERE robot_id = ? AND session_id = ? AND seq = ?",
                    (data, *key),
                ).fetchone()
                if not same:
                    log.warning(
                        "keyframe %s/%s/%d arrived again with different bytes (%d bytes); "
                        "keeping the first copy",
                        *key,
                        len(data),
                    )
                return "duplicate"
            conn.execute(
                "INSERT INTO robots (robot_id, first_seen_s, last_seen_s) VALUES (?, ?, ?) "
                "ON CONFLICT (robot_id) DO UPDATE SET "
                "first_seen_s = min(first_seen_s, excluded.first_seen_s), "
                "last_seen_s = max(last_seen_s, excluded.last_seen_s)",
                (msg.robot_id, t, t),
            )
            conn.execute(
                "INSERT INTO sessions (robot_id, session_id, started_s) VALUES (?, ?, ?) "
                "ON CONFLICT (robot_id, session_id) DO UPDATE SET "
                "started_s = min(started_s, excluded.started_s)",
                (msg.robot_id, msg.session_id, t),
            )
        return "stored"

    def count_rejection(self, reason: str, n: int = 1) -> None:
        """Add ``n`` to the counter of ``reason`` in one transaction (committed before returning,
        or not at all: a caller that keeps counts while the store cannot write adds them later,
        once, with ``n``).

        Reasons should come from a small fixed set (e.g. the failing wire field), never
        from free text of a message, so the table stays small.

        Raises:
            StoreUnavailableError, StoreDamagedError: as for :meth:`insert` (nothing was added).
            StoreError: ``reason`` is not a 1-200 character str, ``n`` is not an int >= 1, or
                another database failure.
        """
        if not isinstance(reason, str) or not 0 < len(reason) <= MAX_REASON_LEN:
            raise StoreError(f"reason must be a str of 1-{MAX_REASON_LEN} characters, got {reason!r:.80}")
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n < 2**62:
            raise StoreError(f"n must be an int >= 1, got {n!r:.40}")
        with self._write("count_rejection") as conn:
            conn.execute(
                "INSERT INTO rejections (reason, count) VALUES (?, ?) "
                "ON CONFLICT (reason) DO UPDATE SET count = count + excluded.count",
                (reason, n),
            )

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

    # ------------------------------------------------------------------ reads

    def rejections(self) -> dict[str, int]:
        """Every rejection reason with its count, by reason."""
        with self._read("rejections") as conn:
            rows = conn.execute("SELECT reason, count FROM rejections ORDER BY reason").fetchall()
        return {str(r[0]): int(r[1]) for r in rows}

    def robots(self) -> list[RobotSummary]:
        """Every robot with at least one stored keyframe, ordered by ``robot_id``."""
        with self._read("robots") as conn:
            rows = conn.execute(
                "SELECT r.robot_id, "
                "(SELECT COUNT(*) FROM keyframes AS k WHERE k.robot_id = r.robot_id), "
                "(SELECT COUNT(*) FROM sessions AS s WHERE s.robot_id = r.robot_id), "
                "r.first_seen_s, r.last_seen_s FROM robots AS r ORDER BY r.robot_id"
            ).fetchall()
        return [RobotSummary(str(r[0]), int(r[1]), int(r[2]), float(r[3]), float(r[4])) for r in rows]

    def keyframes(self, robot_id: str, *, after: Cursor | None = None, limit: int = 100) -> KeyframePage:
        """One page of ``robot_id``'s keyframes in the stable order ``(stamp, session_id, seq)``.

        Args:
            robot_id: the robot (an unknown one gives an empty page).
            after: None for the first page; a page's ``next_cursor`` ``(session_id, seq)`` for
                the following one; or a stamp in seconds to start after that time. Rows
                stored later with a stamp before the cursor are not revisited.
            limit: page size, 1 to :data:`MAX_PAGE`.

        Raises:
            StoreError: bad arguments, a ``(session_id, seq)`` cursor that names no keyframe
                of this robot, or a database failure.
        """
        _check_str(robot_id, "robot_id")
        if isinstance(limit, bool) or not isinstance(limit, int) or not 1 <= limit <= MAX_PAGE:
            raise StoreError(f"limit must be an int in [1, {MAX_PAGE}], got {limit!r}")
        columns = "robot_id, session_id, seq, stamp, received_s, pose_source, payload_bytes"
        with self._read("keyframes") as conn:
            if after is None:
                rows = conn.execute(
                    f"SELECT {columns} FROM keyframes WHERE robot_id = ? "
                    "ORDER BY stamp, session_id, seq LIMIT ?",
                    (robot_id, limit + 1),
                ).fetchall()
            else:
                params: tuple[float | str | int, ...]
                if isinstance(after, tuple):
                    stamp, session_id, seq = self._cursor_position(conn, robot_id, after)
                    where, params = "(stamp, session_id, seq) > (?, ?, ?)", (stamp, session_id, seq)
                else:
                    where, params = "stamp > ?", (_check_seconds(after, "after", positive=False),)
                rows = conn.execute(
                    f"SELECT {columns} FROM keyframes WHERE robot_id = ? AND {where} "
                    "ORDER BY stamp, session_id, seq LIMIT ?",
                    (robot_id, *params, limit + 1),
                ).fetchall()
        page = [
            KeyframeRow(str(r[0]), str(r[1]), int(r[2]), float(r[3]), float(r[4]), str(r[5]), int(r[6]))
            for r in rows[:limit]
        ]
        more = len(rows) > limit
        return KeyframePage(page, (page[-1].session_id, page[-1].seq) if more else None)

    def trajectory(self, robot_id: str, session_id: str | None = None) -> Trajectory:
        """Stamps and camera poses of ``robot_id``'s keyframes, ordered by ``(stamp, session_id, seq)``.

        Args:
            robot_id: the robot (unknown: empty arrays).
            session_id: only this session; None for all. Poses of different sessions are in
                different ``odom`` frames, so mixing them is only meaningful per session.

        Returns:
            ``(stamps, T_odom_camera)``: float64 (N,) seconds and float64 (N, 4, 4).
        """
        _check_str(robot_id, "robot_id")
        with self._read("trajectory") as conn:
            if session_id is None:
                rows = conn.execute(
                    "SELECT stamp, T_odom_camera FROM keyframes WHERE robot_id = ? "
                    "ORDER BY stamp, session_id, seq",
                    (robot_id,),
                ).fetchall()
            else:
                _check_str(session_id, "session_id")
                rows = conn.execute(
                    "SELECT stamp, T_odom_camera FROM keyframes WHERE robot_id = ? AND session_id = ? "
                    "ORDER BY stamp, seq",
                    (robot_id, session_id),
                ).fetchall()
        stamps = np.array([float(r[0]) for r in rows], dtype=np.float64)
        poses = np.frombuffer(b"".join(bytes(r[1]) for r in rows), dtype=_POSE_DTYPE)
        return stamps, poses.astype(np.float64).reshape(len(rows), 4, 4)

    def payload(self, robot_id: str, session_id: str, seq: int) -> bytes | None:
        """The stored wire bytes of one keyframe (the first copy received), None if absent."""
        _check_str(robot_id, "robot_id")
        _check_str(session_id, "session_id")
        _check_seq(seq)
        with self._read("payload") as conn:
            row = conn.execute(
                "SELECT payload FROM keyframes WHERE robot_id = ? AND session_id = ? AND seq = ?",
                (robot_id, session_id, seq),
            ).fetchone()
        return None if row is None else bytes(row[0])

    def stats(self) -> StoreStats:
        """Totals over the whole store, from one consistent snapshot."""
        with self._read("stats") as conn:
            conn.execute("BEGIN")
            try:
                robots = conn.execute("SELECT COUNT(*) FROM robots").fetchone()[0]
                sessions = conn.execute("SELECT COUNT(*) FROM sessions").fetchone()[0]
                keyframes, nbytes = conn.execute(
                    "SELECT COUNT(*), COALESCE(SUM(payload_bytes), 0) FROM keyframes"
                ).fetchone()
                rejected = conn.execute("SELECT COALESCE(SUM(count), 0) FROM rejections").fetchone()[0]
                version = conn.execute("PRAGMA user_version").fetchone()[0]
            finally:
                conn.execute("COMMIT")
        return StoreStats(
            int(robots), int(sessions), int(keyframes), int(nbytes), int(rejected), int(version)
        )

    # ------------------------------------------------------------------ shared access

    @contextmanager
    def reading(self, what: str) -> Iterator[sqlite3.Connection]:
        """This thread's connection for reads by another component on the same file
        (the object map); SQLite errors become :class:`StoreError` naming ``what``."""
        with self._read(what) as conn:
            yield conn

    @contextmanager
    def writing(self, what: str) -> Iterator[sqlite3.Connection]:
        """One ``BEGIN IMMEDIATE`` .. ``COMMIT`` transaction on this thread's connection, for
        another component on the same file; rolled back on any exception."""
        with self._write(what) as conn:
            yield conn

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
            with self._health_lock:
                first = self._damage is None
                if first:
                    self._damage = detail
            if first:
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

    # ------------------------------------------------------------------ internals

    @staticmethod
    def _cursor_position(
        conn: sqlite3.Connection, robot_id: str, after: tuple[object, ...]
    ) -> tuple[float, str, int]:
        if len(after) != 2 or not isinstance(after[0], str):
            raise StoreError(f"cursor must be (session_id, seq) or a stamp, got {after!r:.80}")
        session_id, seq = after[0], _check_seq(after[1])
        row = conn.execute(
            "SELECT stamp FROM keyframes WHERE robot_id = ? AND session_id = ? AND seq = ?",
            (robot_id, session_id, seq),
        ).fetchone()
        if row is None:
            raise StoreError(f"cursor {after!r:.80} names no keyframe of robot {robot_id!r}")
        return float(row[0]), session_id, seq

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



# ---------------------------------------------------------------------- helpers


def _check_str(value: object, field: str) -> str:
    if not isinstance(value, str) or not value:
        raise StoreError(f"{field} must be a non-empty str, got {value!r:.80}")
    return value


def _check_seq(value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < 2**63:
        raise StoreError(f"seq must be an int in [0, 2**63), got {value!r:.80}")
    return value


def _check_seconds(value: object, field: str, *, positive: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise StoreError(f"{field} must be a number of seconds, got {value!r:.80}")
    v = float(value)
    if not math.isfinite(v) or (positive and v <= 0):
        raise StoreError(f"{field} must be a finite{' positive' if positive else ''} number, got {v}")
    return v

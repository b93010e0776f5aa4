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

import logging
import math
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Final, Literal, Protocol, TypeAlias

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

    def count_rejection(self, reason: str) -> None:
        """Add one to the counter of ``reason``."""
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
            own connection).

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
    path = url[len(SQLITE_SCHEME) :]
    if not path:
        raise StoreError(f"store URL {url!r} has no file path: expected {SQLITE_SCHEME}PATH")
    if path == ":memory:" or path.startswith("file:") or "?" in path:
        raise StoreError(f"store URL {url!r}: only a plain file path is supported after {SQLITE_SCHEME}")
    return SqliteKeyframeStore.open(Path(path))


class SqliteKeyframeStore(sqlitedb.GuardedAccess):
    """The SQLite keyframe store. Create with :func:`open_store` or :meth:`open`.

    Thread safe with one connection per thread; see the module docstring.
    """

    _DB_LABEL = "keyframe store"
    _DB_ERROR = StoreError

    def __init__(self, path: Path) -> None:
        """Internal: use :meth:`open`."""
        self.path = path
        self._local = threading.local()
        self._conns: list[tuple[threading.Thread, sqlite3.Connection]] = []
        self._conns_lock = threading.Lock()
        self._closed = False

    # ------------------------------------------------------------------ life cycle

    @classmethod
    def open(cls, path: str | Path) -> SqliteKeyframeStore:
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
        store = cls(path)
        try:
            conn = store._connection()  # this thread's connection; checks and migrates the file
            sqlitedb.check_and_migrate(conn, path, STORE_DB)
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
            StoreError: bad arguments or a database failure (nothing was stored).
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

    def count_rejection(self, reason: str) -> None:
        """Add one to the counter of ``reason`` (committed before returning).

        Reasons should come from a small fixed set (e.g. the failing wire field), never
        from free text of a message, so the table stays small.

        Raises:
            StoreError: ``reason`` is not a 1-200 character str, or a database failure.
        """
        if not isinstance(reason, str) or not 0 < len(reason) <= MAX_REASON_LEN:
            raise StoreError(f"reason must be a str of 1-{MAX_REASON_LEN} characters, got {reason!r:.80}")
        with self._write("count_rejection") as conn:
            conn.execute(
                "INSERT INTO rejections (reason, count) VALUES (?, 1) "
                "ON CONFLICT (reason) DO UPDATE SET count = count + 1",
                (reason,),
            )

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
        conn = sqlitedb.connect(self.path, STORE_DB)
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

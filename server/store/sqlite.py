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
from types import TracebackType
from typing import Any, Final, NoReturn
from urllib.parse import unquote

import numpy as np
from numpy.typing import NDArray

from wardmap.server.perception.types import ObjectMeasurement
from wardmap.server.store.codec import (
    camera_from_json,
    camera_to_json,
    pack_measurement,
    pose_blob,
    pose_from_blob,
    poses_from_blobs,
    unpack_measurement,
    without_images,
)
from wardmap.server.store.records import (
    MAX_PAGE,
    MAX_REASON_LEN,
    AnchoredKeyframe,
    Checkpoint,
    ClosedSession,
    Cursor,
    GraphChange,
    GraphEdgeRow,
    GraphNodeRow,
    InsertResult,
    KeyframeKey,
    KeyframePage,
    KeyframeRef,
    KeyframeRow,
    MappedPose,
    NodeKey,
    ObjectDetail,
    ObjectHit,
    ObjectPage,
    ObjectRecord,
    ObjectRow,
    ObjectWrite,
    Observation,
    ObservationRecord,
    RobotSummary,
    SessionAnchor,
    StoreDamagedError,
    StoredKeyframe,
    StoreError,
    StoreStats,
    StoreUnavailableError,
    TokenRecord,
    Trajectory,
    UnknownObjectError,
    Vec3,
)
from wardmap.shared import sqlitedb
from wardmap.shared.errors import WireError
from wardmap.shared.wire import KeyframeMsg

log = logging.getLogger(__name__)

APPLICATION_ID: Final = 0x77726D73  # "wrms": marks the SQLite file as a wardmap keyframe store
BUSY_TIMEOUT_S: Final = 10.0
ERASE_BATCH: Final = 64
"""Keyframes whose images :meth:`SqliteMapStore.erase_images` rewrites per transaction."""



def _graph_edges_table(name: str, kinds: tuple[str, ...]) -> str:
    """``CREATE TABLE`` of the pose graph's factors (v8; v10 widened ``kinds``)."""
    allowed = ", ".join(f"'{k}'" for k in kinds)
    return f"""CREATE TABLE {name} (
            edge_id INTEGER PRIMARY KEY,
            kind TEXT NOT NULL CHECK (kind IN ({allowed})),
            a_robot TEXT NOT NULL, a_session TEXT NOT NULL, a_seq INTEGER NOT NULL,
            b_robot TEXT, b_session TEXT, b_seq INTEGER,
            T_a_b BLOB NOT NULL CHECK (length(T_a_b) = 128),
            sigmas BLOB NOT NULL CHECK (length(sigmas) = 48),
            robust INTEGER NOT NULL CHECK (robust IN (0, 1)),
            inliers INTEGER NOT NULL)"""


# SQL statements that take the schema from version ``i`` to ``i + 1`` (``MIGRATIONS[i]``).
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
    # v3: the mapping stage (server/mapping/): object measurements per keyframe and how far
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
    # v6: the mapping stage's association state at a settled cursor (one row, in the data-only
    # format of server/association/state.py), so a restart replays only the keyframes after it
    # (server/mapping/stage.py, "Restart").
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
    # v8: the SLAM back-end (server/backend/): pose-graph nodes with their place-recognition
    # codes and latest map estimates, factors, each session's anchoring, and the graph epoch.
    (
        """CREATE TABLE graph_nodes (
            robot_id TEXT NOT NULL,
            session_id TEXT NOT NULL,
            seq INTEGER NOT NULL,
            node_order INTEGER NOT NULL UNIQUE,
            stamp REAL NOT NULL,
            pose_source TEXT NOT NULL,
            T_odom_camera BLOB NOT NULL CHECK (length(T_odom_camera) = 128),
            T_map_camera BLOB CHECK (T_map_camera IS NULL OR length(T_map_camera) = 128),
            prior BLOB CHECK (prior IS NULL OR length(prior) = 128),
            codes BLOB NOT NULL,
            PRIMARY KEY (robot_id, session_id, seq)) WITHOUT ROWID""",
        _graph_edges_table("graph_edges", ("odometry", "loop", "prior")),
        """CREATE TABLE graph_sessions (
            robot_id TEXT NOT NULL,
            session_id TEXT NOT NULL,
            T_map_odom BLOB CHECK (T_map_odom IS NULL OR length(T_map_odom) = 128),
            anchored_s REAL,
            anchored_to TEXT NOT NULL,
            revision INTEGER NOT NULL,
            PRIMARY KEY (robot_id, session_id)) WITHOUT ROWID""",
        "CREATE TABLE graph_epoch (id INTEGER PRIMARY KEY CHECK (id = 1), epoch INTEGER NOT NULL)",
    ),
    # v9: the REST API's bearer tokens; the secret only as its SHA-256 digest (server/api/auth.py).
    (
        """CREATE TABLE api_tokens (
            token_id TEXT PRIMARY KEY,
            name TEXT NOT NULL,
            scope TEXT NOT NULL CHECK (scope IN ('read', 'admin')),
            secret_sha256 BLOB NOT NULL CHECK (length(secret_sha256) = 32),
            created_s REAL NOT NULL,
            revoked_s REAL) WITHOUT ROWID""",
    ),
    # v10: ``bundle`` edges (consecutive keyframes' relative pose after a bundle adjustment);
    # SQLite cannot alter a CHECK, so the table is copied.
    (
        _graph_edges_table("graph_edges_v10", ("odometry", "loop", "prior", "bundle")),
        "INSERT INTO graph_edges_v10 SELECT * FROM graph_edges",
        "DROP TABLE graph_edges",
        "ALTER TABLE graph_edges_v10 RENAME TO graph_edges",
    ),
    # v11: erased images (retention, ``wardmap images erase``): when the payload's colour image
    # was replaced by a black one and its thermal raster dropped; NULL = images as received.
    (
        "ALTER TABLE keyframes ADD COLUMN images_erased_s REAL",
    ),
)

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



class SqliteMapStore(sqlitedb.GuardedAccess):
    """The SQLite map store: implements :class:`~wardmap.server.store.protocol.MapStore`.
    Create with :func:`~wardmap.server.store.open_store` or :meth:`open`.

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

    def __enter__(self) -> SqliteMapStore:
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
        return stamps, poses_from_blobs([r[1] for r in rows])

    def payload(self, robot_id: str, session_id: str, seq: int) -> bytes | None:
        """The stored wire bytes of one keyframe (the first copy received), None if absent."""
        value = self._keyframe_column("payload", robot_id, session_id, seq)
        return None if value is None else bytes(value)

    def images_erased_s(self, robot_id: str, session_id: str, seq: int) -> float | None:
        """When the keyframe's images were erased (server wall-clock seconds), None if they were
        not (or there is no such keyframe)."""
        value = self._keyframe_column("images_erased_s", robot_id, session_id, seq)
        return None if value is None else float(value)

    def _keyframe_column(self, column: str, robot_id: str, session_id: str, seq: int) -> Any:
        """One column (a name from this module, never from input) of one keyframe, None if absent."""
        _check_str(robot_id, "robot_id")
        _check_str(session_id, "session_id")
        _check_seq(seq)
        with self._read(column) as conn:
            row = conn.execute(
                f"SELECT {column} FROM keyframes WHERE robot_id = ? AND session_id = ? AND seq = ?",
                (robot_id, session_id, seq),
            ).fetchone()
        return None if row is None else row[0]

    def erase_images(
        self, *, now_s: float, received_before_s: float | None = None, stamp_from: float | None = None,
        stamp_to: float | None = None, robot_id: str | None = None,
    ) -> int:
        """Erase the images of the keyframes that match every given filter; how many were erased.

        Each payload is rewritten by :func:`~wardmap.server.store.codec.without_images` (black
        colour JPEG, no thermal; poses, keypoints and depth kept) and marked with ``now_s``;
        keyframes already erased are skipped. Committed in batches of :data:`ERASE_BATCH`, with
        ``secure_delete`` on, so the pages that held the images are zeroed when freed.

        Args:
            now_s: server wall-clock seconds recorded as the erasure time.
            received_before_s: keyframes the server received before this (retention).
            stamp_from, stamp_to: keyframes whose capture stamp lies in ``[from, to)`` (seconds).
            robot_id: only this robot's keyframes.

        Raises:
            StoreError: no filter, bad arguments, or a database failure (earlier batches stay erased).
        """
        t = _check_seconds(now_s, "now_s")
        where: list[str] = ["images_erased_s IS NULL"]
        params: list[float | str] = []
        if received_before_s is not None:
            where.append("received_s < ?")
            params.append(_check_seconds(received_before_s, "received_before_s"))
        if stamp_from is not None:
            where.append("stamp >= ?")
            params.append(_check_seconds(stamp_from, "stamp_from", positive=False))
        if stamp_to is not None:
            where.append("stamp < ?")
            params.append(_check_seconds(stamp_to, "stamp_to", positive=False))
        if robot_id is not None:
            where.append("robot_id = ?")
            params.append(_check_str(robot_id, "robot_id"))
        if len(where) == 1:
            raise StoreError("erase_images: give at least one filter (received_before_s, stamps, robot_id)")
        sql = (f"SELECT rowid, payload FROM keyframes WHERE {' AND '.join(where)} AND rowid > ? "
               "ORDER BY rowid LIMIT ?")
        erased, last = 0, 0
        while True:
            with self._write("erase images") as conn:
                conn.execute("PRAGMA secure_delete = ON")  # the old images' pages are zeroed when freed
                rows = conn.execute(sql, (*params, last, ERASE_BATCH)).fetchall()
                for rowid, payload in rows:
                    last = int(rowid)
                    try:
                        stripped = without_images(bytes(payload))
                    except WireError as exc:  # validated at insert: only a damaged row gets here
                        log.error("keyframe row %d cannot be decoded, its images are not erased: %s",
                                  last, exc)
                        continue
                    conn.execute("UPDATE keyframes SET payload = ?, images_erased_s = ? WHERE rowid = ?",
                                 (stripped, t, last))
                    erased += 1
            if len(rows) < ERASE_BATCH:
                return erased

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

    # ------------------------------------------------------------------ objects

    def write_objects(
        self, objects: Sequence[ObjectRow], observations: Sequence[Observation], now_s: float
    ) -> list[ObjectWrite]:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.write_objects`."""
        obj_rows = [_object_params(o, now_s) for o in objects]
        obs_rows = [_observation_params(o, now_s) for o in observations]
        ids = [o.object_id for o in objects]
        with self._write("object map upsert") as conn:
            existing = _existing(conn, ids)
            conn.executemany(
                "INSERT INTO objects (object_id, category, confidence, T_world_object, x, y, z, yaw, "
                "qx, qy, qz, qw, size_x, size_y, size_z, min_x, min_y, min_z, max_x, max_y, max_z, "
                "color_r, color_g, color_b, n_observations, first_seen_s, last_seen_s, confirmed) "
                "VALUES (:object_id, :category, :confidence, :T, :x, :y, :z, :yaw, :qx, :qy, :qz, :qw, "
                ":size_x, :size_y, :size_z, "
                ":min_x, :min_y, :min_z, :max_x, :max_y, :max_z, :color_r, :color_g, :color_b, "
                "0, :now, :now, :confirmed) "
                "ON CONFLICT (object_id) DO UPDATE SET category = excluded.category, "
                "confidence = excluded.confidence, T_world_object = excluded.T_world_object, "
                "x = excluded.x, y = excluded.y, z = excluded.z, yaw = excluded.yaw, "
                "qx = excluded.qx, qy = excluded.qy, qz = excluded.qz, qw = excluded.qw, "
                "size_x = excluded.size_x, size_y = excluded.size_y, size_z = excluded.size_z, "
                "min_x = excluded.min_x, min_y = excluded.min_y, min_z = excluded.min_z, "
                "max_x = excluded.max_x, max_y = excluded.max_y, max_z = excluded.max_z, "
                "color_r = excluded.color_r, color_g = excluded.color_g, color_b = excluded.color_b, "
                "confirmed = excluded.confirmed",
                obj_rows,
            )
            conn.executemany(
                "INSERT OR REPLACE INTO objects_rtree "
                "(object_id, min_x, max_x, min_y, max_y, min_z, max_z) "
                "VALUES (:object_id, :min_x, :max_x, :min_y, :max_y, :min_z, :max_z)",
                obj_rows,
            )
            touched: dict[int, None] = dict.fromkeys(ids)
            if obs_rows:
                missing = {int(r["object_id"]) for r in obs_rows} - set(ids)
                missing -= _existing(conn, sorted(missing))
                if missing:
                    raise UnknownObjectError(
                        "observations name objects that are neither given nor stored: "
                        f"{sorted(missing)[:10]}"
                    )
                for row in obs_rows:
                    old = conn.execute(
                        "SELECT object_id FROM observations WHERE robot_id = :robot_id AND "
                        "session_id = :session_id AND seq = :seq AND box_x1 = :box_x1 AND "
                        "box_y1 = :box_y1 AND box_x2 = :box_x2 AND box_y2 = :box_y2",
                        row,
                    ).fetchone()
                    if old is not None:
                        touched.setdefault(int(old[0]))
                    touched.setdefault(int(row["object_id"]))
                conn.executemany(
                    "INSERT INTO observations (object_id, robot_id, session_id, seq, stamp, added_s, "
                    "category, confidence, box_x1, box_y1, box_x2, box_y2, T_world_object, "
                    "size_x, size_y, size_z) VALUES (:object_id, :robot_id, :session_id, :seq, :stamp, "
                    ":now, :category, :confidence, :box_x1, :box_y1, :box_x2, :box_y2, :T, "
                    ":size_x, :size_y, :size_z) "
                    "ON CONFLICT (robot_id, session_id, seq, box_x1, box_y1, box_x2, box_y2) "
                    "DO UPDATE SET "
                    "object_id = excluded.object_id, stamp = excluded.stamp, "
                    "category = excluded.category, confidence = excluded.confidence, "
                    "T_world_object = excluded.T_world_object, size_x = excluded.size_x, "
                    "size_y = excluded.size_y, size_z = excluded.size_z",
                    obs_rows,
                )
            order = list(touched)
            _refresh_derived(conn, order)
            records = _records(conn, order)
        given = set(ids)
        return [ObjectWrite(records[oid], oid in given and oid not in existing) for oid in order]

    def delete_object(
        self, object_id: int, merged_into: int | None = None
    ) -> tuple[ObjectRecord, ObjectRecord | None]:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.delete_object`."""
        oid, target = object_id, merged_into
        with self._write("object map delete") as conn:
            before = _records(conn, [oid])
            if oid not in before:
                raise UnknownObjectError(f"unknown object {oid}")
            if target is not None and not _existing(conn, [target]):
                raise UnknownObjectError(f"unknown object {target} (merged_into)")
            if target is None:
                conn.execute("DELETE FROM observations WHERE object_id = ?", (oid,))
            else:
                conn.execute("UPDATE observations SET object_id = ? WHERE object_id = ?", (target, oid))
            conn.execute("DELETE FROM object_robots WHERE object_id = ?", (oid,))
            conn.execute("DELETE FROM objects_rtree WHERE object_id = ?", (oid,))
            conn.execute("DELETE FROM objects WHERE object_id = ?", (oid,))
            after = None
            if target is not None:
                _refresh_derived(conn, [target])
                after = _records(conn, [target])[target]
        return before[oid], after

    def find_objects(
        self,
        *,
        category: str | None = None,
        near: Vec3 | None = None,
        radius_m: float | None = None,
        min_confidence: float | None = None,
        robot: str | None = None,
        include_unconfirmed: bool = False,
        limit: int = 100,
        offset: int = 0,
    ) -> ObjectPage:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.find_objects`."""
        sql, params = find_sql(
            category=category, near=near, radius_m=radius_m, min_confidence=min_confidence, robot=robot,
            include_unconfirmed=include_unconfirmed, limit=limit, offset=offset,
        )
        with self._read("object map query") as conn:
            rows = conn.execute(sql, params).fetchall()
            page = rows[:limit]
            robots = _robots(conn, [int(r[0]) for r in page])
        hits = [
            ObjectHit(
                _record(r, robots.get(int(r[0]), ())),
                None if near is None else math.sqrt(max(float(r[28]), 0.0)),
            )
            for r in page
        ]
        return ObjectPage(hits, offset + limit if len(rows) > limit else None)

    def object_detail(self, object_id: int, max_observations: int) -> ObjectDetail | None:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.object_detail`."""
        oid = object_id
        with self._read("object map get") as conn:
            conn.execute("BEGIN")  # one snapshot for the three reads
            try:
                records = _records(conn, [oid])
                if oid not in records:
                    return None
                obs_rows = conn.execute(
                    f"SELECT {_OBS_COLUMNS} FROM observations WHERE object_id = ? "
                    "ORDER BY added_s DESC, observation_id DESC LIMIT ?",
                    (oid, max_observations),
                ).fetchall()
                kf_rows = conn.execute(
                    "SELECT DISTINCT b.robot_id, b.session_id, b.seq, b.stamp, "
                    "EXISTS (SELECT 1 FROM keyframes AS k WHERE k.robot_id = b.robot_id AND "
                    "k.session_id = b.session_id AND k.seq = b.seq) "
                    "FROM (SELECT robot_id, session_id, seq, stamp FROM observations WHERE object_id = ? "
                    "ORDER BY added_s DESC, observation_id DESC LIMIT ?) AS b "
                    "ORDER BY b.stamp, b.robot_id, b.session_id, b.seq",
                    (oid, max_observations),
                ).fetchall()
            finally:
                conn.execute("COMMIT")
        observations = [_observation(r) for r in obs_rows]
        keyframes = [KeyframeRef(str(r[0]), str(r[1]), int(r[2]), float(r[3]), bool(r[4])) for r in kf_rows]
        return ObjectDetail(records[oid], observations, keyframes)

    def count_objects(self, *, unconfirmed: bool | None = None) -> int:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.count_objects`."""
        where = "" if unconfirmed is None else f" WHERE confirmed = {0 if unconfirmed else 1}"
        with self._read("object map count") as conn:
            return int(conn.execute(f"SELECT COUNT(*) FROM objects{where}").fetchone()[0])

    def category_counts(self, *, include_unconfirmed: bool = False) -> dict[str, int]:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.category_counts`."""
        where = "" if include_unconfirmed else " WHERE confirmed = 1"
        with self._read("object map categories") as conn:
            rows = conn.execute(f"SELECT category, COUNT(*) FROM objects{where} GROUP BY category").fetchall()
        return {str(r[0]): int(r[1]) for r in rows}

    def object_ids(self) -> list[int]:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.object_ids`."""
        with self._read("object map ids") as conn:
            return [int(r[0]) for r in conn.execute("SELECT object_id FROM objects ORDER BY object_id")]

    def observation_counts(self) -> dict[int, int]:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.observation_counts`."""
        with self._read("object map observation counts") as conn:
            rows = conn.execute("SELECT object_id, COUNT(*) FROM observations GROUP BY object_id").fetchall()
        return {int(r[0]): int(r[1]) for r in rows}

    # ------------------------------------------------------------------ the mapping stage

    def cursor(self, name: str) -> int:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.cursor`."""
        with self._read("mapping: cursor") as conn:
            row = conn.execute("SELECT last_rowid FROM pipeline_cursor WHERE name = ?", (name,)).fetchone()
        return int(row[0]) if row else 0

    def next_keyframes(self, after: int, limit: int) -> list[StoredKeyframe]:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.next_keyframes`."""
        with self._read("mapping: next keyframes") as conn:
            rows = conn.execute(
                "SELECT rowid, robot_id, session_id, seq, payload FROM keyframes WHERE rowid > ? "
                "ORDER BY rowid LIMIT ?",
                (after, limit),
            ).fetchall()
        return [StoredKeyframe(int(r[0]), str(r[1]), str(r[2]), int(r[3]), bytes(r[4])) for r in rows]

    def count_keyframes_after(self, after: int) -> int:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.count_keyframes_after`."""
        with self._read("mapping: backlog") as conn:
            row = conn.execute("SELECT COUNT(*) FROM keyframes WHERE rowid > ?", (after,)).fetchone()
        return int(row[0])

    def session_has_keyframes_after(self, robot_id: str, session_id: str, after: int) -> bool:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.session_has_keyframes_after`."""
        with self._read("mapping: idle sessions") as conn:
            row = conn.execute(
                "SELECT 1 FROM keyframes WHERE robot_id = ? AND session_id = ? AND rowid > ? LIMIT 1",
                (robot_id, session_id, after),
            ).fetchone()
        return row is not None

    def commit_keyframe(
        self, cursor: str, rowid: int, pose: MappedPose, measurements: Sequence[ObjectMeasurement],
        *, anchored: bool,
    ) -> None:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.commit_keyframe`."""
        rows = [(pose.robot_id, pose.session_id, pose.seq, int(anchored), pack_measurement(m))
                for m in measurements]
        with self._write("mapping: store measurements") as conn:
            conn.executemany(
                "INSERT INTO measurements (robot_id, session_id, seq, anchored, payload) "
                "VALUES (?, ?, ?, ?, ?)",
                rows,
            )
            conn.execute(_INSERT_MAPPED, _mapped_params(pose))
            conn.execute(
                "INSERT INTO pipeline_cursor (name, last_rowid) VALUES (?, ?) "
                "ON CONFLICT(name) DO UPDATE SET last_rowid = excluded.last_rowid",
                (cursor, rowid),
            )

    def unmapped_keyframes(self, upto: int, limit: int) -> list[KeyframeKey]:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.unmapped_keyframes`."""
        with self._read("mapping: keyframes to backfill") as conn:
            rows = conn.execute(
                "SELECT k.rowid, k.robot_id, k.session_id, k.seq FROM keyframes k "
                "LEFT JOIN mapped_keyframes mk USING (robot_id, session_id, seq) "
                "WHERE k.rowid <= ? AND mk.robot_id IS NULL ORDER BY k.rowid LIMIT ?",
                (upto, limit),
            ).fetchall()
        return [KeyframeKey(int(r[0]), str(r[1]), str(r[2]), int(r[3])) for r in rows]

    def record_mapped(self, poses: Sequence[MappedPose]) -> None:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.record_mapped`."""
        with self._write("mapping: backfill mapped keyframes") as conn:
            conn.executemany(_INSERT_MAPPED, [_mapped_params(p) for p in poses])

    def anchored_keyframes(self, after: int, upto: int, limit: int) -> list[AnchoredKeyframe]:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.anchored_keyframes`."""
        with self._read("mapping: replay") as conn:
            rows = conn.execute(
                "SELECT k.rowid, k.robot_id, k.session_id, k.seq, g.T_map_camera, mk.camera, mk.T_map_camera "
                "FROM keyframes k JOIN mapped_keyframes mk USING (robot_id, session_id, seq) "
                "JOIN graph_nodes g USING (robot_id, session_id, seq) "
                "WHERE k.rowid > ? AND k.rowid <= ? AND mk.T_map_camera IS NOT NULL "
                "AND g.T_map_camera IS NOT NULL ORDER BY k.rowid LIMIT ?",
                (after, upto, limit),
            ).fetchall()
            if not rows:
                return []
            by_key: dict[tuple[str, str, int], list[ObjectMeasurement]] = {}
            for robot_id, session_id, seq, payload in conn.execute(
                "SELECT m.robot_id, m.session_id, m.seq, m.payload FROM measurements m "
                "JOIN keyframes k USING (robot_id, session_id, seq) "
                "WHERE k.rowid > ? AND k.rowid <= ? "
                "ORDER BY k.rowid, m.measurement_id",
                (after, int(rows[-1][0])),
            ):
                by_key.setdefault((str(robot_id), str(session_id), int(seq)), []).append(
                    unpack_measurement(payload))
        out = []
        for rowid, robot_id, session_id, seq, pose, camera, measured in rows:
            key = (str(robot_id), str(session_id), int(seq))
            out.append(AnchoredKeyframe(int(rowid), *key, pose_from_blob(pose), camera_from_json(camera),
                                        by_key.get(key, []), pose_from_blob(measured)))
        return out

    def count_measurements(self) -> int:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.count_measurements`."""
        with self._read("mapping: measurements") as conn:
            return int(conn.execute("SELECT COUNT(*) FROM measurements").fetchone()[0])

    def close_sessions(self, sessions: Sequence[tuple[str, str]], at_rowid: int) -> None:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.close_sessions`."""
        with self._write("mapping: close idle sessions") as conn:
            conn.executemany(
                "INSERT OR IGNORE INTO closed_sessions (robot_id, session_id, at_rowid) VALUES (?, ?, ?)",
                [(robot_id, session_id, at_rowid) for robot_id, session_id in sessions],
            )

    def closed_sessions(self, first: int = 0, last: int | None = None) -> list[ClosedSession]:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.closed_sessions`."""
        upto = "" if last is None else " AND at_rowid <= ?"
        with self._read("mapping: closed sessions") as conn:
            rows = conn.execute(
                f"SELECT at_rowid, robot_id, session_id FROM closed_sessions WHERE at_rowid >= ?{upto} "
                "ORDER BY at_rowid, robot_id, session_id",
                (first,) if last is None else (first, last),
            ).fetchall()
        return [ClosedSession(int(r[0]), str(r[1]), str(r[2])) for r in rows]

    def checkpoint(self) -> Checkpoint | None:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.checkpoint`."""
        with self._read("mapping: association checkpoint") as conn:
            row = conn.execute(
                "SELECT last_rowid, config_key, state, written_s FROM association_checkpoint WHERE id = 1"
            ).fetchone()
        return None if row is None else Checkpoint(int(row[0]), str(row[1]), bytes(row[2]), float(row[3]))

    def save_checkpoint(self, checkpoint: Checkpoint) -> None:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.save_checkpoint`."""
        c = checkpoint
        with self._write("mapping: association checkpoint") as conn:
            conn.execute(
                "INSERT INTO association_checkpoint (id, last_rowid, config_key, state, written_s) "
                "VALUES (1, ?, ?, ?, ?) ON CONFLICT(id) DO UPDATE SET "
                "last_rowid = excluded.last_rowid, config_key = excluded.config_key, "
                "state = excluded.state, written_s = excluded.written_s",
                (c.last_rowid, c.config_key, c.state, c.written_s))

    # ------------------------------------------------------------------ the back-end's pose graph

    def commit_graph(self, cursor: str, rowid: int, change: GraphChange) -> None:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.commit_graph`."""
        with self._write("back-end: store the pose graph") as conn:
            if change.nodes:
                first = int(conn.execute("SELECT COALESCE(MAX(node_order), 0) FROM graph_nodes")
                            .fetchone()[0])
                conn.executemany(
                    "INSERT OR IGNORE INTO graph_nodes (robot_id, session_id, seq, node_order, stamp, "
                    "pose_source, T_odom_camera, T_map_camera, prior, codes) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    [(*n.key, first + 1 + i, n.stamp, n.pose_source, pose_blob(n.T_odom_camera),
                      None if n.T_map_camera is None else pose_blob(n.T_map_camera),
                      None if n.prior_T_map_odom is None else pose_blob(n.prior_T_map_odom), n.codes)
                     for i, n in enumerate(change.nodes)])
            if change.edges:
                conn.executemany(
                    "INSERT INTO graph_edges (kind, a_robot, a_session, a_seq, b_robot, b_session, b_seq, "
                    "T_a_b, sigmas, robust, inliers) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    [(e.kind, *e.a, *(e.b if e.b is not None else (None, None, None)), pose_blob(e.T_a_b),
                      np.asarray(e.sigmas, "<f8").tobytes(), int(e.robust), int(e.inliers))
                     for e in change.edges])
            if change.estimates:
                conn.executemany(
                    "UPDATE graph_nodes SET T_map_camera = ? "
                    "WHERE robot_id = ? AND session_id = ? AND seq = ?",
                    [(pose_blob(T), *key) for key, T in change.estimates])
            if change.sessions:
                conn.executemany(
                    "INSERT INTO graph_sessions (robot_id, session_id, T_map_odom, anchored_s, anchored_to, "
                    "revision) VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT (robot_id, session_id) DO UPDATE SET "
                    "T_map_odom = excluded.T_map_odom, anchored_s = excluded.anchored_s, "
                    "anchored_to = excluded.anchored_to, revision = excluded.revision",
                    [(a.robot_id, a.session_id, None if a.T_map_odom is None else pose_blob(a.T_map_odom),
                      a.anchored_s, a.anchored_to, a.revision) for a in change.sessions])
            if change.bump_epoch:
                conn.execute("INSERT INTO graph_epoch (id, epoch) VALUES (1, 1) "
                             "ON CONFLICT (id) DO UPDATE SET epoch = epoch + 1")
            conn.execute(
                "INSERT INTO pipeline_cursor (name, last_rowid) VALUES (?, ?) "
                "ON CONFLICT(name) DO UPDATE SET last_rowid = excluded.last_rowid",
                (cursor, rowid),
            )

    def graph_records(self) -> tuple[list[GraphNodeRow], list[GraphEdgeRow]]:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.graph_records`."""
        with self._read("back-end: load the pose graph") as conn:
            node_rows = conn.execute(
                "SELECT robot_id, session_id, seq, pose_source, T_odom_camera, T_map_camera, prior, codes, "
                "stamp FROM graph_nodes ORDER BY node_order").fetchall()
            edge_rows = conn.execute(
                "SELECT kind, a_robot, a_session, a_seq, b_robot, b_session, b_seq, T_a_b, sigmas, robust, "
                "inliers FROM graph_edges ORDER BY edge_id").fetchall()
        nodes = [GraphNodeRow((str(r[0]), str(r[1]), int(r[2])), float(r[8]), pose_from_blob(r[4]), str(r[3]),
                              None if r[5] is None else pose_from_blob(r[5]),
                              None if r[6] is None else pose_from_blob(r[6]), bytes(r[7]))
                 for r in node_rows]
        edges = [GraphEdgeRow(str(r[0]), (str(r[1]), str(r[2]), int(r[3])),
                              None if r[4] is None else (str(r[4]), str(r[5]), int(r[6])),
                              pose_from_blob(r[7]), np.frombuffer(r[8], "<f8").astype(np.float64),
                              bool(r[9]), int(r[10]))
                 for r in edge_rows]
        return nodes, edges

    def graph_epoch(self) -> int:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.graph_epoch`."""
        with self._read("back-end: graph epoch") as conn:
            row = conn.execute("SELECT epoch FROM graph_epoch WHERE id = 1").fetchone()
        return 0 if row is None else int(row[0])

    def graph_poses(self, keys: Sequence[NodeKey]) -> dict[NodeKey, NDArray[np.float64] | None]:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.graph_poses`."""
        out: dict[NodeKey, NDArray[np.float64] | None] = {}
        with self._read("back-end: keyframe map poses") as conn:
            for key in keys:
                row = conn.execute(
                    "SELECT T_map_camera FROM graph_nodes WHERE robot_id = ? AND session_id = ? AND seq = ?",
                    key).fetchone()
                out[key] = None if row is None or row[0] is None else pose_from_blob(row[0])
        return out

    def session_anchors(self) -> list[SessionAnchor]:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.session_anchors`."""
        with self._read("back-end: sessions") as conn:
            rows = conn.execute(
                "SELECT robot_id, session_id, T_map_odom, anchored_s, anchored_to, revision "
                "FROM graph_sessions ORDER BY robot_id, session_id").fetchall()
        return [SessionAnchor(str(r[0]), str(r[1]), None if r[2] is None else pose_from_blob(r[2]),
                              None if r[3] is None else float(r[3]), str(r[4]), int(r[5])) for r in rows]

    def latest_nodes(self) -> dict[str, GraphNodeRow]:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.latest_nodes`."""
        with self._read("back-end: latest nodes") as conn:
            rows = conn.execute(
                "SELECT robot_id, session_id, seq, stamp, pose_source, T_odom_camera, T_map_camera, prior, "
                "MAX(node_order) FROM graph_nodes GROUP BY robot_id").fetchall()
        return {str(r[0]): GraphNodeRow((str(r[0]), str(r[1]), int(r[2])), float(r[3]), pose_from_blob(r[5]),
                                        str(r[4]), None if r[6] is None else pose_from_blob(r[6]),
                                        None if r[7] is None else pose_from_blob(r[7]), b"")
                for r in rows}

    def map_trajectory(self, robot_id: str, session_id: str | None = None) -> Trajectory:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.map_trajectory`."""
        _check_str(robot_id, "robot_id")
        where, params = "k.robot_id = ?", [robot_id]
        if session_id is not None:
            _check_str(session_id, "session_id")
            where, params = where + " AND k.session_id = ?", [robot_id, session_id]
        with self._read("map trajectory") as conn:
            rows = conn.execute(
                "SELECT k.stamp, g.T_map_camera FROM keyframes k JOIN graph_nodes g "
                f"USING (robot_id, session_id, seq) WHERE {where} AND g.T_map_camera IS NOT NULL "
                "ORDER BY k.stamp, k.session_id, k.seq", params).fetchall()
        stamps = np.array([float(r[0]) for r in rows], dtype=np.float64)
        return stamps, poses_from_blobs([r[1] for r in rows])

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

    # ------------------------------------------------------------------ REST API tokens

    def add_token(self, token: TokenRecord) -> None:
        """See :meth:`~wardmap.server.store.protocol.TokenStore.add_token`."""
        t = token
        with self._write("tokens: add") as conn:
            if conn.execute("SELECT 1 FROM api_tokens WHERE token_id = ?", (t.token_id,)).fetchone():
                raise StoreError(f"token {t.token_id!r} exists already")
            conn.execute(
                "INSERT INTO api_tokens (token_id, name, scope, secret_sha256, created_s, revoked_s) "
                "VALUES (?, ?, ?, ?, ?, ?)",
                (t.token_id, t.name, t.scope, t.secret_sha256, t.created_s, t.revoked_s))

    def token(self, token_id: str) -> TokenRecord | None:
        """See :meth:`~wardmap.server.store.protocol.TokenStore.token`."""
        with self._read("tokens: look-up") as conn:
            row = conn.execute(
                f"SELECT {_TOKEN_COLUMNS} FROM api_tokens WHERE token_id = ?", (token_id,)
            ).fetchone()
        return None if row is None else _token(row)

    def tokens(self) -> list[TokenRecord]:
        """See :meth:`~wardmap.server.store.protocol.TokenStore.tokens`."""
        with self._read("tokens: list") as conn:
            rows = conn.execute(
                f"SELECT {_TOKEN_COLUMNS} FROM api_tokens ORDER BY created_s, token_id"
            ).fetchall()
        return [_token(r) for r in rows]

    def revoke_token(self, token_id: str, revoked_s: float) -> bool:
        """See :meth:`~wardmap.server.store.protocol.TokenStore.revoke_token`."""
        with self._write("tokens: revoke") as conn:
            cur = conn.execute(
                "UPDATE api_tokens SET revoked_s = ? WHERE token_id = ? AND revoked_s IS NULL",
                (float(revoked_s), token_id))
            return cur.rowcount == 1

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

_TOKEN_COLUMNS: Final = "token_id, name, scope, secret_sha256, created_s, revoked_s"


def _token(r: Sequence[Any]) -> TokenRecord:
    scope = str(r[2])
    if scope not in ("read", "admin"):  # the table's CHECK forbids it: only a hand-edited file
        raise StoreDamagedError(f"token {r[0]!r} has an unknown scope {scope!r}")
    return TokenRecord(str(r[0]), str(r[1]), "admin" if scope == "admin" else "read", bytes(r[3]),
                       float(r[4]), None if r[5] is None else float(r[5]))



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


# ---------------------------------------------------------------------- object map rows

_OBJECT_COLUMNS: Final = (
    "o.object_id, o.category, o.confidence, o.T_world_object, o.x, o.y, o.z, o.yaw, "
    "o.qx, o.qy, o.qz, o.qw, o.size_x, o.size_y, o.size_z, "
    "o.min_x, o.min_y, o.min_z, o.max_x, o.max_y, o.max_z, "
    "o.color_r, o.color_g, o.color_b, o.n_observations, o.first_seen_s, o.last_seen_s, o.confirmed"
)
_OBS_COLUMNS: Final = (
    "observation_id, added_s, object_id, robot_id, session_id, seq, stamp, category, confidence, "
    "box_x1, box_y1, box_x2, box_y2, T_world_object, size_x, size_y, size_z"
)
_IN_IDS: Final = "(SELECT value FROM json_each(?))"
"""A list of ids as one JSON parameter (no limit on the number of SQL variables)."""
_INSERT_MAPPED: Final = ("INSERT OR REPLACE INTO mapped_keyframes (robot_id, session_id, seq, T_map_camera, "
                         "camera) VALUES (?, ?, ?, ?, ?)")


def find_sql(
    *,
    category: str | None,
    near: Vec3 | None,
    radius_m: float | None,
    min_confidence: float | None,
    robot: str | None,
    include_unconfirmed: bool,
    limit: int,
    offset: int,
) -> tuple[str, dict[str, Any]]:
    """The SELECT (and its parameters) :meth:`SqliteMapStore.find_objects` runs: up to
    ``limit + 1`` rows of the object columns, then the squared distance to ``near`` when given.

    With ``radius_m`` the R*Tree selects candidates whose bounds meet the cube of half-side
    ``radius_m`` around ``near``; the exact centre distance then decides.
    """
    where: list[str] = []
    params: dict[str, Any] = {"limit": limit + 1, "offset": offset}
    source = "objects AS o"
    select = _OBJECT_COLUMNS
    order = "o.object_id"
    if near is not None:
        params.update(px=near[0], py=near[1], pz=near[2])
        d2 = "((o.x - :px) * (o.x - :px) + (o.y - :py) * (o.y - :py) + (o.z - :pz) * (o.z - :pz))"
        select += f", {d2} AS d2"
        order = "d2, o.object_id"
        if radius_m is not None:
            r = float(radius_m)
            # CROSS JOIN: the R*Tree drives the loop (SQLite keeps the left table outermost).
            source = "objects_rtree AS r CROSS JOIN objects AS o ON o.object_id = r.object_id"
            where += [
                "r.max_x >= :lo_x", "r.min_x <= :hi_x", "r.max_y >= :lo_y", "r.min_y <= :hi_y",
                "r.max_z >= :lo_z", "r.min_z <= :hi_z", f"{d2} <= :r2",
            ]
            params.update(
                lo_x=near[0] - r, hi_x=near[0] + r, lo_y=near[1] - r, hi_y=near[1] + r,
                lo_z=near[2] - r, hi_z=near[2] + r, r2=r * r,
            )
    if category is not None:
        where.append("o.category = :category")
        params["category"] = category
    if not include_unconfirmed:
        where.append("o.confirmed = 1")
    if min_confidence is not None:
        where.append("o.confidence >= :min_confidence")
        params["min_confidence"] = float(min_confidence)
    if robot is not None:
        where.append(
            "EXISTS (SELECT 1 FROM object_robots AS ro WHERE ro.object_id = o.object_id "
            "AND ro.robot_id = :robot)"
        )
        params["robot"] = robot
    sql = f"SELECT {select} FROM {source}"
    if where:
        sql += " WHERE " + " AND ".join(where)
    sql += f" ORDER BY {order} LIMIT :limit OFFSET :offset"
    return sql, params


def _object_params(o: ObjectRow, now_s: float) -> dict[str, Any]:
    T = o.T_world_object
    row: dict[str, Any] = {
        "object_id": o.object_id, "category": o.category, "confidence": o.confidence,
        "T": pose_blob(T), "x": T[0, 3], "y": T[1, 3], "z": T[2, 3], "yaw": o.yaw,
        "qx": o.q_xyzw[0], "qy": o.q_xyzw[1], "qz": o.q_xyzw[2], "qw": o.q_xyzw[3],
        "size_x": o.size[0], "size_y": o.size[1], "size_z": o.size[2],
        "min_x": o.bounds_min[0], "min_y": o.bounds_min[1], "min_z": o.bounds_min[2],
        "max_x": o.bounds_max[0], "max_y": o.bounds_max[1], "max_z": o.bounds_max[2],
        "color_r": None, "color_g": None, "color_b": None, "confirmed": int(o.confirmed), "now": now_s,
    }
    if o.color_rgb is not None:
        row.update(color_r=o.color_rgb[0], color_g=o.color_rgb[1], color_b=o.color_rgb[2])
    return {k: float(v) if isinstance(v, np.floating) else v for k, v in row.items()}


def _observation_params(obs: Observation, now_s: float) -> dict[str, Any]:
    box, size = obs.box_xyxy, obs.size
    return {
        "object_id": obs.object_id, "robot_id": obs.robot_id, "session_id": obs.session_id,
        "seq": int(obs.seq), "stamp": float(obs.stamp), "category": obs.category,
        "confidence": float(obs.confidence),
        "box_x1": float(box[0]), "box_y1": float(box[1]), "box_x2": float(box[2]), "box_y2": float(box[3]),
        "T": pose_blob(obs.T_world_object),
        "size_x": float(size[0]), "size_y": float(size[1]), "size_z": float(size[2]), "now": now_s,
    }


def _mapped_params(p: MappedPose) -> tuple[str, str, int, bytes | None, str | None]:
    if p.T_map_camera is None or p.camera is None:
        return p.robot_id, p.session_id, p.seq, None, None
    return p.robot_id, p.session_id, p.seq, pose_blob(p.T_map_camera), camera_to_json(p.camera)


def _existing(conn: sqlite3.Connection, ids: Sequence[int]) -> set[int]:
    if not ids:
        return set()
    rows = conn.execute(f"SELECT object_id FROM objects WHERE object_id IN {_IN_IDS}", (json.dumps(ids),))
    return {int(r[0]) for r in rows}


def _refresh_derived(conn: sqlite3.Connection, ids: Sequence[int]) -> None:
    """Recompute count, first/last seen and robots of ``ids`` from their observations."""
    arg = (json.dumps(list(ids)),)
    conn.execute(
        "UPDATE objects SET "
        "n_observations = (SELECT COUNT(*) FROM observations AS b "
        "WHERE b.object_id = objects.object_id), "
        "first_seen_s = min(first_seen_s, COALESCE((SELECT MIN(added_s) FROM observations AS b "
        "WHERE b.object_id = objects.object_id), first_seen_s)), "
        "last_seen_s = COALESCE((SELECT MAX(added_s) FROM observations AS b "
        "WHERE b.object_id = objects.object_id), first_seen_s) "
        f"WHERE object_id IN {_IN_IDS}",
        arg,
    )
    conn.execute(f"DELETE FROM object_robots WHERE object_id IN {_IN_IDS}", arg)
    conn.execute(
        "INSERT INTO object_robots (object_id, robot_id) SELECT DISTINCT object_id, robot_id "
        f"FROM observations WHERE object_id IN {_IN_IDS}",
        arg,
    )


def _robots(conn: sqlite3.Connection, ids: Sequence[int]) -> dict[int, tuple[str, ...]]:
    if not ids:
        return {}
    rows = conn.execute(
        f"SELECT object_id, robot_id FROM object_robots WHERE object_id IN {_IN_IDS} "
        "ORDER BY object_id, robot_id",
        (json.dumps(list(ids)),),
    ).fetchall()
    out: dict[int, list[str]] = {}
    for oid, robot in rows:
        out.setdefault(int(oid), []).append(str(robot))
    return {k: tuple(v) for k, v in out.items()}


def _records(conn: sqlite3.Connection, ids: Sequence[int]) -> dict[int, ObjectRecord]:
    rows = conn.execute(
        f"SELECT {_OBJECT_COLUMNS} FROM objects AS o WHERE o.object_id IN {_IN_IDS}",
        (json.dumps(list(ids)),),
    ).fetchall()
    robots = _robots(conn, [int(r[0]) for r in rows])
    return {int(r[0]): _record(r, robots.get(int(r[0]), ())) for r in rows}


def _record(r: Sequence[Any], robots: tuple[str, ...]) -> ObjectRecord:
    color = None if r[21] is None else (float(r[21]), float(r[22]), float(r[23]))
    return ObjectRecord(
        object_id=int(r[0]), category=str(r[1]), confidence=float(r[2]), T_world_object=pose_from_blob(r[3]),
        position=(float(r[4]), float(r[5]), float(r[6])), yaw=float(r[7]),
        q_xyzw=(float(r[8]), float(r[9]), float(r[10]), float(r[11])),
        size=(float(r[12]), float(r[13]), float(r[14])),
        bounds_min=(float(r[15]), float(r[16]), float(r[17])),
        bounds_max=(float(r[18]), float(r[19]), float(r[20])),
        color_rgb=color, n_observations=int(r[24]), first_seen_s=float(r[25]), last_seen_s=float(r[26]),
        robots=robots, confirmed=bool(r[27]),
    )


def _observation(r: Sequence[Any]) -> ObservationRecord:
    return ObservationRecord(
        observation_id=int(r[0]), added_s=float(r[1]), object_id=int(r[2]), robot_id=str(r[3]),
        session_id=str(r[4]), seq=int(r[5]), stamp=float(r[6]), category=str(r[7]), confidence=float(r[8]),
        box_xyxy=np.array([r[9], r[10], r[11], r[12]], dtype=np.float64),
        T_world_object=pose_from_blob(r[13]),
        size=np.array([r[14], r[15], r[16]], dtype=np.float64),
    )

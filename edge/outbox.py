"""Durable keyframe outbox: every keyframe stays on disk until the map server acks it.

The edge agent puts each encoded keyframe here *before* publishing it over Zenoh; the
sender reads :meth:`Outbox.pending`, publishes, calls :meth:`Outbox.mark_sent`, and the
ack handler calls :meth:`Outbox.ack`. After a reconnect or a restart of the agent the
unacked items come back from :meth:`Outbox.pending` with their original
``(robot_id, session_id, seq)`` key, so the server (idempotent on that key) can dedupe.

Guarantees:

- A :meth:`Outbox.put` that returned is committed with ``synchronous=FULL`` in WAL mode:
  it survives a crash of the process and a power loss.
- Nothing is ever evicted. When the outbox holds ``max_items`` items or ``max_bytes``
  payload bytes, :meth:`Outbox.put` raises :class:`OutboxFull` (policy: *block the
  producer*; the caller slows down or waits for acks and retries).
- Ordering: :meth:`Outbox.pending` returns items by session start order, then ``seq``.

Ownership and threads: one process owns an outbox file at a time (an exclusive
``flock`` on ``<path>.lock``; a second open raises :class:`OutboxError`). Inside that
process the :class:`Outbox` object is thread safe: every method takes one internal lock,
so a publisher thread and an ack thread may share it. The lock is never exposed.

Storage: SQLite (stdlib ``sqlite3``) with ``PRAGMA application_id`` marking the file as
a wardmap outbox and ``PRAGMA user_version`` holding the schema version; ``MIGRATIONS``
are applied in order, inside one transaction, when an older file is opened. Clock
values (``created_s``, ``last_sent_s``) are wall-clock seconds (``time.time()``) because
they outlive the process; see :meth:`Outbox.pending` for clock jumps.
"""

from __future__ import annotations

import fcntl
import logging
import math
import os
import secrets
import sqlite3
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Final

from wardmap.shared import sqlitedb
from wardmap.shared.errors import WardmapError

log = logging.getLogger(__name__)

GIB: Final = 1 << 30
APPLICATION_ID: Final = 0x77726D6F  # "wrmo": marks the SQLite file as a wardmap outbox
BUSY_TIMEOUT_S: Final = 5.0

"""SQL statements that take the schema from version ``i`` to ``i + 1`` (``MIGRATIONS[i]``)."""

MIGRATIONS: Final[tuple[sqlitedb.Migration, ...]] = (
    # v1: the outbox, the sessions (start order and persisted next_seq), and meta.
    (
        "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
        """CREATE TABLE sessions (
            ordinal INTEGER PRIMARY KEY AUTOINCREMENT,
            robot_id TEXT NOT NULL,
            session_id TEXT NOT NULL,
            started_s REAL NOT NULL,
            next_seq INTEGER NOT NULL,
            UNIQUE (robot_id, session_id))""",
        """CREATE TABLE outbox (
            robot_id TEXT NOT NULL,
            session_id TEXT NOT NULL,
            seq INTEGER NOT NULL,
            stamp REAL NOT NULL,
            payload BLOB NOT NULL,
            created_s REAL NOT NULL,
            attempts INTEGER NOT NULL DEFAULT 0,
            last_sent_s REAL,
            PRIMARY KEY (robot_id, session_id, seq))""",
    ),
)

OutboxKey = tuple[str, str, int]
"""``(robot_id, session_id, seq)``: the idempotency key of a keyframe."""


class OutboxError(WardmapError):
    """The outbox cannot be opened or used (bad file, bad argument, conflicting put)."""


class OutboxFull(OutboxError):  # noqa: N818 - the name the edge agent API specifies
    """The outbox holds ``max_items`` items or ``max_bytes`` bytes; wait for acks and retry."""


def _record_schema_version(conn: sqlite3.Connection, version: int) -> None:
    conn.execute(
        "INSERT INTO meta (key, value) VALUES ('schema_version', ?) "
        "ON CONFLICT (key) DO UPDATE SET value = excluded.value",
        (str(version),),
    )


OUTBOX_DB: Final = sqlitedb.SqliteKind(
    "outbox database", APPLICATION_ID, MIGRATIONS, OutboxError, BUSY_TIMEOUT_S, _record_schema_version
)


@dataclass(frozen=True, slots=True)
class OutboxItem:
    """One stored keyframe.

    Attributes:
        robot_id, session_id, seq: the key (see :data:`OutboxKey`).
        stamp: keyframe time stamp, seconds (as given to :meth:`Outbox.put`).
        payload: the encoded wire message.
        created_s: wall-clock seconds when it was put.
        attempts: how many times :meth:`Outbox.mark_sent` was called for it.
        last_sent_s: wall-clock seconds of the last send, or None if never sent.
    """

    robot_id: str
    session_id: str
    seq: int
    stamp: float
    payload: bytes
    created_s: float
    attempts: int
    last_sent_s: float | None

    @property
    def key(self) -> OutboxKey:
        return (self.robot_id, self.session_id, self.seq)


@dataclass(frozen=True, slots=True)
class OutboxStats:
    """A snapshot of the outbox.

    Attributes:
        items: number of unacked items.
        bytes: total payload bytes of those items.
        oldest_stamp: smallest ``stamp`` among them (seconds), None if empty.
        max_attempts: largest ``attempts`` among them, 0 if empty.
    """

    items: int
    bytes: int
    oldest_stamp: float | None
    max_attempts: int


def new_session_id() -> str:
    """A fresh session id: zero-padded wall-clock nanoseconds, ``-``, 8 random hex digits.

    Ids sort by start time as strings; the random part keeps two agents started in the
    same nanosecond (or after a clock jump back) apart.
    """
    return f"{time.time_ns():020d}-{secrets.token_hex(4)}"


class Outbox(sqlitedb.GuardedAccess):
    """A disk-backed, bounded, never-evicting queue of keyframes awaiting the server's ack.

    Create with :meth:`Outbox.open` (a context manager). Thread safe within the owning
    process; see the module docstring.
    """

    _DB_LABEL = "outbox"
    _DB_ERROR = OutboxError

    def __init__(
        self, path: Path, conn: sqlite3.Connection, lock_fd: int, max_items: int, max_bytes: int
    ) -> None:
        """Internal: use :meth:`Outbox.open`."""
        self.path = path
        self.max_items = max_items
        self.max_bytes = max_bytes
        self._conn: sqlite3.Connection | None = conn
        self._lock_fd = lock_fd
        self._lock = threading.Lock()
        items, nbytes = conn.execute(
            "SELECT COUNT(*), COALESCE(SUM(length(payload)), 0) FROM outbox"
        ).fetchone()
        self._items = int(items)
        self._bytes = int(nbytes)

    # ------------------------------------------------------------------ life cycle

    @classmethod
    def open(
        cls, path: str | os.PathLike[str], *, max_items: int = 10_000, max_bytes: int = 2 * GIB
    ) -> Outbox:
        """Open (or create) the outbox file at ``path``; its parent folder is created.

        Args:
            path: the SQLite file.
            max_items: capacity in items (> 0).
            max_bytes: capacity in payload bytes (> 0).

        Raises:
            OutboxError: the path is unwritable, the file is not a wardmap outbox or is
                corrupt, it was written by a newer wardmap, or another process has it open.
        """
        for name, value in (("max_items", max_items), ("max_bytes", max_bytes)):
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise OutboxError(f"{name} must be a positive int, got {value!r}")
        path = Path(path)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutboxError(f"cannot create the outbox folder {path.parent}: {exc}") from exc
        lock_fd = _lock_file(path)
        conn: sqlite3.Connection | None = None
        try:
            conn = sqlitedb.connect(path, OUTBOX_DB)
            sqlitedb.check_and_migrate(conn, path, OUTBOX_DB)
            outbox = cls(path, conn, lock_fd, max_items, max_bytes)
        except BaseException as exc:
            if conn is not None:
                conn.close()
            os.close(lock_fd)
            if isinstance(exc, sqlite3.Error):
                raise OutboxError(f"cannot open the outbox {path}: {exc}") from exc
            raise
        log.info("outbox %s open: %d pending items, %d bytes", path, outbox._items, outbox._bytes)
        return outbox

    def close(self) -> None:
        """Close the file (idempotent). Every committed put stays on disk."""
        with self._lock:
            if self._conn is None:
                return
            try:
                self._conn.close()
            finally:
                self._conn = None
                os.close(self._lock_fd)

    def __enter__(self) -> Outbox:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # ------------------------------------------------------------------ writes

    def put(self, robot_id: str, session_id: str, seq: int, stamp: float, payload: bytes) -> None:
        """Store one keyframe atomically and durably.

        Putting a key again with the same stamp and payload is a no-op (safe to retry);
        with a different stamp or payload it raises :class:`OutboxError`.

        Raises:
            OutboxFull: storing it would exceed ``max_items`` or ``max_bytes``; nothing
                was stored and nothing was evicted. Wait for acks and retry.
            OutboxError: bad arguments, a conflicting duplicate, a payload larger than
                ``max_bytes`` on its own, or a database failure.
        """
        key = _check_key((robot_id, session_id, seq))
        stamp_f = _check_stamp(stamp)
        data = _check_payload(payload)
        with self._lock:
            self._put_locked(key, stamp_f, data)

    def start_session(self, robot_id: str, *, session_id: str | None = None) -> SessionIds:
        """Register a session (a fresh :func:`new_session_id` unless given) and return its ids.

        Call once per agent start. Items of earlier sessions stay pending with their own
        keys and come first in :meth:`pending`. Passing an existing ``session_id``
        resumes it: its ``next_seq`` continues from the persisted value.
        """
        sid = new_session_id() if session_id is None else session_id
        _check_key((robot_id, sid, 0))
        with self._lock, self._write("start_session") as conn:
            conn.execute(
                "INSERT INTO sessions (robot_id, session_id, started_s, next_seq) VALUES (?, ?, ?, 0) "
                "ON CONFLICT (robot_id, session_id) DO NOTHING",
                (robot_id, sid, time.time()),
            )
        log.info("outbox %s: session %s/%s started", self.path, robot_id, sid)
        return SessionIds(self, robot_id, sid)

    def next_seq(self, robot_id: str, session_id: str) -> int:
        """The smallest seq above every seq ever put in this session (0 for a new session)."""
        _check_key((robot_id, session_id, 0))
        with self._lock, self._read("next_seq") as conn:
            return self._next_seq_locked(conn, robot_id, session_id)

    def put_next(self, robot_id: str, session_id: str, stamp: float, payload: bytes) -> int:
        """Put with ``seq = next_seq(robot_id, session_id)`` atomically; return that seq.

        A failed put (e.g. :class:`OutboxFull`) consumes no seq, so a retry leaves no gap.
        """
        _check_key((robot_id, session_id, 0))
        stamp_f = _check_stamp(stamp)
        data = _check_payload(payload)
        with self._lock:
            with self._read("put_next") as conn:
                seq = self._next_seq_locked(conn, robot_id, session_id)
            self._put_locked((robot_id, session_id, seq), stamp_f, data)
        return seq

    def mark_sent(self, keys: Iterable[OutboxKey], now: float | None = None) -> int:
        """Record a send of ``keys`` at ``now`` (default: ``time.time()``); return how many exist.

        Increments ``attempts`` and sets ``last_sent_s``. Keys already acked are ignored.
        """
        checked = [_check_key(k) for k in keys]
        t = time.time() if now is None else _check_stamp(now, "now")
        if not checked:
            return 0
        with self._lock, self._write("mark_sent") as conn:
            cur = conn.executemany(
                "UPDATE outbox SET attempts = attempts + 1, last_sent_s = ? "
                "WHERE robot_id = ? AND session_id = ? AND seq = ?",
                [(t, *key) for key in checked],
            )
            return int(cur.rowcount)

    def ack(self, robot_id: str, session_id: str, seq: int) -> bool:
        """Remove an acknowledged item; True if it was there (idempotent: a repeat returns False)."""
        return self.ack_many([(robot_id, session_id, seq)]) == 1

    def ack_many(self, keys: Iterable[OutboxKey]) -> int:
        """Remove acknowledged items in one transaction; return how many were removed."""
        checked = [_check_key(k) for k in keys]
        if not checked:
            return 0
        removed = 0
        freed = 0
        with self._lock:
            with self._write("ack") as conn:
                for key in checked:
                    row = conn.execute(
                        "DELETE FROM outbox WHERE robot_id = ? AND session_id = ? AND seq = ? "
                        "RETURNING length(payload)",
                        key,
                    ).fetchone()
                    if row is not None:
                        removed += 1
                        freed += int(row[0])
            self._items -= removed
            self._bytes -= freed
        return removed

    def vacuum(self) -> None:
        """Give the space of acked items back to the file system (rewrites the file)."""
        with self._lock, self._db_errors("vacuum"):
            conn = self._connection()
            conn.execute("VACUUM")
            conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")

    # ------------------------------------------------------------------ reads

    def pending(
        self, limit: int = 100, *, resend_after_s: float | None = None, now: float | None = None
    ) -> list[OutboxItem]:
        """Up to ``limit`` unacked items, oldest session first, then by ``seq``.

        Args:
            limit: maximum number of items (>= 1).
            resend_after_s: if given, skip items sent less than this many seconds before
                ``now`` (their ack may still come); they are returned again once the
                timeout has passed. None returns every unacked item.
            now: wall-clock seconds (default ``time.time()``). An item whose
                ``last_sent_s`` lies after ``now`` (the clock jumped back) counts as due.
        """
        if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
            raise OutboxError(f"limit must be an int >= 1, got {limit!r}")
        t = time.time() if now is None else _check_stamp(now, "now")
        cutoff = t
        if resend_after_s is not None:
            resend = _check_stamp(resend_after_s, "resend_after_s")
            if resend < 0:
                raise OutboxError(f"resend_after_s must be >= 0, got {resend_after_s!r}")
            cutoff = t - resend
        with self._lock, self._read("pending") as conn:
            rows = conn.execute(
                "SELECT o.robot_id, o.session_id, o.seq, o.stamp, o.payload, o.created_s, o.attempts, "
                "o.last_sent_s FROM outbox AS o JOIN sessions AS s "
                "ON s.robot_id = o.robot_id AND s.session_id = o.session_id "
                "WHERE :every OR o.last_sent_s IS NULL OR o.last_sent_s <= :cutoff OR o.last_sent_s > :now "
                "ORDER BY s.ordinal, o.seq LIMIT :limit",
                {"every": resend_after_s is None, "cutoff": cutoff, "now": t, "limit": limit},
            ).fetchall()
        return [
            OutboxItem(
                str(r[0]), str(r[1]), int(r[2]), float(r[3]), bytes(r[4]), float(r[5]), int(r[6]), r[7]
            )
            for r in rows
        ]

    def stats(self) -> OutboxStats:
        """Counts, payload bytes, oldest stamp and the most attempts among unacked items."""
        with self._lock, self._read("stats") as conn:
            items, nbytes, oldest, attempts = conn.execute(
                "SELECT COUNT(*), COALESCE(SUM(length(payload)), 0), MIN(stamp), COALESCE(MAX(attempts), 0) "
                "FROM outbox"
            ).fetchone()
        return OutboxStats(int(items), int(nbytes), None if oldest is None else float(oldest), int(attempts))

    def __len__(self) -> int:
        with self._lock:
            self._connection()
            return self._items

    # ------------------------------------------------------------------ internals (lock held)

    def _put_locked(self, key: OutboxKey, stamp: float, data: bytes) -> None:
        if len(data) > self.max_bytes:
            raise OutboxError(
                f"payload of {len(data)} bytes for {key} exceeds the outbox capacity "
                f"max_bytes={self.max_bytes}"
            )
        robot_id, session_id, seq = key
        inserted = False
        with self._write("put") as conn:
            row = conn.execute(
                "SELECT stamp, payload FROM outbox WHERE robot_id = ? AND session_id = ? AND seq = ?", key
            ).fetchone()
            if row is not None:
                if float(row[0]) == stamp and bytes(row[1]) == data:
                    return
                raise OutboxError(f"{key} is already in the outbox with a different stamp or payload")
            if self._items + 1 > self.max_items or self._bytes + len(data) > self.max_bytes:
                raise OutboxFull(
                    f"outbox {self.path} is full ({self._items}/{self.max_items} items, "
                    f"{self._bytes + len(data)}/{self.max_bytes} bytes with this one); "
                    "wait for the server's acks and retry"
                )
            now = time.time()
            conn.execute(
                "INSERT INTO sessions (robot_id, session_id, started_s, next_seq) VALUES (?, ?, ?, ?) "
                "ON CONFLICT (robot_id, session_id) "
                "DO UPDATE SET next_seq = max(next_seq, excluded.next_seq)",
                (robot_id, session_id, now, seq + 1),
            )
            conn.execute(
                "INSERT INTO outbox (robot_id, session_id, seq, stamp, payload, created_s, attempts, "
                "last_sent_s) VALUES (?, ?, ?, ?, ?, ?, 0, NULL)",
                (robot_id, session_id, seq, stamp, data, now),
            )
            inserted = True
        if inserted:  # only after COMMIT succeeded
            self._items += 1
            self._bytes += len(data)

    @staticmethod
    def _next_seq_locked(conn: sqlite3.Connection, robot_id: str, session_id: str) -> int:
        row = conn.execute(
            "SELECT next_seq FROM sessions WHERE robot_id = ? AND session_id = ?", (robot_id, session_id)
        ).fetchone()
        return 0 if row is None else int(row[0])

    def _connection(self) -> sqlite3.Connection:
        if self._conn is None:
            raise OutboxError(f"outbox {self.path} is closed")
        return self._conn



class SessionIds:
    """The ids of one agent run: a robot, a session id fresh per start, and its seq counter.

    ``next_seq`` lives in the outbox file, so it is never reused within a session, even
    after every item was acked. Get one from :meth:`Outbox.start_session`.
    """

    def __init__(self, outbox: Outbox, robot_id: str, session_id: str) -> None:
        self.outbox = outbox
        self.robot_id = robot_id
        self.session_id = session_id

    @property
    def next_seq(self) -> int:
        """The seq the next :meth:`put` will use."""
        return self.outbox.next_seq(self.robot_id, self.session_id)

    def put(self, stamp: float, payload: bytes) -> int:
        """Put a keyframe under the next seq of this session; return the seq (see :meth:`Outbox.put_next`)."""
        return self.outbox.put_next(self.robot_id, self.session_id, stamp, payload)

    def __repr__(self) -> str:
        return f"SessionIds(robot_id={self.robot_id!r}, session_id={self.session_id!r})"


# ---------------------------------------------------------------------- helpers


def _lock_file(path: Path) -> int:
    """Take an exclusive, non-blocking flock on ``<path>.lock``; return its descriptor."""
    lock_path = path.with_name(path.name + ".lock")
    try:
        fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise OutboxError(f"cannot open the outbox {path}: {exc}") from exc
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError as exc:
        os.close(fd)
        raise OutboxError(
            f"outbox {path} is already open (by another agent or Outbox in this process)"
        ) from exc
    except OSError as exc:
        os.close(fd)
        raise OutboxError(f"cannot lock the outbox {path}: {exc}") from exc
    return fd


def _check_key(key: object) -> OutboxKey:
    if not isinstance(key, tuple) or len(key) != 3:
        raise OutboxError(f"an outbox key is (robot_id, session_id, seq), got {key!r}")
    robot_id, session_id, seq = key
    for name, value in (("robot_id", robot_id), ("session_id", session_id)):
        if not isinstance(value, str) or not value:
            raise OutboxError(f"{name} must be a non-empty str, got {value!r}")
    if isinstance(seq, bool) or not isinstance(seq, int) or not 0 <= seq < 2**63 - 1:
        raise OutboxError(f"seq must be an int in [0, 2**63 - 1), got {seq!r}")
    return (robot_id, session_id, seq)


def _check_stamp(value: object, name: str = "stamp") -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise OutboxError(f"{name} must be a finite number of seconds, got {value!r}")
    return float(value)


def _check_payload(payload: object) -> bytes:
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise OutboxError(f"payload must be bytes, got {type(payload).__name__}")
    return bytes(payload)

"""The map store's queries both SQL backends share (:class:`SqlMapStore`).

SQLite (``sqlite.py``) and PostgreSQL (``postgres.py``) run the same statements for every
read and for every write but the keyframe insert: the SQL here is the subset both dialects
speak (``INSERT ... ON CONFLICT``, row values, ``EXISTS``), written with SQLite's ``?`` and
``:name`` placeholders, which the PostgreSQL store's connections translate for psycopg. A
backend subclass supplies the connections (:meth:`SqlMapStore._read`, ``_write``,
``_snapshot``), the keyframe insert, the readiness probe and the few dialect hooks
(``_IN_IDS``, ``_ids``, the object index, the schema version). The Protocol docstrings
(``protocol.py``) say what each method does.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Sequence
from contextlib import AbstractContextManager
from types import TracebackType
from typing import Any, ClassVar, Self

import numpy as np
from numpy.typing import NDArray

from wardmap.server.perception.types import ObjectMeasurement
from wardmap.server.store.codec import (
    camera_from_json,
    camera_to_json,
    pack_measurement,
    pack_measurements,
    pose_blob,
    pose_from_blob,
    poses_from_blobs,
    unpack_measurement,
    unpack_measurements,
    without_images,
)
from wardmap.server.store.records import (
    MAX_REASON_LEN,
    AnchoredKeyframe,
    Checkpoint,
    ClaimedKeyframe,
    ClosedSession,
    CompactPage,
    CompactRow,
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
    Perceived,
    PerceptionSlot,
    RobotSummary,
    SessionAnchor,
    StoredKeyframe,
    StoreError,
    StoreStats,
    TokenRecord,
    Trajectory,
    UnknownObjectError,
    Vec3,
)
from wardmap.server.store.rows import (
    COMPACT_COLUMNS,
    OBJECT_COLUMNS,
    OBS_COLUMNS,
    TOKEN_COLUMNS,
    check_cursor,
    check_limit,
    check_reason,
    check_seconds,
    check_seq,
    check_str,
    find_sql,
    insert_args,
    mapped_params,
    object_params,
    object_record,
    observation_params,
    observation_record,
    token_from_row,
)
from wardmap.server.store.schema import Dialect
from wardmap.shared.errors import WireError
from wardmap.shared.wire import KeyframeMsg

log = logging.getLogger(__name__)

MAX_HOLDER_LEN = 40
"""Longest writer-lease holder name (PostgreSQL shows it in a 63-byte ``application_name``)."""
ERASE_BATCH = 64
"""Keyframes whose images :meth:`SqlMapStore.erase_images` rewrites per transaction."""

CLAIM_CANDIDATES = 8
"""Keyframes :meth:`SqlMapStore.claim_keyframe` reads as candidates per call (others' claims race)."""
_CURSOR_OF = "COALESCE((SELECT last_rowid FROM pipeline_cursor WHERE name = ?), 0)"
"""The rowid of the named cursor (one ``?``), 0 when it has none."""

_INSERT_MAPPED = (
    "INSERT INTO mapped_keyframes (robot_id, session_id, seq, T_map_camera, camera) VALUES (?, ?, ?, ?, ?) "
    "ON CONFLICT (robot_id, session_id, seq) DO UPDATE SET T_map_camera = excluded.T_map_camera, "
    "camera = excluded.camera"
)


def check_lease_holder(holder: object) -> str:
    """``holder`` if it is a valid writer-lease holder name (1-:data:`MAX_HOLDER_LEN` printable
    ASCII characters), else StoreError naming what came."""
    if not (isinstance(holder, str) and 0 < len(holder) <= MAX_HOLDER_LEN and holder.isascii()
            and holder.isprintable()):
        raise StoreError(f"a writer lease holder must be 1-{MAX_HOLDER_LEN} printable ASCII characters, "
                         f"got {holder!r:.60}")
    return holder


class SqlMapStore:
    """The shared part of an SQL map store (see the module docstring). Connections are typed
    ``Any``: ``sqlite3.Connection``, or the PostgreSQL store's placeholder-translating wrapper;
    both have ``execute`` and ``executemany`` returning a DB-API cursor."""

    dialect: Dialect
    """Which SQL the object index speaks (``rows.find_sql``)."""
    _health_lock: threading.Lock
    """Guards :attr:`_damage` (each backend sets both in its constructor)."""
    _damage: str | None
    """The first damage a statement reported; sticky until the database is repaired."""
    _IN_IDS: ClassVar[str]
    """``"<column> {_IN_IDS}"`` keeps rows whose column is one of the ids given by :meth:`_ids`."""
    _FENCE_READ: ClassVar[str] = "SELECT epoch FROM writer_fence WHERE id = 1"
    """How a map write reads the writer fence (PostgreSQL: ``FOR SHARE``, so a new holder's bump
    waits for the old holder's write in flight)."""
    _fence_epoch: int | None = None
    """The writer-fence epoch this store's writer lease took (None: it never held one, and its
    map writes are not fenced: tools, tests, a standby's admin edits)."""

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def take_writer_fence(self) -> int:
        """Bump the writer fence's epoch and fence this store's map writes with it (the writer
        lease calls it when taken; a former holder's writes are refused from now on)."""
        with self._write("writer lease: fence") as conn:
            epoch = int(conn.execute("UPDATE writer_fence SET epoch = epoch + 1 WHERE id = 1 RETURNING epoch")
                        .fetchone()[0])
        self._fence_epoch = epoch
        return epoch

    def _fence(self, conn: Any) -> None:
        """Inside a map write (the writer's: measurements, cursors, graph, checkpoint, objects):
        StoreError when this store took the writer fence and another holder has since."""
        held = self._fence_epoch
        if held is None:
            return
        now = int(conn.execute(self._FENCE_READ).fetchone()[0])
        if now != held:
            raise StoreError(f"the writer lease moved to another server (fence epoch {held}, now {now}): "
                             "this server's map writes are refused")

    def _first_damage(self, detail: str) -> bool:
        """Record ``detail`` as the store's damage unless one is recorded; True when it was the
        first (the caller logs it once)."""
        with self._health_lock:
            first = self._damage is None
            if first:
                self._damage = detail
        return first

    def _ids(self, ids: Sequence[int]) -> object:
        """The one parameter :data:`_IN_IDS` takes for ``ids``."""
        raise NotImplementedError

    def _read(self, what: str) -> AbstractContextManager[Any]:
        """A connection that sees the last committed state; errors name ``what``."""
        raise NotImplementedError

    def _write(self, what: str) -> AbstractContextManager[Any]:
        """A connection inside one transaction, committed when the block ends without error."""
        raise NotImplementedError

    def _snapshot(self, what: str) -> AbstractContextManager[Any]:
        """A connection whose statements all see one snapshot (reads only)."""
        raise NotImplementedError

    def _schema_version(self, conn: Any) -> int:
        raise NotImplementedError

    def _serialise_inserts(self, conn: Any) -> None:
        """Make keyframe inserts take turns until the transaction ends (SQLite's ``BEGIN
        IMMEDIATE`` does already), so a key is looked up and inserted by one writer at a time and
        insertion order (``rowid``) equals commit order."""

    def _index_objects(self, conn: Any, rows: Sequence[dict[str, Any]]) -> None:
        """Keep the object index up to date for these :func:`~rows.object_params` rows (a
        backend whose index is a separate table writes it; PostgreSQL's is on the table)."""

    def _unindex_object(self, conn: Any, object_id: int) -> None:
        """Remove a deleted object from the object index (see :meth:`_index_objects`)."""

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
        key, data, t = insert_args(msg, payload, received_s)
        pose = pose_blob(msg.T_odom_camera)
        with self._write("insert") as conn:
            self._serialise_inserts(conn)
            # Looked up first, so a key found stored takes no rowid (insertion order has no gaps);
            # ON CONFLICT is the second guard.
            row = conn.execute(
                "SELECT payload = ? FROM keyframes WHERE robot_id = ? AND session_id = ? AND seq = ?",
                (data, *key),
            ).fetchone()
            stored = row is None and conn.execute(
                "INSERT INTO keyframes (robot_id, session_id, seq, stamp, received_s, pose_source, "
                "payload_bytes, T_odom_camera, payload) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?) "
                "ON CONFLICT (robot_id, session_id, seq) DO NOTHING",
                (*key, float(msg.stamp), t, str(msg.pose_source), len(data), pose, data),
            ).rowcount == 1
            if not stored:
                if row is not None and not row[0]:
                    log.warning("keyframe %s/%s/%d arrived again with different bytes (%d bytes); "
                                "keeping the first copy", *key, len(data))
                return "duplicate"
            conn.execute(
                "INSERT INTO robots (robot_id, first_seen_s, last_seen_s) VALUES (?, ?, ?) "
                "ON CONFLICT (robot_id) DO UPDATE SET "
                "first_seen_s = CASE WHEN excluded.first_seen_s < robots.first_seen_s "
                "THEN excluded.first_seen_s ELSE robots.first_seen_s END, "
                "last_seen_s = CASE WHEN excluded.last_seen_s > robots.last_seen_s "
                "THEN excluded.last_seen_s ELSE robots.last_seen_s END",
                (msg.robot_id, t, t),
            )
            conn.execute(
                "INSERT INTO sessions (robot_id, session_id, started_s) VALUES (?, ?, ?) "
                "ON CONFLICT (robot_id, session_id) DO UPDATE SET "
                "started_s = CASE WHEN excluded.started_s < sessions.started_s "
                "THEN excluded.started_s ELSE sessions.started_s END",
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
        check_reason(reason, n)
        with self._write("count_rejection") as conn:
            conn.execute(
                "INSERT INTO rejections (reason, count) VALUES (?, ?) "
                "ON CONFLICT (reason) DO UPDATE SET count = rejections.count + excluded.count",
                (reason, n),
            )

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
        check_str(robot_id, "robot_id")
        check_limit(limit)
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
                    where, params = "stamp > ?", (check_seconds(after, "after", positive=False),)
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
        check_str(robot_id, "robot_id")
        with self._read("trajectory") as conn:
            if session_id is None:
                rows = conn.execute(
                    "SELECT stamp, T_odom_camera FROM keyframes WHERE robot_id = ? "
                    "ORDER BY stamp, session_id, seq",
                    (robot_id,),
                ).fetchall()
            else:
                check_str(session_id, "session_id")
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
        check_str(robot_id, "robot_id")
        check_str(session_id, "session_id")
        check_seq(seq)
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
        keyframes already erased are skipped. Committed in batches of :data:`ERASE_BATCH`
        (SQLite with ``secure_delete`` on, so the pages that held the images are zeroed when
        freed; PostgreSQL frees the old row versions at its next VACUUM).

        Args:
            now_s: server wall-clock seconds recorded as the erasure time.
            received_before_s: keyframes the server received before this (retention).
            stamp_from, stamp_to: keyframes whose capture stamp lies in ``[from, to)`` (seconds).
            robot_id: only this robot's keyframes.

        Raises:
            StoreError: no filter, bad arguments, or a database failure (earlier batches stay erased).
        """
        t = check_seconds(now_s, "now_s")
        where: list[str] = ["images_erased_s IS NULL"]
        params: list[float | str] = []
        if received_before_s is not None:
            where.append("received_s < ?")
            params.append(check_seconds(received_before_s, "received_before_s"))
        if stamp_from is not None:
            where.append("stamp >= ?")
            params.append(check_seconds(stamp_from, "stamp_from", positive=False))
        if stamp_to is not None:
            where.append("stamp < ?")
            params.append(check_seconds(stamp_to, "stamp_to", positive=False))
        if robot_id is not None:
            where.append("robot_id = ?")
            params.append(check_str(robot_id, "robot_id"))
        if len(where) == 1:
            raise StoreError("erase_images: give at least one filter (received_before_s, stamps, robot_id)")
        sql = (f"SELECT rowid, payload FROM keyframes WHERE {' AND '.join(where)} AND rowid > ? "
               "ORDER BY rowid LIMIT ?")
        erased, last = 0, 0
        while True:
            with self._write("erase images") as conn:
                if self.dialect == "sqlite":
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
        with self._snapshot("stats") as conn:
            robots = conn.execute("SELECT COUNT(*) FROM robots").fetchone()[0]
            sessions = conn.execute("SELECT COUNT(*) FROM sessions").fetchone()[0]
            keyframes, nbytes = conn.execute(
                "SELECT COUNT(*), COALESCE(SUM(payload_bytes), 0) FROM keyframes"
            ).fetchone()
            rejected = conn.execute("SELECT COALESCE(SUM(count), 0) FROM rejections").fetchone()[0]
            version = self._schema_version(conn)
        return StoreStats(
            int(robots), int(sessions), int(keyframes), int(nbytes), int(rejected), int(version)
        )

    def write_objects(
        self, objects: Sequence[ObjectRow], observations: Sequence[Observation], now_s: float
    ) -> list[ObjectWrite]:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.write_objects`."""
        obj_rows = [object_params(o, now_s) for o in objects]
        obs_rows = [observation_params(o, now_s) for o in observations]
        ids = [o.object_id for o in objects]
        with self._write("object map upsert") as conn:
            self._fence(conn)
            existing = self._existing(conn, ids)
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
            self._index_objects(conn, obj_rows)
            touched: dict[int, None] = dict.fromkeys(ids)
            if obs_rows:
                missing = {int(r["object_id"]) for r in obs_rows} - set(ids)
                missing -= self._existing(conn, sorted(missing))
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
            self._refresh_derived(conn, order)
            records = self._records(conn, order)
        given = set(ids)
        return [ObjectWrite(records[oid], oid in given and oid not in existing) for oid in order]

    def delete_object(
        self, object_id: int, merged_into: int | None = None
    ) -> tuple[ObjectRecord, ObjectRecord | None]:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.delete_object`."""
        oid, target = object_id, merged_into
        with self._write("object map delete") as conn:
            self._fence(conn)
            before = self._records(conn, [oid])
            if oid not in before:
                raise UnknownObjectError(f"unknown object {oid}")
            if target is not None and not self._existing(conn, [target]):
                raise UnknownObjectError(f"unknown object {target} (merged_into)")
            if target is None:
                conn.execute("DELETE FROM observations WHERE object_id = ?", (oid,))
            else:
                conn.execute("UPDATE observations SET object_id = ? WHERE object_id = ?", (target, oid))
            conn.execute("DELETE FROM object_robots WHERE object_id = ?", (oid,))
            self._unindex_object(conn, oid)
            conn.execute("DELETE FROM objects WHERE object_id = ?", (oid,))
            after = None
            if target is not None:
                self._refresh_derived(conn, [target])
                after = self._records(conn, [target])[target]
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
            self.dialect,
            category=category, near=near, radius_m=radius_m, min_confidence=min_confidence, robot=robot,
            include_unconfirmed=include_unconfirmed, limit=limit, offset=offset,
        )
        with self._read("object map query") as conn:
            rows = conn.execute(sql, params).fetchall()
            page = rows[:limit]
            robots = self._robots(conn, [int(r[0]) for r in page])
        hits = [
            ObjectHit(
                object_record(r, robots.get(int(r[0]), ())),
                None if near is None else math.sqrt(max(float(r[28]), 0.0)),
            )
            for r in page
        ]
        return ObjectPage(hits, offset + limit if len(rows) > limit else None)

    def find_compact(
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
    ) -> CompactPage:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.find_compact`."""
        sql, params = find_sql(
            self.dialect,
            category=category, near=near, radius_m=radius_m, min_confidence=min_confidence, robot=robot,
            include_unconfirmed=include_unconfirmed, limit=limit, offset=offset, columns=COMPACT_COLUMNS,
        )
        with self._read("object map query") as conn:
            rows = conn.execute(sql, params).fetchall()
        page: list[CompactRow] = [
            (int(r[0]), str(r[1]), float(r[2]), float(r[3]), float(r[4]), float(r[5]), float(r[6]),
             float(r[7]), float(r[8]))
            for r in rows[:limit]
        ]
        return CompactPage(page, offset + limit if len(rows) > limit else None)

    def object_detail(self, object_id: int, max_observations: int) -> ObjectDetail | None:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.object_detail`."""
        oid = object_id
        with self._snapshot("object map get") as conn:  # one snapshot for the three reads
            records = self._records(conn, [oid])
            if oid not in records:
                return None
            obs_rows = conn.execute(
                f"SELECT {OBS_COLUMNS} FROM observations WHERE object_id = ? "
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
        observations = [observation_record(r) for r in obs_rows]
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
            self._fence(conn)
            conn.executemany(
                "INSERT INTO measurements (robot_id, session_id, seq, anchored, payload) "
                "VALUES (?, ?, ?, ?, ?)",
                rows,
            )
            conn.execute(_INSERT_MAPPED, mapped_params(pose))
            conn.execute("DELETE FROM perception WHERE robot_id = ? AND session_id = ? AND seq = ?",
                         (pose.robot_id, pose.session_id, pose.seq))
            conn.execute(
                "INSERT INTO pipeline_cursor (name, last_rowid) VALUES (?, ?) "
                "ON CONFLICT(name) DO UPDATE SET last_rowid = excluded.last_rowid",
                (cursor, rowid),
            )

    def claim_keyframe(
        self, worker: str, *, cursor: str, now_s: float, claim_s: float, rowid: int | None = None,
    ) -> ClaimedKeyframe | None:
        """See :meth:`~wardmap.server.store.protocol.PerceptionStore.claim_keyframe`.

        Candidates are read first; each is then claimed by a conditional upsert in a transaction
        of its own, which takes it only when it has no row or an expired, resultless one, and
        only while it is still after the cursor (a keyframe the mapping stage committed
        meanwhile is not claimed again). A candidate another worker took first is skipped."""
        check_str(worker, "worker")
        if not (math.isfinite(now_s) and math.isfinite(claim_s) and claim_s > 0):
            raise StoreError(f"claim_keyframe: need finite now_s and claim_s > 0, got {now_s!r}, {claim_s!r}")
        only = "" if rowid is None else " AND k.rowid = ?"
        with self._read("perception: candidates") as conn:
            candidates = [int(r[0]) for r in conn.execute(
                "SELECT k.rowid FROM keyframes k LEFT JOIN perception p USING (robot_id, session_id, seq) "
                f"WHERE k.rowid > {_CURSOR_OF}{only} "
                "AND (p.robot_id IS NULL OR (p.done = 0 AND p.expires_s <= ?)) ORDER BY k.rowid LIMIT ?",
                (cursor, now_s, CLAIM_CANDIDATES) if rowid is None else (cursor, rowid, now_s, 1)).fetchall()]
        for candidate in candidates:
            with self._write("perception: claim") as conn:
                row = conn.execute(
                    "INSERT INTO perception (robot_id, session_id, seq, kf_rowid, worker, expires_s, "
                    "attempts) SELECT robot_id, session_id, seq, rowid, ?, ?, 1 FROM keyframes k "
                    f"WHERE k.rowid = ? AND k.rowid > {_CURSOR_OF} "
                    "ON CONFLICT (robot_id, session_id, seq) DO UPDATE SET worker = excluded.worker, "
                    "expires_s = excluded.expires_s, attempts = perception.attempts + 1 "
                    "WHERE perception.done = 0 AND perception.expires_s <= ? RETURNING attempts",
                    (worker, now_s + claim_s, candidate, cursor, now_s)).fetchone()
                if row is None:
                    continue
                kf = conn.execute("SELECT robot_id, session_id, seq, payload FROM keyframes WHERE rowid = ?",
                                  (candidate,)).fetchone()
            return ClaimedKeyframe(candidate, str(kf[0]), str(kf[1]), int(kf[2]), bytes(kf[3]), int(row[0]))
        return None

    def store_perceived(self, worker: str, result: Perceived) -> bool:
        """See :meth:`~wardmap.server.store.protocol.PerceptionStore.store_perceived`."""
        check_str(worker, "worker")
        p = result.pose
        pose = None if p.T_map_camera is None else pose_blob(p.T_map_camera)
        camera = None if p.camera is None else camera_to_json(p.camera)
        failure = None if result.failure is None else check_str(result.failure[:MAX_REASON_LEN], "failure")
        with self._write("perception: store a result") as conn:
            return bool(conn.execute(
                "UPDATE perception SET done = 1, worker = ?, anchored = ?, T_measured_camera = ?, "
                "camera = ?, failure = ?, measurements = ? "
                "WHERE robot_id = ? AND session_id = ? AND seq = ? AND done = 0",
                (worker, int(result.anchored), pose, camera, failure, pack_measurements(result.measurements),
                 p.robot_id, p.session_id, p.seq)).rowcount == 1)

    def release_claim(self, worker: str, rowid: int) -> None:
        """See :meth:`~wardmap.server.store.protocol.PerceptionStore.release_claim`."""
        with self._write("perception: release a claim") as conn:
            conn.execute("UPDATE perception SET expires_s = 0 WHERE kf_rowid = ? AND worker = ? AND done = 0",
                         (rowid, worker))

    def perception_slots(self, after: int, upto: int, limit: int) -> list[PerceptionSlot]:
        """See :meth:`~wardmap.server.store.protocol.PerceptionStore.perception_slots`."""
        with self._read("perception: results") as conn:
            rows = conn.execute(
                "SELECT k.rowid, k.robot_id, k.session_id, k.seq, p.done, p.expires_s, p.anchored, "
                "p.T_measured_camera, p.camera, p.failure, p.measurements "
                "FROM keyframes k LEFT JOIN perception p USING (robot_id, session_id, seq) "
                "WHERE k.rowid > ? AND k.rowid <= ? ORDER BY k.rowid LIMIT ?",
                (after, upto, limit)).fetchall()
        out = []
        for rowid, robot_id, session_id, seq, done, expires_s, anchored, pose, camera, failure, blob in rows:
            key = (str(robot_id), str(session_id), int(seq))
            result = None
            if done:
                mapped = MappedPose(*key, None if pose is None else pose_from_blob(pose),
                                    None if camera is None else camera_from_json(camera))
                result = Perceived(mapped, bool(anchored), unpack_measurements(blob),
                                   None if failure is None else str(failure))
            out.append(PerceptionSlot(int(rowid), *key, result,
                                      None if done or expires_s is None else float(expires_s)))
        return out

    def count_unperceived(self, cursor: str) -> int:
        """See :meth:`~wardmap.server.store.protocol.PerceptionStore.count_unperceived`."""
        with self._read("perception: backlog") as conn:
            return int(conn.execute(
                "SELECT COUNT(*) FROM keyframes k LEFT JOIN perception p USING (robot_id, session_id, seq) "
                f"WHERE k.rowid > {_CURSOR_OF} AND (p.done IS NULL OR p.done = 0)", (cursor,)).fetchone()[0])

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
            self._fence(conn)
            conn.executemany(_INSERT_MAPPED, [mapped_params(p) for p in poses])

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
            self._fence(conn)
            conn.executemany(
                "INSERT INTO closed_sessions (robot_id, session_id, at_rowid) VALUES (?, ?, ?) "
                "ON CONFLICT DO NOTHING",
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
            self._fence(conn)
            conn.execute(
                "INSERT INTO association_checkpoint (id, last_rowid, config_key, state, written_s) "
                "VALUES (1, ?, ?, ?, ?) ON CONFLICT(id) DO UPDATE SET "
                "last_rowid = excluded.last_rowid, config_key = excluded.config_key, "
                "state = excluded.state, written_s = excluded.written_s",
                (c.last_rowid, c.config_key, c.state, c.written_s))

    def commit_graph(self, cursor: str, rowid: int, change: GraphChange) -> None:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.commit_graph`."""
        with self._write("back-end: store the pose graph") as conn:
            self._fence(conn)
            if change.nodes:
                first = int(conn.execute("SELECT COALESCE(MAX(node_order), 0) FROM graph_nodes")
                            .fetchone()[0])
                conn.executemany(
                    "INSERT INTO graph_nodes (robot_id, session_id, seq, node_order, stamp, "
                    "pose_source, T_odom_camera, T_map_camera, prior, codes) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT DO NOTHING",
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
            if change.pending is not None:
                conn.execute("INSERT INTO graph_pending (id, state) VALUES (1, ?) "
                             "ON CONFLICT (id) DO UPDATE SET state = excluded.state", (change.pending,))
            if change.bump_epoch:
                conn.execute("INSERT INTO graph_epoch (id, epoch) VALUES (1, 1) "
                             "ON CONFLICT (id) DO UPDATE SET epoch = graph_epoch.epoch + 1")
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

    def graph_pending(self) -> bytes | None:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.graph_pending`."""
        with self._read("back-end: pending votes") as conn:
            row = conn.execute("SELECT state FROM graph_pending WHERE id = 1").fetchone()
        return None if row is None else bytes(row[0])

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
                "SELECT g.robot_id, g.session_id, g.seq, g.stamp, g.pose_source, g.T_odom_camera, "
                "g.T_map_camera, g.prior FROM graph_nodes AS g JOIN (SELECT robot_id, MAX(node_order) "
                "AS last FROM graph_nodes GROUP BY robot_id) AS l "
                "ON g.robot_id = l.robot_id AND g.node_order = l.last").fetchall()
        return {str(r[0]): GraphNodeRow((str(r[0]), str(r[1]), int(r[2])), float(r[3]), pose_from_blob(r[5]),
                                        str(r[4]), None if r[6] is None else pose_from_blob(r[6]),
                                        None if r[7] is None else pose_from_blob(r[7]), b"")
                for r in rows}

    def map_trajectory(self, robot_id: str, session_id: str | None = None) -> Trajectory:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.map_trajectory`."""
        check_str(robot_id, "robot_id")
        where, params = "k.robot_id = ?", [robot_id]
        if session_id is not None:
            check_str(session_id, "session_id")
            where, params = where + " AND k.session_id = ?", [robot_id, session_id]
        with self._read("map trajectory") as conn:
            rows = conn.execute(
                "SELECT k.stamp, g.T_map_camera FROM keyframes k JOIN graph_nodes g "
                f"USING (robot_id, session_id, seq) WHERE {where} AND g.T_map_camera IS NOT NULL "
                "ORDER BY k.stamp, k.session_id, k.seq", params).fetchall()
        stamps = np.array([float(r[0]) for r in rows], dtype=np.float64)
        return stamps, poses_from_blobs([r[1] for r in rows])

    @staticmethod
    def _cursor_position(
        conn: Any, robot_id: str, after: tuple[object, ...]
    ) -> tuple[float, str, int]:
        session_id, seq = check_cursor(after)
        row = conn.execute(
            "SELECT stamp FROM keyframes WHERE robot_id = ? AND session_id = ? AND seq = ?",
            (robot_id, session_id, seq),
        ).fetchone()
        if row is None:
            raise StoreError(f"cursor {after!r:.80} names no keyframe of robot {robot_id!r}")
        return float(row[0]), session_id, seq

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
                f"SELECT {TOKEN_COLUMNS} FROM api_tokens WHERE token_id = ?", (token_id,)
            ).fetchone()
        return None if row is None else token_from_row(row)

    def tokens(self) -> list[TokenRecord]:
        """See :meth:`~wardmap.server.store.protocol.TokenStore.tokens`."""
        with self._read("tokens: list") as conn:
            rows = conn.execute(
                f"SELECT {TOKEN_COLUMNS} FROM api_tokens ORDER BY created_s, token_id"
            ).fetchall()
        return [token_from_row(r) for r in rows]

    def revoke_token(self, token_id: str, revoked_s: float) -> bool:
        """See :meth:`~wardmap.server.store.protocol.TokenStore.revoke_token`."""
        with self._write("tokens: revoke") as conn:
            cur = conn.execute(
                "UPDATE api_tokens SET revoked_s = ? WHERE token_id = ? AND revoked_s IS NULL",
                (float(revoked_s), token_id))
            return cur.rowcount == 1

    # ------------------------------------------------------------------ object map internals

    def _existing(self, conn: Any, ids: Sequence[int]) -> set[int]:
        if not ids:
            return set()
        rows = conn.execute(f"SELECT object_id FROM objects WHERE object_id {self._IN_IDS}",
                            (self._ids(ids),))
        return {int(r[0]) for r in rows}

    def _refresh_derived(self, conn: Any, ids: Sequence[int]) -> None:
        """Recompute count, first/last seen and robots of ``ids`` from their observations."""
        arg = (self._ids(ids),)
        conn.execute(
            "UPDATE objects SET "
            "n_observations = (SELECT COUNT(*) FROM observations AS b "
            "WHERE b.object_id = objects.object_id), "
            "first_seen_s = COALESCE((SELECT MIN(added_s) FROM observations AS b "
            "WHERE b.object_id = objects.object_id AND b.added_s < objects.first_seen_s), first_seen_s), "
            "last_seen_s = COALESCE((SELECT MAX(added_s) FROM observations AS b "
            "WHERE b.object_id = objects.object_id), first_seen_s) "
            f"WHERE object_id {self._IN_IDS}",
            arg,
        )
        conn.execute(f"DELETE FROM object_robots WHERE object_id {self._IN_IDS}", arg)
        conn.execute(
            "INSERT INTO object_robots (object_id, robot_id) SELECT DISTINCT object_id, robot_id "
            f"FROM observations WHERE object_id {self._IN_IDS}",
            arg,
        )

    def _robots(self, conn: Any, ids: Sequence[int]) -> dict[int, tuple[str, ...]]:
        if not ids:
            return {}
        rows = conn.execute(
            f"SELECT object_id, robot_id FROM object_robots WHERE object_id {self._IN_IDS} "
            "ORDER BY object_id, robot_id",
            (self._ids(ids),),
        ).fetchall()
        out: dict[int, list[str]] = {}
        for oid, robot in rows:
            out.setdefault(int(oid), []).append(str(robot))
        return {k: tuple(v) for k, v in out.items()}

    def _records(self, conn: Any, ids: Sequence[int]) -> dict[int, ObjectRecord]:
        rows = conn.execute(
            f"SELECT {OBJECT_COLUMNS} FROM objects AS o WHERE o.object_id {self._IN_IDS}",
            (self._ids(ids),),
        ).fetchall()
        robots = self._robots(conn, [int(r[0]) for r in rows])
        return {int(r[0]): object_record(r, robots.get(int(r[0]), ())) for r in rows}

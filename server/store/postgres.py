"""The PostgreSQL map store (psycopg 3 with a ``psycopg_pool`` connection pool).

For a hospital with several wards and map servers: the same :class:`~wardmap.server.store.
protocol.MapStore` as the SQLite store, on a database server. Open with
``open_store("postgresql://USER@HOST:PORT/DB")`` (:meth:`PostgresMapStore.open`).

Guarantees (as ``sqlite.py``'s):

- An :meth:`~PostgresMapStore.insert` that returned is committed: the server acknowledged the
  ``COMMIT`` (with PostgreSQL's default ``synchronous_commit = on`` the commit record is on the
  server's disk; a database with it off is logged as a warning at open). Every other write is
  one transaction too.
- Idempotent on ``(robot_id, session_id, seq)``, also between concurrent writers (several
  threads or servers): keyframe inserts take a transaction-scoped advisory lock
  (:data:`INSERT_LOCK`), look the key up and insert (``ON CONFLICT DO NOTHING`` as a second
  guard); the second writer of a key waits for the first to commit and answers
  ``"duplicate"``. The lock also makes insertion order (the ``rowid`` identity column that the
  mapping stage's cursors read) equal to commit order, so a cursor never passes a keyframe
  that commits later with a smaller ``rowid``; and a keyframe found stored consumes no
  ``rowid`` (no gaps).
- Keyframes are never deleted or rewritten.

Failures: a psycopg error becomes :class:`StoreUnavailableError` when the database cannot
serve *now* (unreachable or restarting server, connection lost, pool exhausted past
:data:`POOL_TIMEOUT_S`, disk full, out of connections, read-only standby, lock or
serialisation conflict), :class:`StoreDamagedError` for PostgreSQL's data-corruption states
(``XX001``, ``XX002``), or a plain :class:`StoreError`; ingest acks ``retry`` for the first two.
:meth:`PostgresMapStore.writable` is the readiness probe.

Connection: the password never travels in the URL (refused with a one-line error): it comes
from the ``password`` argument (``wardmap server --db-password-file FILE``), else the
``WARDMAP_DB_PASSWORD`` environment variable, else libpq's own ``PGPASSFILE``/``~/.pgpass``.
Other libpq parameters may go in the URL's query (``?sslmode=require&connect_timeout=5``);
store options there too (:class:`PostgresOptions`: ``pool_size``, ``postgis``).

Threads: every call borrows a pooled connection for its duration (autocommit; a write is one
``BEGIN`` .. ``COMMIT``; a read that must see one snapshot runs in a ``REPEATABLE READ, READ
ONLY`` transaction). Pooled connections are checked before use, so a restarted server costs
one failed call at most.

Storage: the schema is ``schema.py``'s step list in its PostgreSQL text; the one-row table
``wardmap_schema`` holds the application mark, the schema version and which object index
the database has. The object index: with PostGIS (the extension present, or available and
creatable by the user), an n-D GiST index on the objects' 3D bounds (``schema.POSTGIS_BOUNDS``,
searched with ``&&&``); without it, a GiST index on the bounds' xy box (built-in ``box``),
then z and the exact centre distance. The choice is made when the database is created and
kept; a database created without PostGIS keeps the fallback.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Final, NoReturn

import numpy as np
from numpy.typing import NDArray

from wardmap.server.perception.types import ObjectMeasurement
from wardmap.server.store import schema
from wardmap.server.store.codec import (
    camera_from_json,
    pack_measurement,
    pose_blob,
    pose_from_blob,
    poses_from_blobs,
    unpack_measurement,
)
from wardmap.server.store.records import (
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
from wardmap.server.store.rows import (
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
from wardmap.shared.wire import KeyframeMsg

if TYPE_CHECKING:
    import psycopg
    from psycopg_pool import ConnectionPool

log = logging.getLogger(__name__)

SCHEMES: Final = ("postgresql://", "postgres://")
APPLICATION_ID: Final = 0x77726D73  # "wrms", as the SQLite file's application_id
INSERT_LOCK: Final = APPLICATION_ID
"""The advisory lock key keyframe inserts take (``pg_advisory_xact_lock``), see the module docstring."""
PASSWORD_ENV: Final = "WARDMAP_DB_PASSWORD"
INSTALL_HINT: Final = "the PostgreSQL store needs psycopg 3 and psycopg-pool: pip install 'wardmap[postgres]'"
PASSWORD_SOURCES: Final = (
    f"give it with --db-password-file FILE, the {PASSWORD_ENV} environment variable, "
    "or libpq's PGPASSFILE/~/.pgpass"
)
POOL_TIMEOUT_S: Final = 5.0
"""Longest a call waits for a pooled connection before it fails as :class:`StoreUnavailableError`."""
CONNECT_TIMEOUT_S: Final = 10
"""libpq's ``connect_timeout`` unless the URL gives one."""
PROBE_TIMEOUT_S: Final = 1.0
"""Longest :meth:`PostgresMapStore.writable` waits for a connection or a lock."""
DEFAULT_POOL_SIZE: Final = 8
# PostgreSQL error classes meaning "not now" (psycopg raises most as OperationalError too).
_DAMAGED_STATES: Final = frozenset({"XX001", "XX002"})  # data_corrupted, index_corrupted
_UNAVAILABLE_STATES: Final = frozenset({"25006", "40001", "40P01", "55P03", "57014"})
_MAPPED_SQL: Final = (
    "INSERT INTO mapped_keyframes (robot_id, session_id, seq, T_map_camera, camera) "
    "VALUES (%s, %s, %s, %s, %s) ON CONFLICT (robot_id, session_id, seq) DO UPDATE SET "
    "T_map_camera = excluded.T_map_camera, camera = excluded.camera"
)
_CURSOR_SQL: Final = (
    "INSERT INTO pipeline_cursor (name, last_rowid) VALUES (%s, %s) "
    "ON CONFLICT (name) DO UPDATE SET last_rowid = excluded.last_rowid"
)


def _import() -> tuple[Any, Any]:
    """``(psycopg, psycopg_pool)``, or StoreError with the install hint."""
    try:
        import psycopg
        import psycopg_pool
    except ImportError as exc:
        raise StoreError(f"{INSTALL_HINT} ({exc})") from exc
    return psycopg, psycopg_pool


def classify_postgres_error(exc: BaseException) -> type[StoreError]:
    """Which :class:`StoreError` a psycopg (or pool) failure is; see the module docstring."""
    psycopg, psycopg_pool = _import()
    state = getattr(exc, "sqlstate", None)
    if state in _DAMAGED_STATES:
        return StoreDamagedError
    if state in _UNAVAILABLE_STATES or isinstance(
        exc, psycopg.OperationalError | psycopg.InterfaceError | psycopg_pool.PoolTimeout
    ):
        return StoreUnavailableError
    return StoreError


def read_password_file(path: str | Path) -> str:
    """The password in ``path`` (its first line, without the line break); StoreError if it is
    unreadable or empty."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise StoreError(f"cannot read the database password file {path}: {exc}") from exc
    password = text.splitlines()[0] if text else ""
    if not password:
        raise StoreError(f"the database password file {path} is empty")
    return password


@dataclass(frozen=True, slots=True)
class PostgresOptions:
    """Settings of the PostgreSQL store, given in the URL's query next to libpq's own parameters:
    ``postgresql://wardmap@db:5432/wardmap?pool_size=16&postgis=off``.

    Attributes:
        pool_size: the connection pool's largest size (1-100).
        postgis: when creating the schema, use PostGIS for the object index where the server has
            it (``on``), or never (``off``: the GiST box fallback, no extension is created).
    """

    pool_size: int = DEFAULT_POOL_SIZE
    postgis: bool = True


def parse_url(url: str) -> tuple[dict[str, Any], PostgresOptions, str]:
    """``(libpq parameters, options, URL shown in messages)`` of a ``postgresql://`` URL.

    Raises:
        StoreError: a malformed URL, a password in it, or a bad option.
    """
    psycopg, _ = _import()
    # Messages show the URL without its query (libpq parameters may hold secrets) or password.
    shown = re.sub(r"//([^:/@]*):[^@/]*@", r"//\1:***@", url.partition("?")[0])
    options = PostgresOptions()
    base, _, query = url.partition("?")
    kept = []
    for part in query.split("&") if query else ():
        key, _, value = part.partition("=")
        if key == "pool_size":
            if not value.isdigit() or not 1 <= int(value) <= 100:
                raise StoreError(f"store option pool_size must be an int in [1, 100], got {value!r:.40}")
            options = dataclasses.replace(options, pool_size=int(value))
        elif key == "postgis":
            if value not in ("on", "off"):
                raise StoreError(f"store option postgis must be on or off, got {value!r:.40}")
            options = dataclasses.replace(options, postgis=value == "on")
        else:
            kept.append(part)
    clean = base + ("?" + "&".join(kept) if kept else "")
    try:
        params: dict[str, Any] = psycopg.conninfo.conninfo_to_dict(clean)
    except psycopg.Error as exc:
        raise StoreError(f"bad store URL {shown!r}: {_first_line(exc)}") from exc
    if params.get("password") is not None:
        raise StoreError(
            f"store URL {shown!r} carries a password: never put it on the command line; {PASSWORD_SOURCES}"
        )
    return params, options, shown


class PostgresMapStore:
    """The PostgreSQL map store: implements :class:`~wardmap.server.store.protocol.MapStore`.
    Create with :func:`~wardmap.server.store.open_store` or :meth:`open`. Thread safe (a pool
    of connections; see the module docstring).

    Attributes:
        url: the database's URL as shown in messages (no password, no query).
        object_index: ``"postgis"`` or ``"postgres"`` (the GiST box fallback).
    """

    def __init__(
        self, pool: ConnectionPool[psycopg.Connection[Any]], url: str, object_index: schema.Dialect
    ) -> None:
        """Internal: use :meth:`open`."""
        self._pool = pool
        self.url = url
        self.object_index = object_index
        self._health_lock = threading.Lock()  # guards the two fields below
        # what -> (why its last write failed as unavailable, whether a passing probe clears it)
        self._write_faults: dict[str, tuple[str, bool]] = {}
        self._damage: str | None = None  # first damage seen; sticky
        self._closed = False

    # ------------------------------------------------------------------ life cycle

    @classmethod
    def open(cls, url: str, password: str | None = None) -> PostgresMapStore:
        """Connect to the database ``url`` names, create or migrate its schema, start the pool.

        Args:
            url: ``postgresql://USER@HOST:PORT/DB`` (libpq URL; no password in it).
            password: the password; None: :data:`PASSWORD_ENV`, else libpq's own sources.

        Raises:
            StoreUnavailableError: the server cannot be reached (one line naming it).
            StoreError: psycopg is missing, a password in the URL, authentication failed, the
                database does not exist, it is not a wardmap store or is newer than this build.
        """
        psycopg, psycopg_pool = _import()
        params, options, shown = parse_url(url)
        if password is None:
            password = os.environ.get(PASSWORD_ENV) or None
        if password is not None:
            params["password"] = password
        params.setdefault("connect_timeout", CONNECT_TIMEOUT_S)
        params.setdefault("application_name", "wardmap")
        try:
            conn = psycopg.connect(**params, autocommit=True)
        except psycopg.Error as exc:
            raise _connect_error(exc, shown, params) from exc
        try:
            with conn:
                object_index = _migrate(conn, shown, postgis=options.postgis)
                if str(_one(conn.execute("SHOW synchronous_commit"))[0]) in ("off", "local"):
                    log.warning("keyframe store %s: synchronous_commit is off: an acked keyframe may be "
                                "lost if the database server crashes", shown)
        except psycopg.Error as exc:
            raise classify_postgres_error(exc)(f"keyframe store {shown}: cannot prepare the database: "
                                               f"{_first_line(exc)}") from exc
        pool = psycopg_pool.ConnectionPool(
            kwargs={**params, "autocommit": True}, min_size=1, max_size=options.pool_size, open=False,
            timeout=POOL_TIMEOUT_S, check=psycopg_pool.ConnectionPool.check_connection,
            reconnect_timeout=60.0, name="wardmap-store",
        )
        try:
            pool.open(wait=True, timeout=CONNECT_TIMEOUT_S)
        except psycopg_pool.PoolTimeout as exc:
            pool.close()
            raise StoreUnavailableError(
                f"keyframe store {shown}: the connection pool could not start"
            ) from exc
        log.info("keyframe store %s open (object index: %s)", shown, object_index)
        return cls(pool, shown, object_index)

    def close(self) -> None:
        """Close the pool (idempotent); calls after it raise StoreError."""
        if self._closed:
            return
        self._closed = True
        self._pool.close()

    def __enter__(self) -> PostgresMapStore:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # ------------------------------------------------------------------ keyframes

    def insert(self, msg: KeyframeMsg, payload: bytes, received_s: float) -> InsertResult:
        """See :meth:`~wardmap.server.store.protocol.KeyframeStore.insert` and the module
        docstring (first copy wins, as :meth:`SqliteMapStore.insert` explains)."""
        key, data, t = insert_args(msg, payload, received_s)
        pose = pose_blob(msg.T_odom_camera)
        with self._write("insert") as conn:
            conn.execute("SELECT pg_advisory_xact_lock(%s)", (INSERT_LOCK,))
            row = conn.execute(
                "SELECT payload = %s FROM keyframes WHERE robot_id = %s AND session_id = %s AND seq = %s",
                (data, *key),
            ).fetchone()
            stored = row is None and conn.execute(
                "INSERT INTO keyframes (robot_id, session_id, seq, stamp, received_s, pose_source, "
                "payload_bytes, T_odom_camera, payload) VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s) "
                "ON CONFLICT (robot_id, session_id, seq) DO NOTHING",
                (*key, float(msg.stamp), t, str(msg.pose_source), len(data), pose, data),
            ).rowcount == 1
            if not stored:
                if row is not None and not row[0]:
                    log.warning("keyframe %s/%s/%d arrived again with different bytes (%d bytes); "
                                "keeping the first copy", *key, len(data))
                return "duplicate"
            conn.execute(
                "INSERT INTO robots (robot_id, first_seen_s, last_seen_s) VALUES (%s, %s, %s) "
                "ON CONFLICT (robot_id) DO UPDATE SET "
                "first_seen_s = LEAST(robots.first_seen_s, excluded.first_seen_s), "
                "last_seen_s = GREATEST(robots.last_seen_s, excluded.last_seen_s)",
                (msg.robot_id, t, t),
            )
            conn.execute(
                "INSERT INTO sessions (robot_id, session_id, started_s) VALUES (%s, %s, %s) "
                "ON CONFLICT (robot_id, session_id) DO UPDATE SET "
                "started_s = LEAST(sessions.started_s, excluded.started_s)",
                (msg.robot_id, msg.session_id, t),
            )
        return "stored"

    def count_rejection(self, reason: str, n: int = 1) -> None:
        """See :meth:`~wardmap.server.store.protocol.KeyframeStore.count_rejection`."""
        check_reason(reason, n)
        with self._write("count_rejection") as conn:
            conn.execute(
                "INSERT INTO rejections (reason, count) VALUES (%s, %s) "
                "ON CONFLICT (reason) DO UPDATE SET count = rejections.count + excluded.count",
                (reason, n),
            )

    def writable(self) -> tuple[bool, str]:
        """Whether a write can commit now: ``(True, "ok")`` or ``(False, why)``; never raises.

        Not writable when: closed; damage was seen (sticky); a probe transaction (a one-row
        insert, rolled back, within :data:`PROBE_TIMEOUT_S`) fails: server down or restarting,
        no connection free, a read-only standby, a lock held; or the last write of some kind
        failed as :class:`StoreUnavailableError` and none of that kind succeeded since, unless
        it failed only for the connection (a passing probe clears that)."""
        if self._closed:
            return False, "closed"
        with self._health_lock:
            damage = self._damage
        if damage is not None:
            return False, f"damaged: {damage}"
        timeout_ms = int(PROBE_TIMEOUT_S * 1000)
        try:
            with (self._db_errors("readiness probe"), self._pool.connection(timeout=PROBE_TIMEOUT_S) as conn,
                  conn.transaction(force_rollback=True)):
                conn.execute(f"SET LOCAL lock_timeout = {timeout_ms}")
                conn.execute(f"SET LOCAL statement_timeout = {timeout_ms}")
                conn.execute("INSERT INTO rejections (reason, count) VALUES ('readiness probe', 0) "
                             "ON CONFLICT (reason) DO NOTHING")
        except StoreError as exc:
            return False, str(exc)
        with self._health_lock:
            self._write_faults = {w: f for w, f in self._write_faults.items() if not f[1]}
            faults = sorted(why for why, _ in self._write_faults.values())
        if faults:
            return False, f"last write failed: {faults[0]}"
        return True, "ok"

    def rejections(self) -> dict[str, int]:
        """See :meth:`~wardmap.server.store.protocol.KeyframeStore.rejections`."""
        with self._read("rejections") as conn:
            rows = conn.execute("SELECT reason, count FROM rejections ORDER BY reason").fetchall()
        return {str(r[0]): int(r[1]) for r in rows}

    def robots(self) -> list[RobotSummary]:
        """See :meth:`~wardmap.server.store.protocol.KeyframeStore.robots`."""
        with self._read("robots") as conn:
            rows = conn.execute(
                "SELECT r.robot_id, "
                "(SELECT COUNT(*) FROM keyframes AS k WHERE k.robot_id = r.robot_id), "
                "(SELECT COUNT(*) FROM sessions AS s WHERE s.robot_id = r.robot_id), "
                "r.first_seen_s, r.last_seen_s FROM robots AS r ORDER BY r.robot_id"
            ).fetchall()
        return [RobotSummary(str(r[0]), int(r[1]), int(r[2]), float(r[3]), float(r[4])) for r in rows]

    def keyframes(self, robot_id: str, *, after: Cursor | None = None, limit: int = 100) -> KeyframePage:
        """See :meth:`~wardmap.server.store.protocol.KeyframeStore.keyframes` (and the SQLite
        store's docstring of it)."""
        check_str(robot_id, "robot_id")
        check_limit(limit)
        columns = "robot_id, session_id, seq, stamp, received_s, pose_source, payload_bytes"
        where = ""
        params: tuple[object, ...] = ()
        with self._read("keyframes") as conn:
            if isinstance(after, tuple):
                session_id, seq = check_cursor(after)
                row = conn.execute(
                    "SELECT stamp FROM keyframes WHERE robot_id = %s AND session_id = %s AND seq = %s",
                    (robot_id, session_id, seq),
                ).fetchone()
                if row is None:
                    raise StoreError(f"cursor {after!r:.80} names no keyframe of robot {robot_id!r}")
                where = " AND (stamp, session_id, seq) > (%s, %s, %s)"
                params = (float(row[0]), session_id, seq)
            elif after is not None:
                where, params = " AND stamp > %s", (check_seconds(after, "after", positive=False),)
            rows = conn.execute(
                f"SELECT {columns} FROM keyframes WHERE robot_id = %s{where} "
                "ORDER BY stamp, session_id, seq LIMIT %s",
                (robot_id, *params, limit + 1),
            ).fetchall()
        page = [KeyframeRow(str(r[0]), str(r[1]), int(r[2]), float(r[3]), float(r[4]), str(r[5]), int(r[6]))
                for r in rows[:limit]]
        more = len(rows) > limit
        return KeyframePage(page, (page[-1].session_id, page[-1].seq) if more else None)

    def trajectory(self, robot_id: str, session_id: str | None = None) -> Trajectory:
        """See :meth:`~wardmap.server.store.protocol.KeyframeStore.trajectory`."""
        check_str(robot_id, "robot_id")
        where, params = "robot_id = %s", [robot_id]
        if session_id is not None:
            where, params = where + " AND session_id = %s", [robot_id, check_str(session_id, "session_id")]
        with self._read("trajectory") as conn:
            rows = conn.execute(f"SELECT stamp, T_odom_camera FROM keyframes WHERE {where} "
                                "ORDER BY stamp, session_id, seq", params).fetchall()
        return np.array([float(r[0]) for r in rows], dtype=np.float64), poses_from_blobs([r[1] for r in rows])

    def payload(self, robot_id: str, session_id: str, seq: int) -> bytes | None:
        """See :meth:`~wardmap.server.store.protocol.KeyframeStore.payload`."""
        key = (check_str(robot_id, "robot_id"), check_str(session_id, "session_id"), check_seq(seq))
        with self._read("payload") as conn:
            row = conn.execute(
                "SELECT payload FROM keyframes WHERE robot_id = %s AND session_id = %s AND seq = %s", key
            ).fetchone()
        return None if row is None else bytes(row[0])

    def stats(self) -> StoreStats:
        """See :meth:`~wardmap.server.store.protocol.KeyframeStore.stats`."""
        with self._snapshot("stats") as conn:
            row = _one(conn.execute(
                "SELECT (SELECT COUNT(*) FROM robots), (SELECT COUNT(*) FROM sessions), "
                "(SELECT COUNT(*) FROM keyframes), (SELECT COALESCE(SUM(payload_bytes), 0) FROM keyframes), "
                "(SELECT COALESCE(SUM(count), 0) FROM rejections), (SELECT version FROM wardmap_schema)"
            ))
        return StoreStats(*(int(v) for v in row))

    # ------------------------------------------------------------------ objects

    def write_objects(
        self, objects: Sequence[ObjectRow], observations: Sequence[Observation], now_s: float
    ) -> list[ObjectWrite]:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.write_objects`."""
        obj_rows = [object_params(o, now_s) for o in objects]
        obs_rows = [observation_params(o, now_s) for o in observations]
        ids = [int(o.object_id) for o in objects]
        with self._write("object map upsert") as conn:
            existing = _existing(conn, ids)
            conn.cursor().executemany(
                "INSERT INTO objects (object_id, category, confidence, T_world_object, x, y, z, yaw, "
                "qx, qy, qz, qw, size_x, size_y, size_z, min_x, min_y, min_z, max_x, max_y, max_z, "
                "color_r, color_g, color_b, n_observations, first_seen_s, last_seen_s, confirmed) "
                "VALUES (%(object_id)s, %(category)s, %(confidence)s, %(T)s, %(x)s, %(y)s, %(z)s, %(yaw)s, "
                "%(qx)s, %(qy)s, %(qz)s, %(qw)s, %(size_x)s, %(size_y)s, %(size_z)s, "
                "%(min_x)s, %(min_y)s, %(min_z)s, %(max_x)s, %(max_y)s, %(max_z)s, "
                "%(color_r)s, %(color_g)s, %(color_b)s, 0, %(now)s, %(now)s, %(confirmed)s) "
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
            touched: dict[int, None] = dict.fromkeys(ids)
            if obs_rows:
                missing = {int(r["object_id"]) for r in obs_rows} - set(ids)
                missing -= _existing(conn, sorted(missing))
                if missing:
                    raise UnknownObjectError(
                        f"observations name objects that are neither given nor stored: {sorted(missing)[:10]}"
                    )
                for row in obs_rows:
                    old = conn.execute(
                        "SELECT object_id FROM observations WHERE robot_id = %(robot_id)s AND "
                        "session_id = %(session_id)s AND seq = %(seq)s AND box_x1 = %(box_x1)s AND "
                        "box_y1 = %(box_y1)s AND box_x2 = %(box_x2)s AND box_y2 = %(box_y2)s",
                        row,
                    ).fetchone()
                    if old is not None:
                        touched.setdefault(int(old[0]))
                    touched.setdefault(int(row["object_id"]))
                conn.cursor().executemany(
                    "INSERT INTO observations (object_id, robot_id, session_id, seq, stamp, added_s, "
                    "category, confidence, box_x1, box_y1, box_x2, box_y2, T_world_object, "
                    "size_x, size_y, size_z) VALUES (%(object_id)s, %(robot_id)s, %(session_id)s, %(seq)s, "
                    "%(stamp)s, %(now)s, %(category)s, %(confidence)s, %(box_x1)s, %(box_y1)s, %(box_x2)s, "
                    "%(box_y2)s, %(T)s, %(size_x)s, %(size_y)s, %(size_z)s) "
                    "ON CONFLICT (robot_id, session_id, seq, box_x1, box_y1, box_x2, box_y2) DO UPDATE SET "
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
                conn.execute("DELETE FROM observations WHERE object_id = %s", (oid,))
            else:
                conn.execute("UPDATE observations SET object_id = %s WHERE object_id = %s", (target, oid))
            conn.execute("DELETE FROM object_robots WHERE object_id = %s", (oid,))
            conn.execute("DELETE FROM objects WHERE object_id = %s", (oid,))
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
            self.object_index, category=category, near=near, radius_m=radius_m, min_confidence=min_confidence,
            robot=robot, include_unconfirmed=include_unconfirmed, limit=limit, offset=offset,
        )
        with self._read("object map query") as conn:
            rows = conn.execute(_pyformat(sql), params).fetchall()
            page = rows[:limit]
            robots = _robots(conn, [int(r[0]) for r in page])
        hits = [ObjectHit(object_record(r, robots.get(int(r[0]), ())),
                          None if near is None else math.sqrt(max(float(r[28]), 0.0))) for r in page]
        return ObjectPage(hits, offset + limit if len(rows) > limit else None)

    def object_detail(self, object_id: int, max_observations: int) -> ObjectDetail | None:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.object_detail`."""
        oid = object_id
        with self._snapshot("object map get") as conn:
            records = _records(conn, [oid])
            if oid not in records:
                return None
            obs_rows = conn.execute(
                f"SELECT {OBS_COLUMNS} FROM observations WHERE object_id = %s "
                "ORDER BY added_s DESC, observation_id DESC LIMIT %s",
                (oid, max_observations),
            ).fetchall()
            kf_rows = conn.execute(
                "SELECT DISTINCT b.robot_id, b.session_id, b.seq, b.stamp, "
                "EXISTS (SELECT 1 FROM keyframes AS k WHERE k.robot_id = b.robot_id AND "
                "k.session_id = b.session_id AND k.seq = b.seq) "
                "FROM (SELECT robot_id, session_id, seq, stamp FROM observations WHERE object_id = %s "
                "ORDER BY added_s DESC, observation_id DESC LIMIT %s) AS b "
                "ORDER BY b.stamp, b.robot_id, b.session_id, b.seq",
                (oid, max_observations),
            ).fetchall()
        keyframes = [KeyframeRef(str(r[0]), str(r[1]), int(r[2]), float(r[3]), bool(r[4])) for r in kf_rows]
        return ObjectDetail(records[oid], [observation_record(r) for r in obs_rows], keyframes)

    def count_objects(self, *, unconfirmed: bool | None = None) -> int:
        """See :meth:`~wardmap.server.store.protocol.ObjectStore.count_objects`."""
        where = "" if unconfirmed is None else f" WHERE confirmed = {0 if unconfirmed else 1}"
        with self._read("object map count") as conn:
            return int(_one(conn.execute(f"SELECT COUNT(*) FROM objects{where}"))[0])

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
            row = conn.execute("SELECT last_rowid FROM pipeline_cursor WHERE name = %s", (name,)).fetchone()
        return int(row[0]) if row else 0

    def next_keyframes(self, after: int, limit: int) -> list[StoredKeyframe]:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.next_keyframes`."""
        with self._read("mapping: next keyframes") as conn:
            rows = conn.execute(
                "SELECT rowid, robot_id, session_id, seq, payload FROM keyframes WHERE rowid > %s "
                "ORDER BY rowid LIMIT %s", (after, limit)).fetchall()
        return [StoredKeyframe(int(r[0]), str(r[1]), str(r[2]), int(r[3]), bytes(r[4])) for r in rows]

    def count_keyframes_after(self, after: int) -> int:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.count_keyframes_after`."""
        with self._read("mapping: backlog") as conn:
            row = _one(conn.execute("SELECT COUNT(*) FROM keyframes WHERE rowid > %s", (after,)))
        return int(row[0])

    def session_has_keyframes_after(self, robot_id: str, session_id: str, after: int) -> bool:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.session_has_keyframes_after`."""
        with self._read("mapping: idle sessions") as conn:
            row = conn.execute(
                "SELECT 1 FROM keyframes WHERE robot_id = %s AND session_id = %s AND rowid > %s LIMIT 1",
                (robot_id, session_id, after)).fetchone()
        return row is not None

    def commit_keyframe(
        self, cursor: str, rowid: int, pose: MappedPose, measurements: Sequence[ObjectMeasurement],
        *, anchored: bool,
    ) -> None:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.commit_keyframe`."""
        rows = [(pose.robot_id, pose.session_id, pose.seq, int(anchored), pack_measurement(m))
                for m in measurements]
        with self._write("mapping: store measurements") as conn:
            conn.cursor().executemany(
                "INSERT INTO measurements (robot_id, session_id, seq, anchored, payload) "
                "VALUES (%s, %s, %s, %s, %s)", rows)
            conn.execute(_MAPPED_SQL, mapped_params(pose))
            conn.execute(_CURSOR_SQL, (cursor, rowid))

    def unmapped_keyframes(self, upto: int, limit: int) -> list[KeyframeKey]:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.unmapped_keyframes`."""
        with self._read("mapping: keyframes to backfill") as conn:
            rows = conn.execute(
                "SELECT k.rowid, k.robot_id, k.session_id, k.seq FROM keyframes k "
                "LEFT JOIN mapped_keyframes mk USING (robot_id, session_id, seq) "
                "WHERE k.rowid <= %s AND mk.robot_id IS NULL ORDER BY k.rowid LIMIT %s",
                (upto, limit)).fetchall()
        return [KeyframeKey(int(r[0]), str(r[1]), str(r[2]), int(r[3])) for r in rows]

    def record_mapped(self, poses: Sequence[MappedPose]) -> None:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.record_mapped`."""
        with self._write("mapping: backfill mapped keyframes") as conn:
            conn.cursor().executemany(_MAPPED_SQL, [mapped_params(p) for p in poses])

    def anchored_keyframes(self, after: int, upto: int, limit: int) -> list[AnchoredKeyframe]:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.anchored_keyframes`."""
        with self._snapshot("mapping: replay") as conn:
            rows = conn.execute(
                "SELECT k.rowid, k.robot_id, k.session_id, k.seq, g.T_map_camera, mk.camera, mk.T_map_camera "
                "FROM keyframes k JOIN mapped_keyframes mk USING (robot_id, session_id, seq) "
                "JOIN graph_nodes g USING (robot_id, session_id, seq) "
                "WHERE k.rowid > %s AND k.rowid <= %s AND mk.T_map_camera IS NOT NULL "
                "AND g.T_map_camera IS NOT NULL ORDER BY k.rowid LIMIT %s",
                (after, upto, limit)).fetchall()
            if not rows:
                return []
            by_key: dict[tuple[str, str, int], list[ObjectMeasurement]] = {}
            for robot_id, session_id, seq, payload in conn.execute(
                "SELECT m.robot_id, m.session_id, m.seq, m.payload FROM measurements m "
                "JOIN keyframes k USING (robot_id, session_id, seq) "
                "WHERE k.rowid > %s AND k.rowid <= %s ORDER BY k.rowid, m.measurement_id",
                (after, int(rows[-1][0])),
            ):
                by_key.setdefault((str(robot_id), str(session_id), int(seq)), []).append(
                    unpack_measurement(bytes(payload)))
        out = []
        for rowid, robot_id, session_id, seq, pose, camera, measured in rows:
            key = (str(robot_id), str(session_id), int(seq))
            out.append(AnchoredKeyframe(int(rowid), *key, pose_from_blob(pose), camera_from_json(camera),
                                        by_key.get(key, []), pose_from_blob(measured)))
        return out

    def count_measurements(self) -> int:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.count_measurements`."""
        with self._read("mapping: measurements") as conn:
            return int(_one(conn.execute("SELECT COUNT(*) FROM measurements"))[0])

    def close_sessions(self, sessions: Sequence[tuple[str, str]], at_rowid: int) -> None:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.close_sessions`."""
        with self._write("mapping: close idle sessions") as conn:
            conn.cursor().executemany(
                "INSERT INTO closed_sessions (robot_id, session_id, at_rowid) VALUES (%s, %s, %s) "
                "ON CONFLICT DO NOTHING",
                [(robot_id, session_id, at_rowid) for robot_id, session_id in sessions])

    def closed_sessions(self, first: int = 0, last: int | None = None) -> list[ClosedSession]:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.closed_sessions`."""
        upto = "" if last is None else " AND at_rowid <= %s"
        with self._read("mapping: closed sessions") as conn:
            rows = conn.execute(
                f"SELECT at_rowid, robot_id, session_id FROM closed_sessions WHERE at_rowid >= %s{upto} "
                "ORDER BY at_rowid, robot_id, session_id",
                (first,) if last is None else (first, last)).fetchall()
        return [ClosedSession(int(r[0]), str(r[1]), str(r[2])) for r in rows]

    def checkpoint(self) -> Checkpoint | None:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.checkpoint`."""
        with self._read("mapping: association checkpoint") as conn:
            row = conn.execute("SELECT last_rowid, config_key, state, written_s FROM association_checkpoint "
                               "WHERE id = 1").fetchone()
        return None if row is None else Checkpoint(int(row[0]), str(row[1]), bytes(row[2]), float(row[3]))

    def save_checkpoint(self, checkpoint: Checkpoint) -> None:
        """See :meth:`~wardmap.server.store.protocol.MappingStore.save_checkpoint`."""
        c = checkpoint
        with self._write("mapping: association checkpoint") as conn:
            conn.execute(
                "INSERT INTO association_checkpoint (id, last_rowid, config_key, state, written_s) "
                "VALUES (1, %s, %s, %s, %s) ON CONFLICT (id) DO UPDATE SET "
                "last_rowid = excluded.last_rowid, config_key = excluded.config_key, "
                "state = excluded.state, written_s = excluded.written_s",
                (c.last_rowid, c.config_key, c.state, c.written_s))

    # ------------------------------------------------------------------ the back-end's pose graph

    def commit_graph(self, cursor: str, rowid: int, change: GraphChange) -> None:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.commit_graph`."""
        with self._write("back-end: store the pose graph") as conn:
            cur = conn.cursor()
            if change.nodes:
                (first,) = _one(conn.execute("SELECT COALESCE(MAX(node_order), 0) FROM graph_nodes"))
                cur.executemany(
                    "INSERT INTO graph_nodes (robot_id, session_id, seq, node_order, stamp, "
                    "pose_source, T_odom_camera, T_map_camera, prior, codes) "
                    "VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s) ON CONFLICT DO NOTHING",
                    [(*n.key, first + 1 + i, n.stamp, n.pose_source, pose_blob(n.T_odom_camera),
                      None if n.T_map_camera is None else pose_blob(n.T_map_camera),
                      None if n.prior_T_map_odom is None else pose_blob(n.prior_T_map_odom), n.codes)
                     for i, n in enumerate(change.nodes)])
            if change.edges:
                cur.executemany(
                    "INSERT INTO graph_edges (kind, a_robot, a_session, a_seq, b_robot, b_session, b_seq, "
                    "T_a_b, sigmas, robust, inliers) VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s)",
                    [(e.kind, *e.a, *(e.b if e.b is not None else (None, None, None)), pose_blob(e.T_a_b),
                      np.asarray(e.sigmas, "<f8").tobytes(), int(e.robust), int(e.inliers))
                     for e in change.edges])
            if change.estimates:
                cur.executemany(
                    "UPDATE graph_nodes SET T_map_camera = %s "
                    "WHERE robot_id = %s AND session_id = %s AND seq = %s",
                    [(pose_blob(T), *key) for key, T in change.estimates])
            if change.sessions:
                cur.executemany(
                    "INSERT INTO graph_sessions (robot_id, session_id, T_map_odom, anchored_s, anchored_to, "
                    "revision) VALUES (%s, %s, %s, %s, %s, %s) "
                    "ON CONFLICT (robot_id, session_id) DO UPDATE SET "
                    "T_map_odom = excluded.T_map_odom, anchored_s = excluded.anchored_s, "
                    "anchored_to = excluded.anchored_to, revision = excluded.revision",
                    [(a.robot_id, a.session_id, None if a.T_map_odom is None else pose_blob(a.T_map_odom),
                      a.anchored_s, a.anchored_to, a.revision) for a in change.sessions])
            if change.bump_epoch:
                conn.execute("INSERT INTO graph_epoch (id, epoch) VALUES (1, 1) "
                             "ON CONFLICT (id) DO UPDATE SET epoch = graph_epoch.epoch + 1")
            conn.execute(_CURSOR_SQL, (cursor, rowid))

    def graph_records(self) -> tuple[list[GraphNodeRow], list[GraphEdgeRow]]:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.graph_records`."""
        with self._snapshot("back-end: load the pose graph") as conn:
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
                              pose_from_blob(r[7]), np.frombuffer(bytes(r[8]), "<f8").astype(np.float64),
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
                row = conn.execute("SELECT T_map_camera FROM graph_nodes WHERE robot_id = %s AND "
                                   "session_id = %s AND seq = %s", key).fetchone()
                out[key] = None if row is None or row[0] is None else pose_from_blob(row[0])
        return out

    def session_anchors(self) -> list[SessionAnchor]:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.session_anchors`."""
        with self._read("back-end: sessions") as conn:
            rows = conn.execute("SELECT robot_id, session_id, T_map_odom, anchored_s, anchored_to, revision "
                                "FROM graph_sessions ORDER BY robot_id, session_id").fetchall()
        return [SessionAnchor(str(r[0]), str(r[1]), None if r[2] is None else pose_from_blob(r[2]),
                              None if r[3] is None else float(r[3]), str(r[4]), int(r[5])) for r in rows]

    def latest_nodes(self) -> dict[str, GraphNodeRow]:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.latest_nodes`."""
        with self._read("back-end: latest nodes") as conn:
            rows = conn.execute(
                "SELECT DISTINCT ON (robot_id) robot_id, session_id, seq, stamp, pose_source, T_odom_camera, "
                "T_map_camera, prior FROM graph_nodes ORDER BY robot_id, node_order DESC").fetchall()
        return {str(r[0]): GraphNodeRow((str(r[0]), str(r[1]), int(r[2])), float(r[3]), pose_from_blob(r[5]),
                                        str(r[4]), None if r[6] is None else pose_from_blob(r[6]),
                                        None if r[7] is None else pose_from_blob(r[7]), b"")
                for r in rows}

    def map_trajectory(self, robot_id: str, session_id: str | None = None) -> Trajectory:
        """See :meth:`~wardmap.server.store.protocol.GraphStore.map_trajectory`."""
        where, params = "k.robot_id = %s", [check_str(robot_id, "robot_id")]
        if session_id is not None:
            where, params = where + " AND k.session_id = %s", [robot_id, check_str(session_id, "session_id")]
        with self._read("map trajectory") as conn:
            rows = conn.execute(
                "SELECT k.stamp, g.T_map_camera FROM keyframes k JOIN graph_nodes g "
                f"USING (robot_id, session_id, seq) WHERE {where} AND g.T_map_camera IS NOT NULL "
                "ORDER BY k.stamp, k.session_id, k.seq", params).fetchall()
        return np.array([float(r[0]) for r in rows], dtype=np.float64), poses_from_blobs([r[1] for r in rows])

    # ------------------------------------------------------------------ REST API tokens

    def add_token(self, token: TokenRecord) -> None:
        """See :meth:`~wardmap.server.store.protocol.TokenStore.add_token`."""
        t = token
        with self._write("tokens: add") as conn:
            added = conn.execute(
                "INSERT INTO api_tokens (token_id, name, scope, secret_sha256, created_s, revoked_s) "
                "VALUES (%s, %s, %s, %s, %s, %s) ON CONFLICT DO NOTHING",
                (t.token_id, t.name, t.scope, t.secret_sha256, t.created_s, t.revoked_s)).rowcount
            if added != 1:
                raise StoreError(f"token {t.token_id!r} exists already")

    def token(self, token_id: str) -> TokenRecord | None:
        """See :meth:`~wardmap.server.store.protocol.TokenStore.token`."""
        with self._read("tokens: look-up") as conn:
            row = conn.execute(f"SELECT {TOKEN_COLUMNS} FROM api_tokens WHERE token_id = %s",
                               (token_id,)).fetchone()
        return None if row is None else token_from_row(row)

    def tokens(self) -> list[TokenRecord]:
        """See :meth:`~wardmap.server.store.protocol.TokenStore.tokens`."""
        with self._read("tokens: list") as conn:
            rows = conn.execute(
                f"SELECT {TOKEN_COLUMNS} FROM api_tokens ORDER BY created_s, token_id").fetchall()
        return [token_from_row(r) for r in rows]

    def revoke_token(self, token_id: str, revoked_s: float) -> bool:
        """See :meth:`~wardmap.server.store.protocol.TokenStore.revoke_token`."""
        with self._write("tokens: revoke") as conn:
            return conn.execute("UPDATE api_tokens SET revoked_s = %s "
                                "WHERE token_id = %s AND revoked_s IS NULL",
                                (float(revoked_s), token_id)).rowcount == 1

    # ------------------------------------------------------------------ connections and errors

    @contextmanager
    def _db_errors(self, what: str) -> Iterator[None]:
        """psycopg and pool errors become the classified :class:`StoreError` naming ``what``."""
        psycopg, psycopg_pool = _import()
        try:
            yield
        except (psycopg.Error, psycopg_pool.PoolTimeout, psycopg_pool.PoolClosed) as exc:
            self._raise_classified(what, exc)

    def _raise_classified(self, what: str, exc: BaseException) -> NoReturn:
        kind = classify_postgres_error(exc)
        detail = f"keyframe store {self.url}: {what} failed: {_first_line(exc)}"
        if kind is StoreDamagedError:
            with self._health_lock:
                first = self._damage is None
                if first:
                    self._damage = detail
            if first:
                log.error("%s: the database reports damaged data; restore it from a backup", detail)
        raise kind(detail) from exc

    @contextmanager
    def _connection(self, what: str) -> Iterator[psycopg.Connection[Any]]:
        if self._closed:
            raise StoreError(f"keyframe store {self.url} is closed")
        with self._db_errors(what), self._pool.connection() as conn:
            yield conn

    @contextmanager
    def _read(self, what: str) -> Iterator[psycopg.Connection[Any]]:
        """A pooled connection in autocommit: each statement sees the last committed state."""
        with self._connection(what) as conn:
            yield conn

    @contextmanager
    def _snapshot(self, what: str) -> Iterator[psycopg.Connection[Any]]:
        """A read-only transaction whose statements all see one snapshot."""
        with self._connection(what) as conn, conn.transaction():
            conn.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ, READ ONLY")
            yield conn

    @contextmanager
    def _write(self, what: str) -> Iterator[psycopg.Connection[Any]]:
        """One ``BEGIN`` .. ``COMMIT``; its outcome feeds :meth:`writable`."""
        try:
            with self._connection(what) as conn, conn.transaction():
                yield conn
        except StoreUnavailableError as exc:
            # A lost or refused connection is over when a probe connects; a full disk is not.
            cause = exc.__cause__
            connection_only = getattr(cause, "sqlstate", None) is None or str(
                getattr(cause, "sqlstate", "")).startswith(("08", "57P"))
            with self._health_lock:
                self._write_faults[what] = (str(exc), connection_only)
            raise
        with self._health_lock:
            self._write_faults.pop(what, None)


# ---------------------------------------------------------------------- helpers


def _one(cursor: psycopg.Cursor[Any]) -> Any:
    """The row of a query that always returns one (an aggregate, the schema row)."""
    row = cursor.fetchone()
    if row is None:
        raise StoreDamagedError("the database returned no row where one must be (is wardmap_schema empty?)")
    return row


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _connect_error(exc: Exception, shown: str, params: dict[str, Any]) -> StoreError:
    """One line saying why the first connection failed: unreachable, authentication, no database."""
    state = getattr(exc, "sqlstate", None)
    text = str(exc)
    lowered = text.lower()
    user, db = params.get("user") or "(default user)", params.get("dbname") or "(default database)"
    if state in ("28P01", "28000") or "password authentication failed" in lowered or "no password" in lowered:
        return StoreError(f"keyframe store {shown}: authentication failed for user {user}; "
                          "check the password "
                          f"({PASSWORD_SOURCES}) and pg_hba.conf")
    if state == "3D000" or ("database" in lowered and "does not exist" in lowered):
        return StoreError(f"keyframe store {shown}: database {db} does not exist; create it first "
                          f"(createdb -O {user} {db})")
    return StoreUnavailableError(f"keyframe store {shown}: cannot reach the PostgreSQL server: "
                                 f"{' '.join(text.split())[:300]}")


def _choose_object_index(conn: psycopg.Connection[Any], shown: str, postgis: bool) -> schema.Dialect:
    """``"postgis"`` when allowed and the extension is in the database or can be created here, else
    ``"postgres"``."""
    psycopg, _ = _import()
    if not postgis:
        log.info("keyframe store %s: PostGIS off (postgis=off); the object index is a GiST index over "
                 "the objects' xy bounds", shown)
        return "postgres"
    if conn.execute("SELECT 1 FROM pg_extension WHERE extname = 'postgis'").fetchone():
        return "postgis"
    if not conn.execute("SELECT 1 FROM pg_available_extensions WHERE name = 'postgis'").fetchone():
        log.info("keyframe store %s: PostGIS is not installed on the server; the object index is a GiST "
                 "index over the objects' xy bounds", shown)
        return "postgres"
    try:
        with conn.transaction():  # a savepoint: a refused CREATE EXTENSION leaves the migration going
            conn.execute("CREATE EXTENSION postgis")
    except psycopg.Error as exc:
        log.info("keyframe store %s: cannot create the PostGIS extension (%s); the object index is a GiST "
                 "index over the objects' xy bounds", shown, _first_line(exc))
        return "postgres"
    return "postgis"


def _migrate(conn: psycopg.Connection[Any], shown: str, *, postgis: bool) -> schema.Dialect:
    """Create or upgrade the schema in one transaction (serialised between processes by an advisory
    lock); returns the object index of the database."""
    with conn.transaction():
        conn.execute("SELECT pg_advisory_xact_lock(%s)", (APPLICATION_ID + 1,))
        if _one(conn.execute("SELECT to_regclass('wardmap_schema')"))[0] is None:
            tables = [str(r[0]) for r in conn.execute(
                "SELECT tablename FROM pg_tables WHERE schemaname = current_schema() ORDER BY 1 LIMIT 10")]
            if tables:
                raise StoreError(f"database {shown} has tables ({', '.join(tables)}) but is not a wardmap "
                                 "keyframe store (no wardmap_schema table); refusing to touch it")
            conn.execute(
                "CREATE TABLE wardmap_schema (id INTEGER PRIMARY KEY CHECK (id = 1), application_id BIGINT "
                "NOT NULL, version INTEGER NOT NULL, object_index TEXT NOT NULL "
                "CHECK (object_index IN ('postgres', 'postgis')))")
            conn.execute("INSERT INTO wardmap_schema VALUES (1, %s, 0, %s)",
                         (APPLICATION_ID, _choose_object_index(conn, shown, postgis)))
        app_id, version, index = _one(conn.execute(
            "SELECT application_id, version, object_index FROM wardmap_schema WHERE id = 1"))
        if int(app_id) != APPLICATION_ID:
            raise StoreError(f"database {shown} is not a wardmap keyframe store (application_id {app_id:#x})")
        if version > schema.LATEST:
            raise StoreError(f"keyframe store {shown} has schema version {version} but this wardmap knows "
                             f"up to {schema.LATEST}: it was written by a newer wardmap; "
                             "upgrade wardmap to open it")
        dialect: schema.Dialect = "postgis" if index == "postgis" else "postgres"
        if version < schema.LATEST:
            for step in schema.migrations(dialect)[version:]:
                for statement in step:
                    conn.execute(statement)
            conn.execute("UPDATE wardmap_schema SET version = %s WHERE id = 1", (schema.LATEST,))
            log.info("keyframe store %s: schema migrated from version %d to %d",
                     shown, version, schema.LATEST)
    return dialect


def _pyformat(sql: str) -> str:
    """``:name`` placeholders (``rows.find_sql``) as psycopg's ``%(name)s``."""
    return re.sub(r"(?<![:\w]):([a-z_][a-z0-9_]*)", r"%(\1)s", sql)


def _existing(conn: psycopg.Connection[Any], ids: Sequence[int]) -> set[int]:
    if not ids:
        return set()
    rows = conn.execute("SELECT object_id FROM objects WHERE object_id = ANY(%s)", (list(ids),))
    return {int(r[0]) for r in rows}


def _refresh_derived(conn: psycopg.Connection[Any], ids: Sequence[int]) -> None:
    """Recompute count, first/last seen and robots of ``ids`` from their observations."""
    arg = (list(ids),)
    conn.execute(
        "UPDATE objects AS o SET "
        "n_observations = (SELECT COUNT(*) FROM observations AS b WHERE b.object_id = o.object_id), "
        "first_seen_s = LEAST(o.first_seen_s, COALESCE((SELECT MIN(added_s) FROM observations AS b "
        "WHERE b.object_id = o.object_id), o.first_seen_s)), "
        "last_seen_s = COALESCE((SELECT MAX(added_s) FROM observations AS b "
        "WHERE b.object_id = o.object_id), o.first_seen_s) "
        "WHERE o.object_id = ANY(%s)", arg)
    conn.execute("DELETE FROM object_robots WHERE object_id = ANY(%s)", arg)
    conn.execute("INSERT INTO object_robots (object_id, robot_id) SELECT DISTINCT object_id, robot_id "
                 "FROM observations WHERE object_id = ANY(%s)", arg)


def _robots(conn: psycopg.Connection[Any], ids: Sequence[int]) -> dict[int, tuple[str, ...]]:
    if not ids:
        return {}
    rows = conn.execute("SELECT object_id, robot_id FROM object_robots WHERE object_id = ANY(%s) "
                        "ORDER BY object_id, robot_id", (list(ids),)).fetchall()
    out: dict[int, list[str]] = {}
    for oid, robot in rows:
        out.setdefault(int(oid), []).append(str(robot))
    return {k: tuple(v) for k, v in out.items()}


def _records(conn: psycopg.Connection[Any], ids: Sequence[int]) -> dict[int, ObjectRecord]:
    rows = conn.execute(f"SELECT {OBJECT_COLUMNS} FROM objects AS o WHERE o.object_id = ANY(%s)",
                        (list(ids),)).fetchall()
    robots = _robots(conn, [int(r[0]) for r in rows])
    return {int(r[0]): object_record(r, robots.get(int(r[0]), ())) for r in rows}

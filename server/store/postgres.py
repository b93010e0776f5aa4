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
ONLY`` transaction). Pooled connections are checked before use; after a database restart the
pool reconnects in the background with back-off (1 s, 2 s, ... for :data:`RECONNECT_TIMEOUT_S`,
then anew at the next call), and calls meanwhile fail as
:class:`StoreUnavailableError` within :data:`POOL_TIMEOUT_S`.

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
import functools
import logging
import os
import re
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final, NoReturn

from wardmap.server.store import schema
from wardmap.server.store.records import (
    StoreDamagedError,
    StoreError,
    StoreUnavailableError,
)
from wardmap.server.store.sqlbase import SqlMapStore, check_lease_holder

if TYPE_CHECKING:
    import psycopg
    from psycopg_pool import ConnectionPool

log = logging.getLogger(__name__)

SCHEMES: Final = ("postgresql://", "postgres://")
APPLICATION_ID: Final = 0x77726D73  # "wrms", as the SQLite file's application_id
INSERT_LOCK: Final = APPLICATION_ID
"""The advisory lock key keyframe inserts take (``pg_advisory_xact_lock``), see the module docstring."""
WRITER_LEASE: Final = (APPLICATION_ID, 1)
"""The session advisory lock (``pg_try_advisory_lock(int, int)``) that is the writer lease."""
LEASE_APP_PREFIX: Final = "wardmap writer lease: "
"""The lease connection's ``application_name`` is this and the holder's name (how others see it)."""
LEASE_TIMEOUT_S: Final = 2.0
"""Longest a lease statement waits (statement timeout) before the lease counts as lost."""
LEASE_KEEPALIVE: Final = {"keepalives": 1, "keepalives_idle": 2, "keepalives_interval": 1,
                          "keepalives_count": 3, "tcp_user_timeout": 5000}
"""libpq TCP settings of the lease connection: a silent network is found dead in about 5 s
(the database side uses the same values, set per session, to release the lock)."""
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
RECONNECT_TIMEOUT_S: Final = 10.0
"""How long the pool retries (with back-off) a connection it lost; then the next call starts anew,
so a long database outage does not leave the pool waiting out a long back-off."""
PROBE_TIMEOUT_S: Final = 1.0
"""Longest :meth:`PostgresMapStore.writable` waits for a connection or a lock."""
DEFAULT_POOL_SIZE: Final = 8
# PostgreSQL error classes meaning "not now" (psycopg raises most as OperationalError too).
_DAMAGED_STATES: Final = frozenset({"XX001", "XX002"})  # data_corrupted, index_corrupted
_UNAVAILABLE_STATES: Final = frozenset({"25006", "40001", "40P01", "55P03", "57014"})


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


class PostgresMapStore(SqlMapStore):
    """The PostgreSQL map store: implements :class:`~wardmap.server.store.protocol.MapStore`.
    Create with :func:`~wardmap.server.store.open_store` or :meth:`open`. Thread safe (a pool
    of connections; see the module docstring). The queries it shares with the SQLite store are
    in :class:`~wardmap.server.store.sqlbase.SqlMapStore`.

    Attributes:
        url: the database's URL as shown in messages (no password, no query).
        object_index: ``"postgis"`` or ``"postgres"`` (the GiST box fallback).
    """

    def __init__(
        self, pool: ConnectionPool[psycopg.Connection[Any]], url: str, object_index: schema.Dialect,
        params: dict[str, Any] | None = None,
    ) -> None:
        """Internal: use :meth:`open` (``params``: libpq's, for the writer lease's own connection)."""
        self._pool = pool
        self._params = dict(params or {})
        self.url = url
        self.object_index = object_index
        self.dialect = object_index
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
                if str(_one(conn.execute("SHOW synchronous_commit"))[0]) == "off":
                    log.warning("keyframe store %s: synchronous_commit is off: an acked keyframe may be "
                                "lost if the database server crashes", shown)
        except psycopg.Error as exc:
            raise classify_postgres_error(exc)(f"keyframe store {shown}: cannot prepare the database: "
                                               f"{_first_line(exc)}") from exc
        pool = psycopg_pool.ConnectionPool(
            kwargs={**params, "autocommit": True}, min_size=1, max_size=options.pool_size, open=False,
            timeout=POOL_TIMEOUT_S, check=psycopg_pool.ConnectionPool.check_connection,
            reconnect_timeout=RECONNECT_TIMEOUT_S, name="wardmap-store",
        )
        try:
            pool.open(wait=True, timeout=CONNECT_TIMEOUT_S)
        except psycopg_pool.PoolTimeout as exc:
            pool.close()
            raise StoreUnavailableError(
                f"keyframe store {shown}: the connection pool could not start"
            ) from exc
        log.info("keyframe store %s open (object index: %s)", shown, object_index)
        return cls(pool, shown, object_index, params)

    def close(self) -> None:
        """Close the pool (idempotent); calls after it raise StoreError."""
        if self._closed:
            return
        self._closed = True
        self._pool.close()

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

    # ------------------------------------------------------------------ the writer lease

    def writer_lease(self, holder: str) -> AdvisoryLease:
        """A handle on the writer lease for ``holder`` (:class:`AdvisoryLease`), not acquired."""
        return AdvisoryLease(check_lease_holder(holder), self)

    def lease_holder(self) -> str | None:
        """Who holds the writer lease (its ``application_name`` without the prefix), None when
        nobody does. Raises StoreError when the database cannot tell."""
        with self._read("writer lease holder") as conn:
            row = conn.execute(
                "SELECT a.application_name FROM pg_locks l JOIN pg_stat_activity a ON a.pid = l.pid "
                "WHERE l.locktype = 'advisory' AND l.database = (SELECT oid FROM pg_database WHERE "
                "datname = current_database()) AND l.classid = ? AND l.objid = ? AND l.objsubid = 2 "
                "AND l.granted", WRITER_LEASE).fetchone()
        if row is None:
            return None
        name = str(row[0] or "")
        return name.removeprefix(LEASE_APP_PREFIX) if name.startswith(LEASE_APP_PREFIX) else name or "unknown"

    def _lease_connection(self, holder: str) -> psycopg.Connection[Any]:
        """A new connection of its own for the writer lease (not pooled: the lock is its session's)."""
        psycopg, _ = _import()
        if self._closed:
            raise StoreError(f"keyframe store {self.url} is closed")
        params = {**self._params, **LEASE_KEEPALIVE, "application_name": LEASE_APP_PREFIX + holder}
        with self._db_errors("writer lease connection"):
            conn = psycopg.connect(**params, autocommit=True)
            timeout_ms = int(LEASE_TIMEOUT_S * 1000)
            conn.execute(f"SET statement_timeout = {timeout_ms}")
            for name, value in (("tcp_keepalives_idle", 2), ("tcp_keepalives_interval", 1),
                                ("tcp_keepalives_count", 3), ("tcp_user_timeout", 5000)):
                conn.execute(f"SET {name} = {value}")
        return conn

    # ------------------------------------------------------------------ dialect hooks (sqlbase.py)

    def _serialise_inserts(self, conn: _Connection) -> None:
        """Keyframe inserts take turns (see the module docstring): rowid order = commit order."""
        conn.execute("SELECT pg_advisory_xact_lock(?)", (INSERT_LOCK,))

    _IN_IDS = "= ANY(?)"
    _FENCE_READ = "SELECT epoch FROM writer_fence WHERE id = 1 FOR SHARE"

    def _ids(self, ids: Sequence[int]) -> object:
        return [int(i) for i in ids]

    def _schema_version(self, conn: _Connection) -> int:
        return int(_one(conn.execute("SELECT version FROM wardmap_schema"))[0])

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
        if kind is StoreDamagedError and self._first_damage(detail):
            log.error("%s: the database reports damaged data; restore it from a backup", detail)
        raise kind(detail) from exc

    @contextmanager
    def _connection(self, what: str) -> Iterator[psycopg.Connection[Any]]:
        if self._closed:
            raise StoreError(f"keyframe store {self.url} is closed")
        with self._db_errors(what), self._pool.connection() as conn:
            yield conn

    @contextmanager
    def _read(self, what: str) -> Iterator[_Connection]:
        """A pooled connection in autocommit: each statement sees the last committed state."""
        with self._connection(what) as conn:
            yield _Connection(conn)

    @contextmanager
    def _snapshot(self, what: str) -> Iterator[_Connection]:
        """A read-only transaction whose statements all see one snapshot."""
        with self._connection(what) as conn, conn.transaction():
            conn.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ, READ ONLY")
            yield _Connection(conn)

    @contextmanager
    def _write(self, what: str) -> Iterator[_Connection]:
        """One ``BEGIN`` .. ``COMMIT``; its outcome feeds :meth:`writable`."""
        try:
            with self._connection(what) as conn, conn.transaction():
                yield _Connection(conn)
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


@functools.lru_cache(maxsize=512)
def _pyformat(sql: str) -> str:
    """SQLite's ``?`` and ``:name`` placeholders (``sqlbase.py``, ``rows.find_sql``) as psycopg's
    ``%s`` and ``%(name)s`` (the shared SQL has no ``%`` and no ``::`` casts)."""
    return re.sub(r"(?<![:\w]):([A-Za-z_][A-Za-z0-9_]*)", r"%(\1)s", sql.replace("?", "%s"))


class _Connection:
    """A psycopg connection taking the shared SQL's placeholders (what :class:`SqlMapStore` uses)."""

    def __init__(self, conn: psycopg.Connection[Any]) -> None:
        self._conn = conn

    def execute(self, sql: str, params: Any = None) -> psycopg.Cursor[Any]:
        return self._conn.execute(_pyformat(sql), params)

    def executemany(self, sql: str, rows: Sequence[Any]) -> psycopg.Cursor[Any]:
        cursor = self._conn.cursor()
        cursor.executemany(_pyformat(sql), rows)
        return cursor


class AdvisoryLease:
    """The writer lease on PostgreSQL (:class:`~wardmap.server.store.protocol.WriterLease`): the
    session advisory lock :data:`WRITER_LEASE` held on a connection of its own whose
    ``application_name`` names the holder. The database releases it when that connection ends:
    the holder's process exits or is killed (its socket closes at once), or the network goes
    silent (TCP keepalive and user timeout, :data:`LEASE_KEEPALIVE`: about 5 s). Taking it also
    takes the writer fence (:meth:`SqlMapStore.take_writer_fence`), so a former holder still
    running cannot write the map after this one started. Thread safe."""

    def __init__(self, holder: str, store: PostgresMapStore) -> None:
        self.holder = holder
        self._store = store
        self._lock = threading.Lock()  # guards _conn (one statement at a time on it)
        self._conn: psycopg.Connection[Any] | None = None  # open while the lock is held or tried

    def acquire(self) -> bool:
        with self._lock:
            if self._conn is not None and self._holds():
                return True
            self._drop()
            try:
                self._conn = self._store._lease_connection(self.holder)
                got = bool(_one(self._conn.execute("SELECT pg_try_advisory_lock(%s, %s)", WRITER_LEASE))[0])
            except Exception as exc:  # any failure means "not acquired" (logged)
                log.debug("writer lease: not acquired: %s", _first_line(exc))
                self._drop()
                return False
            if not got:
                self._drop()  # a standby keeps no connection open between attempts
                return False
            try:
                self._store.take_writer_fence()  # waits for the former holder's write in flight
            except StoreError as exc:
                log.warning("writer lease: taken but not fenced, so given back: %s", exc)
                self._drop()
                return False
            return True

    def held(self) -> bool:
        with self._lock:
            if self._conn is None:
                return False
            if self._holds():
                return True
            self._drop()
            return False

    def current_holder(self) -> str | None:
        try:
            return self._store.lease_holder()
        except StoreError:
            return None

    def release(self) -> None:
        with self._lock:
            self._drop()

    def _holds(self) -> bool:
        """Whether this connection's session holds the lock (False on any error)."""
        if self._conn is None:
            return False
        try:
            row = self._conn.execute(
                "SELECT count(*) FROM pg_locks WHERE locktype = 'advisory' AND pid = pg_backend_pid() "
                "AND classid = %s AND objid = %s AND objsubid = 2 AND granted", WRITER_LEASE).fetchone()
        except Exception as exc:  # a lost connection is a lost lease
            log.warning("writer lease: its connection failed: %s", _first_line(exc))
            return False
        return row is not None and int(row[0]) == 1

    def _drop(self) -> None:
        """Close the lease connection (which releases the lock), ignoring errors."""
        conn, self._conn = self._conn, None
        if conn is not None:
            try:
                conn.close()
            except Exception as exc:  # closing a broken connection: nothing more to do
                log.debug("writer lease: closing its connection: %s", _first_line(exc))

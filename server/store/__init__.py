"""The map server's database: keyframes, object map, and the mapping stage's records.

Ingest calls :meth:`~KeyframeStore.insert` for every decoded keyframe and acks the robot
only after it returned; the REST API reads keyframes through the query methods; the object
map (``server/objectmap.py``) and the mapping stage (``server/mapping/``) keep their rows
here. The store is the only owner of the database: the Protocols in ``protocol.py``
(:class:`MapStore` and its parts) are the whole interface, no caller sees a connection or
writes a query. :class:`SqliteMapStore` (``sqlite.py``, stdlib ``sqlite3``) is the embedded
default; :class:`PostgresMapStore` (``postgres.py``, psycopg 3 with a connection pool, PostGIS
for the object index where installed) serves several wards and servers. Both take their
schema from one versioned step list (``schema.py``) and share every query but their
connections, readiness probe and a few dialect hooks (``sqlbase.py``). Choose one with
:func:`open_store` and a URL. Records are in ``records.py``, row conversions in ``rows.py``,
blob encodings shared by backends in ``codec.py``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

from wardmap.server.store.codec import pose_blob, pose_from_blob
from wardmap.server.store.postgres import PASSWORD_ENV, PostgresMapStore, read_password_file
from wardmap.server.store.protocol import (
    GraphStore,
    KeyframeStore,
    LeaseStore,
    MappingStore,
    MapStore,
    ObjectStore,
    PerceptionStore,
    TokenStore,
    WriterLease,
)
from wardmap.server.store.records import (
    MAX_PAGE,
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
    KeyCursor,
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
    Perceived,
    PerceptionSlot,
    RobotSummary,
    SessionAnchor,
    StoreDamagedError,
    StoredKeyframe,
    StoreError,
    StoreStats,
    StoreUnavailableError,
    TokenRecord,
    TokenScope,
    Trajectory,
    UnknownObjectError,
)
from wardmap.server.store.sqlite import (
    APPLICATION_ID,
    MIGRATIONS,
    REPAIR_HINT,
    SqliteMapStore,
    StoreOptions,
    classify_sqlite_error,
)

__all__ = [
    "APPLICATION_ID",
    "MAX_PAGE",
    "MAX_REASON_LEN",
    "MIGRATIONS",
    "PASSWORD_ENV",
    "REPAIR_HINT",
    "SQLITE_SCHEME",
    "AnchoredKeyframe",
    "Checkpoint",
    "ClaimedKeyframe",
    "ClosedSession",
    "CompactPage",
    "CompactRow",
    "Cursor",
    "GraphChange",
    "GraphEdgeRow",
    "GraphNodeRow",
    "GraphStore",
    "InsertResult",
    "KeyCursor",
    "KeyframeKey",
    "KeyframePage",
    "KeyframeRef",
    "KeyframeRow",
    "KeyframeStore",
    "LeaseStore",
    "MapStore",
    "MappedPose",
    "MappingStore",
    "NodeKey",
    "ObjectDetail",
    "ObjectHit",
    "ObjectPage",
    "ObjectRecord",
    "ObjectRow",
    "ObjectStore",
    "ObjectWrite",
    "Observation",
    "ObservationRecord",
    "Perceived",
    "PerceptionSlot",
    "PerceptionStore",
    "PostgresMapStore",
    "RobotSummary",
    "SessionAnchor",
    "SqliteKeyframeStore",
    "SqliteMapStore",
    "StoreDamagedError",
    "StoreError",
    "StoreOptions",
    "StoreStats",
    "StoreUnavailableError",
    "StoredKeyframe",
    "TokenRecord",
    "TokenScope",
    "TokenStore",
    "Trajectory",
    "UnknownObjectError",
    "WriterLease",
    "classify_sqlite_error",
    "open_store",
    "pose_blob",
    "pose_from_blob",
    "read_password_file",
]

SQLITE_SCHEME: Final = "sqlite:///"
SqliteKeyframeStore = SqliteMapStore
"""The SQLite backend's former name."""


def open_store(url: str, *, password: str | None = None) -> MapStore:
    """Open (or create) the store that ``url`` names.

    Args:
        url: ``sqlite:///PATH`` as in SQLAlchemy: ``sqlite:///map.db`` is relative to the
            working folder, ``sqlite:////var/lib/wardmap/map.db`` is absolute. The parent
            folder is created. In-memory databases are not supported (every thread opens its
            own connection). A query sets :class:`StoreOptions`:
            ``sqlite:///map.db?busy_timeout_s=2&max_pages=250000``.
            Or ``postgresql://USER@HOST:PORT/DB`` (also ``postgres://``): a PostgreSQL database
            that exists; its schema is created or migrated (:meth:`PostgresMapStore.open`). A
            password in the URL is refused.
        password: the PostgreSQL password (e.g. from ``--db-password-file``); None: the
            ``WARDMAP_DB_PASSWORD`` environment variable, else libpq's PGPASSFILE/~/.pgpass.
            Not used by SQLite.

    Raises:
        StoreError: an unknown or unsupported scheme, an empty path, a password in the URL,
            or any failure of :meth:`SqliteMapStore.open` or :meth:`PostgresMapStore.open`
            (:class:`StoreUnavailableError` when the database server cannot be reached).
    """
    if not isinstance(url, str):
        raise StoreError(f"store URL must be a str, got {type(url).__name__}")
    if url.startswith(("postgresql://", "postgres://")):
        return PostgresMapStore.open(url, password=password)
    scheme = url.split(":", 1)[0] if ":" in url else ""
    if scheme.startswith(("postgresql+", "postgres")):
        raise StoreError(f"store URL scheme {scheme!r}: expected postgresql://USER@HOST:PORT/DB")
    if not url.startswith(SQLITE_SCHEME):
        raise StoreError(
            f"unknown store URL {url.split('@')[-1]!r}: expected {SQLITE_SCHEME}PATH "
            f"(e.g. {SQLITE_SCHEME}wardmap.db or {SQLITE_SCHEME}/var/lib/wardmap/map.db) "
            "or postgresql://USER@HOST:PORT/DB"
        )
    path, _, query = url[len(SQLITE_SCHEME) :].partition("?")
    if not path:
        raise StoreError(f"store URL {url!r} has no file path: expected {SQLITE_SCHEME}PATH")
    if path == ":memory:" or path.startswith("file:"):
        raise StoreError(f"store URL {url!r}: only a plain file path is supported after {SQLITE_SCHEME}")
    return SqliteMapStore.open(Path(path), StoreOptions.from_query(query))

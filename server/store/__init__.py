"""The map server's database: keyframes, object map, and the mapping stage's records.

Ingest calls :meth:`~KeyframeStore.insert` for every decoded keyframe and acks the robot
only after it returned; the REST API reads keyframes through the query methods; the object
map (``server/objectmap.py``) and the mapping stage (``server/mapping/``) keep their rows
here. The store is the only owner of the database: the Protocols in ``protocol.py``
(:class:`MapStore` and its parts) are the whole interface, no caller sees a connection or
writes a query. :class:`SqliteMapStore` (``sqlite.py``, stdlib ``sqlite3``) is the embedded
default and holds the schema and its migrations; a PostgreSQL backend will implement the
same Protocol. Choose one with :func:`open_store` and a URL. Records are in ``records.py``,
blob encodings shared by backends in ``codec.py``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

from wardmap.server.store.codec import pose_blob, pose_from_blob
from wardmap.server.store.protocol import (
    GraphStore,
    KeyframeStore,
    MappingStore,
    MapStore,
    ObjectStore,
    TokenStore,
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
    "REPAIR_HINT",
    "SQLITE_SCHEME",
    "AnchoredKeyframe",
    "Checkpoint",
    "ClosedSession",
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
    "classify_sqlite_error",
    "open_store",
    "pose_blob",
    "pose_from_blob",
]

SQLITE_SCHEME: Final = "sqlite:///"
SqliteKeyframeStore = SqliteMapStore
"""The SQLite backend's former name."""


def open_store(url: str) -> MapStore:
    """Open (or create) the store that ``url`` names.

    Args:
        url: ``sqlite:///PATH`` as in SQLAlchemy: ``sqlite:///map.db`` is relative to the
            working folder, ``sqlite:////var/lib/wardmap/map.db`` is absolute. The parent
            folder is created. In-memory databases are not supported (every thread opens its
            own connection). A query sets :class:`StoreOptions`:
            ``sqlite:///map.db?busy_timeout_s=2&max_pages=250000``.

    Raises:
        StoreError: an unknown or unsupported scheme, an empty path, or any failure of
            :meth:`SqliteMapStore.open`.
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
    return SqliteMapStore.open(Path(path), StoreOptions.from_query(query))

"""What the map server needs from its database: the Protocols every backend implements.

:class:`MapStore` is the whole contract (``open_store`` returns one); its parts name what each
user needs: ingest and the REST API read and write keyframes (:class:`KeyframeStore`), the
object map its objects (:class:`ObjectStore`), the mapping stage its cursor, measurements,
closures and checkpoint (:class:`MappingStore`). Nothing outside a backend sees its
connections or writes its queries. The SQLite backend (``sqlite.py``) documents the
guarantees (durability, threads) a backend must give.
"""

from __future__ import annotations

from collections.abc import Sequence
from types import TracebackType
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from wardmap.server.perception.types import ObjectMeasurement
from wardmap.server.store.records import (
    AnchoredKeyframe,
    Checkpoint,
    ClaimedKeyframe,
    ClosedSession,
    CompactPage,
    Cursor,
    GraphChange,
    GraphEdgeRow,
    GraphNodeRow,
    InsertResult,
    KeyframeKey,
    KeyframePage,
    MappedPose,
    NodeKey,
    ObjectDetail,
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
    StoreStats,
    TokenRecord,
    Trajectory,
    Vec3,
)
from wardmap.shared.wire import KeyframeMsg


class KeyframeStore(Protocol):
    """Keyframes as robots sent them, and the counters of rejected messages."""

    def insert(self, msg: KeyframeMsg, payload: bytes, received_s: float) -> InsertResult:
        """Store ``msg`` (encoded as ``payload``) durably, committed before this returns;
        ``"duplicate"`` (and nothing changes) when its ``(robot_id, session_id, seq)`` is
        stored already: the first copy wins."""
        ...

    def count_rejection(self, reason: str, n: int = 1) -> None:
        """Add ``n`` to the counter of ``reason`` (1-200 characters), all or nothing."""
        ...

    def writable(self) -> tuple[bool, str]:
        """Whether a write can commit now: ``(True, "ok")`` or ``(False, why)``; never raises."""
        ...

    def rejections(self) -> dict[str, int]:
        """Every rejection reason with its count, by reason."""
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

    def images_erased_s(self, robot_id: str, session_id: str, seq: int) -> float | None:
        """When the keyframe's images were erased (server seconds), None if not (or no such keyframe)."""
        ...

    def erase_images(
        self, *, now_s: float, received_before_s: float | None = None, stamp_from: float | None = None,
        stamp_to: float | None = None, robot_id: str | None = None,
    ) -> int:
        """Erase the images of the keyframes matching every given filter (at least one); how many.

        Received before ``received_before_s`` (retention), capture ``stamp`` in ``[stamp_from,
        stamp_to)``, of ``robot_id``. Each payload becomes :func:`~wardmap.server.store.codec.
        without_images` of itself and is marked erased at ``now_s``; already erased ones are
        skipped. Poses, features, graph, measurements and objects are untouched.
        """
        ...

    def stats(self) -> StoreStats:
        """Totals over the whole store, from one consistent snapshot."""
        ...

    def close(self) -> None:
        """Release the store (idempotent); every call after it raises ``StoreError``."""
        ...


class ObjectStore(Protocol):
    """The object map's rows: objects, their observations, the robots that saw them.

    Inputs are checked by the object map (``server/objectmap.py``) before they come here.
    Every write is one transaction: on any error nothing is written.
    """

    def write_objects(
        self, objects: Sequence[ObjectRow], observations: Sequence[Observation], now_s: float
    ) -> list[ObjectWrite]:
        """Create or replace ``objects``, then add ``observations``; an observation already
        stored under the same keyframe and box is moved to its new object and refreshed.
        New objects and new observations get ``now_s`` as their first-seen and added time.
        Each touched object's count, first/last seen and robots are recomputed from its
        observations.

        Returns:
            Every touched object: those of ``objects`` in their order, then objects that
            gained or lost an observation.

        Raises:
            UnknownObjectError: an observation names an object neither given nor stored.
        """
        ...

    def delete_object(
        self, object_id: int, merged_into: int | None = None
    ) -> tuple[ObjectRecord, ObjectRecord | None]:
        """Remove an object; its observations move to ``merged_into`` (when given) or go with it.

        Returns:
            ``(the object before, merged_into after)``; the second is None without ``merged_into``.

        Raises:
            UnknownObjectError: ``object_id`` or ``merged_into`` is not stored.
        """
        ...

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
        """Objects matching every given filter, ``limit`` from ``offset``: nearest centre first
        (ties by id) with their distance when ``near`` is given, else by id. ``radius_m``
        (with ``near``) keeps centres within that distance; ``robot`` keeps objects some
        observation of that robot supports; unconfirmed objects only with
        ``include_unconfirmed``."""
        ...

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
        """:meth:`find_objects`' page (same filters, order and paging) as
        :data:`~wardmap.server.store.records.CompactRow` tuples only: what a map view draws of
        each object, without building its record (a page of 1000: about 11 ms of server CPU against 35)."""
        ...

    def object_detail(self, object_id: int, max_observations: int) -> ObjectDetail | None:
        """One object with its latest ``max_observations`` observations (newest first) and the
        keyframes they came from (by stamp), from one snapshot; None when unknown."""
        ...

    def count_objects(self, *, unconfirmed: bool | None = None) -> int:
        """Stored objects; with ``unconfirmed`` True or False, only those (not) confirmed."""
        ...

    def category_counts(self, *, include_unconfirmed: bool = False) -> dict[str, int]:
        """Stored objects per category (categories with none are absent)."""
        ...

    def object_ids(self) -> list[int]:
        """Every stored object id, ascending."""
        ...

    def observation_counts(self) -> dict[int, int]:
        """Stored observations per object id (objects with none are absent)."""
        ...


class MappingStore(Protocol):
    """What the mapping stage keeps besides keyframes: named cursors over the insertion order,
    object measurements and map poses per keyframe, idle-session closures and the
    association checkpoint."""

    def cursor(self, name: str) -> int:
        """The ``rowid`` up to which cursor ``name`` has processed keyframes (0: none)."""
        ...

    def next_keyframes(self, after: int, limit: int) -> list[StoredKeyframe]:
        """Up to ``limit`` keyframes with ``rowid > after``, in insertion order."""
        ...

    def count_keyframes_after(self, after: int) -> int:
        """Stored keyframes with ``rowid > after``."""
        ...

    def session_has_keyframes_after(self, robot_id: str, session_id: str, after: int) -> bool:
        """Whether a keyframe of this session has ``rowid > after``."""
        ...

    def commit_keyframe(
        self, cursor: str, rowid: int, pose: MappedPose, measurements: Sequence[ObjectMeasurement],
        *, anchored: bool,
    ) -> None:
        """In one transaction: store the keyframe's ``measurements`` (their masks are not
        kept; ``anchored``: of a session on the map, which replay reads), its map pose
        (replacing any), delete its perception row (:class:`PerceptionStore`), and move cursor
        ``cursor`` to ``rowid``."""
        ...

    def unmapped_keyframes(self, upto: int, limit: int) -> list[KeyframeKey]:
        """Up to ``limit`` keyframes with ``rowid <= upto`` that have no map pose recorded
        (processed before map poses were stored), in insertion order."""
        ...

    def record_mapped(self, poses: Sequence[MappedPose]) -> None:
        """Record map poses of processed keyframes (replacing any), in one transaction."""
        ...

    def anchored_keyframes(self, after: int, upto: int, limit: int) -> list[AnchoredKeyframe]:
        """Up to ``limit`` processed keyframes with ``after < rowid <= upto`` that are on the map
        (the back-end has a ``T_map_camera`` estimate of them), in insertion order, with their
        measurements and the pose those were computed with; keyframe payloads are not read."""
        ...

    def count_measurements(self) -> int:
        """Stored object measurements (all keyframes, on the map or not)."""
        ...

    def close_sessions(self, sessions: Sequence[tuple[str, str]], at_rowid: int) -> None:
        """Record ``(robot_id, session_id)`` closures at cursor ``at_rowid`` (one already
        recorded stays as it is), in one transaction."""
        ...

    def closed_sessions(self, first: int = 0, last: int | None = None) -> list[ClosedSession]:
        """Closures with ``first <= at_rowid <= last`` (None: no upper bound), ordered by
        ``(at_rowid, robot_id, session_id)``."""
        ...

    def checkpoint(self) -> Checkpoint | None:
        """The association checkpoint, None when none was saved."""
        ...

    def save_checkpoint(self, checkpoint: Checkpoint) -> None:
        """Replace the association checkpoint (there is at most one)."""
        ...


class PerceptionStore(Protocol):
    """Perception shared out between servers (``server/mapping/workers.py``): any server's workers
    claim stored keyframes ahead of the mapping stage's cursor, one worker per keyframe at a
    time, and store what they measured; the mapping stage reads the results in insertion order.

    A claim lasts until ``now_s + claim_s`` (server wall-clock seconds: the servers' clocks must
    agree well within ``claim_s``) or until its result is stored; a worker that died leaves its
    claim to expire, and the keyframe is claimed again. A result is stored once: the first one
    stored for a keyframe stays. These writes are not fenced by the writer lease (standbys make
    them); :meth:`MappingStore.commit_keyframe` deletes the keyframe's row.
    """

    def claim_keyframe(
        self, worker: str, *, cursor: str, now_s: float, claim_s: float, rowid: int | None = None,
    ) -> ClaimedKeyframe | None:
        """Claim for ``worker`` the first keyframe in insertion order after cursor ``cursor``
        that has no result and no live claim (only keyframe ``rowid`` when given), until
        ``now_s + claim_s``; None when there is none. Two callers never hold one keyframe's
        claim at once (one transaction per claim; PostgreSQL: a conditional upsert, whose
        loser sees the winner's row)."""
        ...

    def store_perceived(self, worker: str, result: Perceived) -> bool:
        """Store ``worker``'s ``result`` for the keyframe it names (``result.pose``), claimed by
        anyone, the claim live or not; False (nothing changes) when a result is stored already,
        or the keyframe was never claimed or the mapping stage has committed it."""
        ...

    def release_claim(self, worker: str, rowid: int) -> None:
        """End ``worker``'s claim on keyframe ``rowid`` now (after an unexpected error), so any
        worker may claim it again; nothing when the claim is another's or a result is stored."""
        ...

    def perception_slots(self, after: int, upto: int, limit: int) -> list[PerceptionSlot]:
        """Up to ``limit`` keyframes with ``after < rowid <= upto`` in insertion order, each with
        its stored result or its claim's expiry; no keyframe payload is read."""
        ...

    def count_unperceived(self, cursor: str) -> int:
        """Keyframes after cursor ``cursor`` with no stored perception result."""
        ...


class GraphStore(Protocol):
    """What the SLAM back-end keeps (``server/backend/``): the pose graph (nodes with their
    place-recognition codes and latest estimates, factors), each session's anchoring on the
    map, and the graph epoch that tells the mapping stage to rebuild the object map."""

    def commit_graph(self, cursor: str, rowid: int, change: GraphChange) -> None:
        """In one transaction: add ``change``'s nodes and edges, replace the estimates, session
        rows and pending votes it carries, bump the epoch when asked, and move cursor ``cursor``
        to ``rowid``."""
        ...

    def graph_records(self) -> tuple[list[GraphNodeRow], list[GraphEdgeRow]]:
        """Every node (in insertion order) and edge (in insertion order)."""
        ...

    def graph_pending(self) -> bytes | None:
        """The back-end's pending votes as last committed with the graph (None: never)."""
        ...

    def graph_epoch(self) -> int:
        """How many times the back-end asked for an object-map rebuild (0: never)."""
        ...

    def graph_poses(self, keys: Sequence[NodeKey]) -> dict[NodeKey, NDArray[np.float64] | None]:
        """The latest ``T_map_camera`` estimate of each key (None: not anchored or unknown)."""
        ...

    def session_anchors(self) -> list[SessionAnchor]:
        """Every session the back-end has seen, ordered by ``(robot_id, session_id)``."""
        ...

    def latest_nodes(self) -> dict[str, GraphNodeRow]:
        """Per robot, the node the back-end added last (codes empty)."""
        ...

    def map_trajectory(self, robot_id: str, session_id: str | None = None) -> Trajectory:
        """Stamps and map-frame camera poses (latest estimates) of ``robot_id``'s keyframes
        whose session is anchored, ordered by ``(stamp, session_id, seq)``."""
        ...


class TokenStore(Protocol):
    """The REST API's bearer tokens (``server/api/auth.py``), secrets stored only as digests."""

    def add_token(self, token: TokenRecord) -> None:
        """Store a new token; StoreError when its ``token_id`` exists."""
        ...

    def token(self, token_id: str) -> TokenRecord | None:
        """The token ``token_id`` (revoked ones too), or None."""
        ...

    def tokens(self) -> list[TokenRecord]:
        """Every token, revoked ones too, oldest first."""
        ...

    def revoke_token(self, token_id: str, revoked_s: float) -> bool:
        """Mark ``token_id`` revoked at ``revoked_s``; False when no such valid token exists."""
        ...


class WriterLease(Protocol):
    """A handle on the store's one writer lease: whoever holds it runs the mapping stage and the
    back-end (the only writers of cursors, measurements, the pose graph and the object map), so
    several servers on one database have one writer at a time. Not acquired when made.

    The lease lives as long as its holder's hold on the database does (PostgreSQL: a session
    advisory lock on a connection of its own, released by the database when that connection
    closes or its process dies); SQLite serves one server, which always holds it. Taking it
    bumps the store's writer fence: from then on the map writes (graph, measurements, cursors,
    checkpoint, objects) of a store whose lease was taken before are refused (StoreError), so a
    holder that lost the lease cannot write after its successor started. Thread safe.

    Attributes:
        holder: the name this handle holds the lease under (shown by :meth:`current_holder`).
    """

    holder: str

    def acquire(self) -> bool:
        """Take the lease if nobody holds it; True when this handle holds it now. Never raises
        (a database it cannot reach is False)."""
        ...

    def held(self) -> bool:
        """Whether this handle still holds the lease (asks the database); never raises. False
        once the hold is lost (connection gone): the holder must stop writing."""
        ...

    def current_holder(self) -> str | None:
        """The holder's name as any server sees it, None when nobody holds the lease or the
        database cannot tell now; never raises."""
        ...

    def release(self) -> None:
        """Give the lease back (idempotent)."""
        ...


class LeaseStore(Protocol):
    """The writer lease of several servers on one store (:class:`WriterLease`)."""

    def writer_lease(self, holder: str) -> WriterLease:
        """A new handle on the writer lease for ``holder`` (1-40 printable ASCII characters),
        not acquired; StoreError for a bad name."""
        ...


class MapStore(KeyframeStore, ObjectStore, MappingStore, PerceptionStore, GraphStore, TokenStore, LeaseStore,
               Protocol):
    """The server's whole database: what a backend implements (see the module docstring)."""

    def __enter__(self) -> MapStore: ...

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None: ...

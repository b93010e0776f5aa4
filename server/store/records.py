"""The records every map store backend reads and writes, and its errors.

Frames and units follow docs/ARCHITECTURE.md. ``*_s`` values are the server's wall-clock
seconds (``time.time()``); ``stamp`` is the robot's capture time. ``rowid`` is a keyframe's
place in insertion order (1, 2, ...; 0 is "before the first"): the mapping stage's cursors
count in it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final, Literal, TypeAlias

import numpy as np
from numpy.typing import NDArray

from wardmap.server.perception.types import ObjectMeasurement
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import WardmapError

F64: TypeAlias = NDArray[np.float64]
Vec3: TypeAlias = tuple[float, float, float]
Vec4: TypeAlias = tuple[float, float, float, float]

MAX_PAGE: Final = 1000
"""Largest ``limit`` :meth:`KeyframeStore.keyframes` accepts."""
MAX_REASON_LEN: Final = 200
"""Longest rejection reason, in characters."""


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


class UnknownObjectError(StoreError):
    """An object id the store does not hold; the message names it."""


# --------------------------------------------------------------------------- keyframes

InsertResult: TypeAlias = Literal["stored", "duplicate"]
KeyCursor: TypeAlias = tuple[str, int]
"""``(session_id, seq)`` of a keyframe of the queried robot: the page starts after it."""
Cursor: TypeAlias = KeyCursor | float
"""A :data:`KeyCursor`, or a stamp in seconds: the page starts at the first stamp above it."""
Trajectory: TypeAlias = tuple[NDArray[np.float64], NDArray[np.float64]]
"""``(stamps (N,) seconds, T_odom_camera (N, 4, 4))``."""


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
        schema_version: the schema version of the store.
    """

    robots: int
    sessions: int
    keyframes: int
    payload_bytes: int
    rejections: int
    schema_version: int


# --------------------------------------------------------------------------- objects


@dataclass(frozen=True, eq=False)
class Observation:
    """One measurement of an object in a keyframe (paper 000 Eq. 1: class, pose, size).

    Attributes:
        object_id: the object it belongs to (in the same upsert or already stored).
        robot_id, session_id, seq: the keyframe.
        stamp: keyframe capture time, robot clock, seconds.
        category: measured class (may differ from the object's).
        confidence: detector score in [0, 1].
        box_xyxy: (4,) float64 ``x1, y1, x2, y2`` pixel box in the keyframe's colour image;
            with the keyframe it identifies the measurement.
        T_world_object: (4, 4) float64 measured object pose in ``world``.
        size: (3,) float64 measured extent, metres.
    """

    object_id: int
    robot_id: str
    session_id: str
    seq: int
    stamp: float
    category: str
    confidence: float
    box_xyxy: NDArray[np.float64]
    T_world_object: NDArray[np.float64]
    size: NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class ObservationRecord(Observation):
    """A stored :class:`Observation` with its row id and the server time it was first added."""

    observation_id: int
    added_s: float


@dataclass(frozen=True, eq=False)
class ObjectRow:
    """One object as the store writes it: a checked object state with its derived geometry.

    Attributes:
        object_id, category, confidence, T_world_object, color_rgb, confirmed: as in
            ``ObjectState`` (``server/objectmap.py``).
        yaw: heading of the object's x axis about world z, radians in (-pi, pi].
        q_xyzw: the rotation of ``T_world_object`` as a unit quaternion.
        size: (x, y, z) extent, metres.
        bounds_min, bounds_max: world-axis-aligned bounds of the oriented box, metres.
    """

    object_id: int
    category: str
    confidence: float
    T_world_object: NDArray[np.float64]
    yaw: float
    q_xyzw: Vec4
    size: Vec3
    bounds_min: Vec3
    bounds_max: Vec3
    color_rgb: Vec3 | None
    confirmed: bool


@dataclass(frozen=True, eq=False)
class ObjectRecord:
    """One stored object.

    Attributes:
        object_id, category, confidence, T_world_object, color_rgb, confirmed: as in
            ``ObjectState`` (``server/objectmap.py``).
        position: ``T_world_object[:3, 3]``, metres.
        q_xyzw: the rotation of ``T_world_object`` as a unit quaternion (x, y, z, w).
        yaw: heading of the object's x axis about world z, radians in (-pi, pi].
        size: (x, y, z) extent, metres.
        bounds_min, bounds_max: world-axis-aligned bounds of the oriented box, metres.
        n_observations: stored observations.
        first_seen_s, last_seen_s: server seconds when the object was created or first
            observed (the earlier) and when it was last observed (its creation if never).
        robots: robots with an observation of it, sorted.
    """

    object_id: int
    category: str
    confidence: float
    T_world_object: NDArray[np.float64]
    position: Vec3
    q_xyzw: Vec4
    yaw: float
    size: Vec3
    bounds_min: Vec3
    bounds_max: Vec3
    color_rgb: Vec3 | None
    n_observations: int
    first_seen_s: float
    last_seen_s: float
    robots: tuple[str, ...]
    confirmed: bool = True


@dataclass(frozen=True, eq=False)
class ObjectWrite:
    """An object :meth:`ObjectStore.write_objects` touched: its record after the write, and
    whether the write created it (False: it existed, or only its observations changed)."""

    record: ObjectRecord
    created: bool


@dataclass(frozen=True, eq=False)
class ObjectHit:
    """A query result: the object and, when the query has ``near``, its centre's distance (m)."""

    record: ObjectRecord
    distance_m: float | None


@dataclass(frozen=True, eq=False)
class ObjectPage:
    """One page of a query; ``next_offset`` is None on the last page."""

    hits: list[ObjectHit]
    next_offset: int | None


CompactRow = tuple[int, str, float, float, float, float, float, float, float]
"""What a floor view draws of an object: ``(object_id, category, x, y, z, yaw, size_x, size_y,
size_z)``; the centre in map-frame metres, the yaw in radians, the size in metres."""


@dataclass(frozen=True, eq=False)
class CompactPage:
    """One page of a query as :data:`CompactRow` tuples (same order and paging as its
    :class:`ObjectPage`); ``next_offset`` is None on the last page."""

    rows: list[CompactRow]
    next_offset: int | None


@dataclass(frozen=True, slots=True)
class KeyframeRef:
    """A keyframe an object was observed in; ``stored`` says whether the store holds it."""

    robot_id: str
    session_id: str
    seq: int
    stamp: float
    stored: bool


@dataclass(frozen=True, eq=False)
class ObjectDetail:
    """One object, its latest observations (newest first) and their keyframes (by stamp)."""

    record: ObjectRecord
    observations: list[ObservationRecord]
    keyframes: list[KeyframeRef]


# --------------------------------------------------------------------------- the mapping stage


@dataclass(frozen=True, slots=True)
class KeyframeKey:
    """A stored keyframe's key and its place in insertion order."""

    rowid: int
    robot_id: str
    session_id: str
    seq: int

    @property
    def key(self) -> str:
        """``"<robot>/<session>/<seq>"``, the keyframe's name in measurements."""
        return f"{self.robot_id}/{self.session_id}/{self.seq}"


@dataclass(frozen=True, slots=True)
class StoredKeyframe(KeyframeKey):
    """A stored keyframe with its wire bytes."""

    payload: bytes


@dataclass(frozen=True, eq=False)
class MappedPose:
    """The camera pose a processed keyframe's measurements were computed with, and its camera.

    Attributes:
        robot_id, session_id, seq: the keyframe.
        T_map_camera: (4, 4) float64 colour-camera pose the measurements are expressed with:
            ``T_map_odom @ T_odom_camera`` with the session's map-pose prior, or its odom pose
            when it has none (the back-end's estimate moves them to the map at association);
            None for an undecodable payload or one without intrinsics.
        camera: its colour camera; None exactly when ``T_map_camera`` is None.
    """

    robot_id: str
    session_id: str
    seq: int
    T_map_camera: NDArray[np.float64] | None
    camera: PinholeCamera | None


@dataclass(frozen=True, eq=False)
class AnchoredKeyframe:
    """A processed keyframe on the map with its stored measurements, for replay.

    Attributes:
        rowid, robot_id, session_id, seq: the keyframe.
        T_map_camera: (4, 4) float64 colour-camera pose in the map frame: the back-end's
            latest estimate.
        camera: its colour camera.
        measurements: its measurements in the order they were stored (masks empty), in the
            frame of ``T_measured_camera``.
        T_measured_camera: (4, 4) float64 the camera pose the measurements were computed with
            (:class:`MappedPose`); ``T_map_camera @ inv(T_measured_camera)`` takes them to the map.
    """

    rowid: int
    robot_id: str
    session_id: str
    seq: int
    T_map_camera: NDArray[np.float64]
    camera: PinholeCamera
    measurements: Sequence[ObjectMeasurement]
    T_measured_camera: NDArray[np.float64] | None = None


@dataclass(frozen=True, slots=True)
class ClaimedKeyframe(KeyframeKey):
    """A stored keyframe a perception worker claimed (``PerceptionStore.claim_keyframe``).

    Attributes:
        payload: its wire bytes.
        attempts: how many claims it has had, this one included (a worker that died or failed
            unexpectedly left the earlier ones to expire).
    """

    payload: bytes
    attempts: int


@dataclass(frozen=True, eq=False)
class Perceived:
    """A keyframe's perception result, as the worker that measured it stored it.

    Attributes:
        pose: the keyframe and the colour-camera pose its measurements were computed with
            (:class:`MappedPose`; both None when it was not measured).
        anchored: its session had ``T_map_odom`` (the robot's map-pose prior).
        measurements: its object measurements (masks empty once stored), in the frame of
            ``pose.T_map_camera``.
        failure: why perception skipped it (``"<error type>: <message>"``, at most
            ``MAX_REASON_LEN`` characters), None when it was measured.
    """

    pose: MappedPose
    anchored: bool
    measurements: Sequence[ObjectMeasurement]
    failure: str | None = None


@dataclass(frozen=True, eq=False)
class PerceptionSlot:
    """A keyframe ahead of the mapping stage's cursor with what perception has of it.

    Attributes:
        rowid, robot_id, session_id, seq: the keyframe.
        result: its stored perception result, None while it has none.
        claim_expires_s: when the claim on it expires (server wall-clock seconds; None: never
            claimed, or its result is stored).
    """

    rowid: int
    robot_id: str
    session_id: str
    seq: int
    result: Perceived | None
    claim_expires_s: float | None

    @property
    def key(self) -> str:
        """``"<robot>/<session>/<seq>"``."""
        return f"{self.robot_id}/{self.session_id}/{self.seq}"


@dataclass(frozen=True, slots=True)
class ClosedSession:
    """A session whose last keyframe group the mapping stage closed when its cursor was at
    ``at_rowid`` (it went quiet)."""

    at_rowid: int
    robot_id: str
    session_id: str


@dataclass(frozen=True, eq=False)
class Checkpoint:
    """The mapping stage's association state at a settled cursor.

    Attributes:
        last_rowid: the cursor the state belongs to.
        config_key: what the state is valid for (code and settings), compared as text.
        state: the encoded state (``server/mapping/checkpoint.py``).
        written_s: server wall-clock seconds when it was written.
    """

    last_rowid: int
    config_key: str
    state: bytes
    written_s: float


NodeKey = tuple[str, str, int]
"""A keyframe of the pose graph: ``(robot_id, session_id, seq)``."""


@dataclass(frozen=True, eq=False)
class GraphNodeRow:
    """One pose-graph node (a keyframe) as the back-end stores it.

    Attributes:
        key: the keyframe.
        stamp: its capture time, Unix seconds.
        T_odom_camera: (4, 4) float64 its tracked pose in the session's odom frame.
        pose_source: the tracker's pose source (wire ``pose_source``).
        T_map_camera: (4, 4) float64 its latest estimate on the map; None while its
            session is not anchored.
        prior_T_map_odom: (4, 4) float64 the ``--map-pose`` prior it came with, or None.
        codes: its place-recognition code (random-fern block codes, one byte per block).
    """

    key: NodeKey
    stamp: float
    T_odom_camera: NDArray[np.float64]
    pose_source: str
    T_map_camera: NDArray[np.float64] | None
    prior_T_map_odom: NDArray[np.float64] | None
    codes: bytes


@dataclass(frozen=True, eq=False)
class GraphEdgeRow:
    """One pose-graph factor.

    Attributes:
        kind: ``odometry`` (consecutive keyframes), ``loop`` (a verified place match) or
            ``prior`` (a ``--map-pose`` prior or the map's gauge; ``b`` is None).
        a, b: the keyframes it links (``T_a_b`` maps ``b``'s camera frame to ``a``'s).
        T_a_b: (4, 4) float64 the measured relative pose (for a prior: ``T_map_a``).
        sigmas: (6,) float64 standard deviations, rotation (rad, 3) then translation (m, 3).
        robust: under a robust kernel (loop edges).
        inliers: verified feature inliers (loop edges; 0 otherwise).
    """

    kind: str
    a: NodeKey
    b: NodeKey | None
    T_a_b: NDArray[np.float64]
    sigmas: NDArray[np.float64]
    robust: bool
    inliers: int = 0


@dataclass(frozen=True, eq=False)
class SessionAnchor:
    """Where a robot session is on the map.

    Attributes:
        robot_id, session_id: the session.
        T_map_odom: (4, 4) float64 its odom frame on the map; None while it is not anchored.
        anchored_s: server wall-clock seconds when it was anchored (None: not yet).
        anchored_to: ``"<robot>/<session>"`` it was anchored through (itself: it set the map
            or came with a map-pose prior; empty: not anchored).
        revision: how many times its ``T_map_odom`` was published (increases by one each time).
    """

    robot_id: str
    session_id: str
    T_map_odom: NDArray[np.float64] | None
    anchored_s: float | None
    anchored_to: str
    revision: int


@dataclass(frozen=True, eq=False)
class GraphChange:
    """What one back-end step adds to the stored pose graph (written in one transaction).

    Attributes:
        nodes: new nodes.
        edges: new factors.
        estimates: ``(key, T_map_camera)`` of nodes whose estimate changed.
        sessions: sessions whose anchoring or ``T_map_odom`` changed (replacing their row).
        bump_epoch: the map moved enough that the object map must be rebuilt (the mapping
            stage re-associates when the epoch changes).
        pending: the back-end's pending votes (``BackendCore.pending_state``), replacing the
            stored ones; None: unchanged.
    """

    nodes: Sequence[GraphNodeRow] = ()
    edges: Sequence[GraphEdgeRow] = ()
    estimates: Sequence[tuple[NodeKey, NDArray[np.float64]]] = ()
    sessions: Sequence[SessionAnchor] = ()
    bump_epoch: bool = False
    pending: bytes | None = None


# --------------------------------------------------------------------------- REST API tokens

TokenScope: TypeAlias = Literal["read", "admin"]
"""``read``: every read route; ``admin``: also the routes that change state."""


@dataclass(frozen=True, slots=True)
class TokenRecord:
    """A REST API bearer token as stored: its secret only as a SHA-256 digest.

    Attributes:
        token_id: the token's public id (in its text, ``wm_<token_id>_<secret>``; names it in
            ``wardmap token list`` and ``revoke``).
        name: what it is for (free text, may be empty).
        scope: ``read`` or ``admin``.
        secret_sha256: the 32-byte SHA-256 digest of the secret part.
        created_s: server wall-clock seconds when it was created.
        revoked_s: when it was revoked (None: valid).
    """

    token_id: str
    name: str
    scope: TokenScope
    secret_sha256: bytes
    created_s: float
    revoked_s: float | None = None

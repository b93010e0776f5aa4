"""The REST API's response bodies (pydantic), separate from the store's dataclasses.

An object's body (:class:`ObjectOut`) is the shared map message
(:class:`~wardmap.shared.mapwire.MapObject`, ``object_to_wire``): the same fields as an
object over Zenoh. The list route sends that dict directly (latency); the tests validate it
against these models.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel

__all__ = [
    "CategoryList",
    "CategoryOut",
    "ErrorOut",
    "Flag",
    "Health",
    "KeyframeList",
    "KeyframeOut",
    "KeyframeRefOut",
    "ObjectDetailOut",
    "ObjectList",
    "ObjectOut",
    "ObservationOut",
    "PoseOut",
    "RobotList",
    "RobotOut",
    "TrajectoryOut",
    "TransformOut",
]


Flag = Literal["true", "false"]
"""A query flag: the two words the Zenoh queryable's parser takes too (``ObjectQuery.from_params``),
so a robot and an HTTP client cannot get different answers from one query string."""


class Health(BaseModel):
    status: Literal["ok"]


class Readiness(BaseModel):
    """``ok``, or why keyframes cannot be stored now; with a mapping stage, whether this server
    runs it (``writer``: it holds the store's writer lease) or not (``standby``), and who does
    (None: nobody, or the database could not tell)."""

    status: str
    mapping: Literal["writer", "standby"] | None = None
    writer: str | None = None


class RobotOut(BaseModel):
    robot_id: str
    keyframes: int
    sessions: int
    first_seen_s: float
    last_seen_s: float
    """Server time of its latest keyframe, Unix seconds."""
    session_id: str | None = None
    """Its latest session (the one the fields below describe); None before the back-end saw it."""
    anchored: bool = False
    """Whether that session is on the shared map (anchored by a verified place match, a map
    pose given at start, or by being the first session of the map)."""
    anchored_at_s: float | None = None
    anchored_to: str | None = None
    """The session (``robot/session``) it was anchored through; itself when it set the map."""
    T_map_odom: TransformOut | None = None
    """The session's odom frame on the map (what the robot was sent)."""
    map_pose: PoseOut | None = None
    """Its latest keyframe's camera pose on the map (back-end estimate)."""


class RobotList(BaseModel):
    robots: list[RobotOut]


class KeyframeOut(BaseModel):
    robot_id: str
    session_id: str
    seq: int
    stamp: float
    received_s: float
    pose_source: str
    payload_bytes: int


class KeyframeList(BaseModel):
    keyframes: list[KeyframeOut]
    next_cursor: str | None
    """Opaque; pass as ``cursor`` for the next page. None on the last page."""


class PoseOut(BaseModel):
    stamp: float
    t: list[float]
    """Translation ``[x, y, z]`` of the camera in the trajectory's frame, metres."""
    q_xyzw: list[float]


class TrajectoryOut(BaseModel):
    robot_id: str
    frame: str = "map"
    """``map``: back-end estimates of the keyframes of anchored sessions; ``odom``: the poses
    the robot tracked, each session in its own odom frame."""
    poses: list[PoseOut]


class ErrorOut(BaseModel):
    detail: str


class InvalidOut(BaseModel):
    """A 422: a filter the map refused (``detail`` says why) or, from FastAPI's parameter
    validation, a list of ``{type, loc, msg, input, ...}`` errors."""

    detail: str | list[dict[str, Any]]


class TransformOut(BaseModel):
    """A pose in the wire form of ``docs/wire.md``: translation and unit quaternion."""

    t: list[float]
    """Translation ``[x, y, z]``, metres."""
    q_xyzw: list[float]


class ObjectOut(BaseModel):
    """One object of the map (``shared/mapwire.py`` ``MapObject``); world frame, metres."""

    object_id: int
    category: str
    confidence: float
    position: list[float]
    """Centre of the object's box ``[x, y, z]``, metres (``T_world_object.t``)."""
    q_xyzw: list[float]
    """Orientation of the object frame (x forward, z up) in the world frame (``T_world_object.q_xyzw``)."""
    T_world_object: TransformOut
    """The object's pose as Zenoh sends it: ``position`` and ``q_xyzw`` together."""
    yaw: float
    """Heading of the object's x axis about world z, radians."""
    size: list[float]
    """Extent along the object's x, y, z, metres."""
    bounds_min: list[float]
    bounds_max: list[float]
    color_rgb: list[float] | None
    """Mean colour ``[R, G, B]`` in 0..255; None when unknown."""
    n_observations: int
    first_seen_s: float
    last_seen_s: float
    robots: list[str]
    confirmed: bool = True
    """False while association has not confirmed the object: a standing class (bed, cabinet,
    cart, chair, desk, wheelchair) seen only in flat slivers at the side of the view; listed
    only with ``include_unconfirmed=true`` (docs/association.md, Confirmation)."""
    distance_m: float | None = None
    """Distance of the centre from ``near`` (only when ``near`` was given)."""


class ObjectList(BaseModel):
    objects: list[ObjectOut]
    limit: int
    offset: int
    next_offset: int | None
    """Pass as ``offset`` for the next page; None on the last page."""


class ObservationOut(BaseModel):
    observation_id: int
    robot_id: str
    session_id: str
    seq: int
    stamp: float
    added_s: float
    category: str
    confidence: float
    box_xyxy: list[float]
    position: list[float]
    q_xyzw: list[float]
    size: list[float]


class KeyframeRefOut(BaseModel):
    robot_id: str
    session_id: str
    seq: int
    stamp: float
    stored: bool
    """Whether the keyframe store holds this keyframe."""


class ObjectDetailOut(BaseModel):
    object: ObjectOut
    observations: list[ObservationOut]
    """The latest observations, newest first (at most ``observations`` of the request)."""
    keyframes: list[KeyframeRefOut]


class CategoryOut(BaseModel):
    name: str
    mobility: str | None
    """``moving``, ``movable`` or ``static`` (knowledge graph); None for a class it no longer has."""
    count: int


class CategoryList(BaseModel):
    categories: list[CategoryOut]
    total: int

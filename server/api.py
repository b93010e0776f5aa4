"""The map server's REST API (FastAPI).

:func:`create_app` builds the app; its lifespan opens the keyframe store, builds the
:class:`~wardmap.server.objectmap.ObjectMap` on it (and starts an optional
:class:`~wardmap.server.ingest.Ingest` and zenoh map service) and closes them on shutdown, so importing
this module or calling :func:`create_app` opens nothing. Routes get their collaborators via
``Annotated[..., Depends(...)]``; response bodies are the pydantic models below, separate
from the store's dataclasses. :class:`~wardmap.shared.errors.WardmapError` maps to HTTP in
one place (:func:`_wardmap_error`).
"""

from __future__ import annotations

import base64
import binascii
import json
import logging
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Annotated, Any, Literal, Protocol

from fastapi import Depends, FastAPI, HTTPException, Query, Request
from fastapi.responses import JSONResponse, PlainTextResponse
from pydantic import BaseModel

from wardmap.server.ingest import Ingest, IngestCounters
from wardmap.server.mapmessages import map_object
from wardmap.server.objectmap import (
    DEFAULT_LIMIT,
    MAX_LIMIT,
    MAX_OBSERVATIONS,
    MAX_OFFSET,
    ObjectMap,
    ObjectMapError,
    ObjectQuery,
    parse_near,
)
from wardmap.server.perception.measure import SKIP_KINDS
from wardmap.server.pipeline import MapPipeline, PipelineCounters, PipelineFactory
from wardmap.server.store import MAX_PAGE, KeyframeStore, StoreError, open_store
from wardmap.shared.errors import KnowledgeGraphError, WardmapError
from wardmap.shared.mapwire import object_to_wire
from wardmap.shared.se3 import rotation_to_quat, transform_to_tum

log = logging.getLogger(__name__)

__all__ = ["create_app"]

IngestFactory = Callable[[KeyframeStore], Ingest]

Flag = Literal["true", "false"]
"""A query flag: the two words the Zenoh queryable's parser takes too (``ObjectQuery.from_params``),
so a robot and an HTTP client cannot get different answers from one query string."""


class Service(Protocol):
    """A component the lifespan starts after the store opened and stops before it closes."""

    def start(self) -> None: ...

    def stop(self) -> None: ...


MapServeFactory = Callable[[ObjectMap], Service]


# --------------------------------------------------------------------------- wire schemas


class Health(BaseModel):
    status: Literal["ok"]


class RobotOut(BaseModel):
    robot_id: str
    keyframes: int
    sessions: int
    first_seen_s: float
    last_seen_s: float


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
    """Translation ``[x, y, z]`` of the camera in the session's odom frame, metres."""
    q_xyzw: list[float]


class TrajectoryOut(BaseModel):
    robot_id: str
    poses: list[PoseOut]


class ErrorOut(BaseModel):
    detail: str


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


def _vec(values: Any) -> list[float]:
    return [float(v) for v in values]


# --------------------------------------------------------------------------- cursors


def encode_cursor(session_id: str, seq: int) -> str:
    """Opaque page cursor for ``(session_id, seq)``: urlsafe base64 of a JSON pair."""
    return base64.urlsafe_b64encode(json.dumps([session_id, seq]).encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[str, int]:
    """Inverse of :func:`encode_cursor`; raises ValueError on anything else."""
    try:
        raw = base64.b64decode(cursor + "=" * (-len(cursor) % 4), altchars=b"-_", validate=True)
        value = json.loads(raw)
    except (binascii.Error, ValueError, UnicodeDecodeError) as exc:
        raise ValueError("malformed cursor") from exc
    if (
        not isinstance(value, list) or len(value) != 2 or not isinstance(value[0], str)
        or isinstance(value[1], bool) or not isinstance(value[1], int)
    ):
        raise ValueError("malformed cursor")
    return value[0], value[1]


# --------------------------------------------------------------------------- dependencies


def get_store(request: Request) -> KeyframeStore:
    store: KeyframeStore = request.app.state.store
    return store


def get_ingest(request: Request) -> Ingest | None:
    ingest: Ingest | None = request.app.state.ingest
    return ingest


def get_objectmap(request: Request) -> ObjectMap:
    objects: ObjectMap = request.app.state.objectmap
    return objects


StoreDep = Annotated[KeyframeStore, Depends(get_store)]
ObjectMapDep = Annotated[ObjectMap, Depends(get_objectmap)]
IngestDep = Annotated[Ingest | None, Depends(get_ingest)]


# --------------------------------------------------------------------------- app


def create_app(
    store_url: str,
    *,
    ingest_factory: IngestFactory | None = None,
    mapserve_factory: MapServeFactory | None = None,
    pipeline_factory: PipelineFactory | None = None,
) -> FastAPI:
    """The FastAPI app serving the keyframe store at ``store_url``.

    Args:
        store_url: ``sqlite:///PATH`` (see :func:`~wardmap.server.store.open_store`); opened
            in the lifespan, not here.
        ingest_factory: builds the :class:`Ingest` from the open store; it is started after
            the store opened and stopped before the store closes. None: API only.
        mapserve_factory: builds the zenoh map service (``server/mapserve.py``) from the
            :class:`ObjectMap`; started after the ingest, stopped before it. None: REST only.
        pipeline_factory: builds the mapping stage (``server/pipeline.py``: perception,
            association, object map) from the store and the object map; started last,
            stopped first. None: keyframes are stored but not mapped.
    """

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        store = open_store(store_url)
        ingest: Ingest | None = None
        mapserve: Service | None = None
        pipeline: MapPipeline | None = None
        try:
            objectmap = ObjectMap(store)
            if ingest_factory is not None:
                ingest = ingest_factory(store)
                ingest.start()
            if mapserve_factory is not None:
                mapserve = mapserve_factory(objectmap)
                mapserve.start()
            if pipeline_factory is not None:
                pipeline = pipeline_factory(store, objectmap)
                pipeline.start()
            app.state.store = store
            app.state.pipeline = pipeline
            app.state.ingest = ingest
            app.state.objectmap = objectmap
            yield
        finally:
            if pipeline is not None:
                pipeline.stop()
            if mapserve is not None:
                mapserve.stop()
            if ingest is not None:
                ingest.stop()
            store.close()

    app = FastAPI(title="wardmap map server", version="1", lifespan=lifespan)
    app.add_exception_handler(WardmapError, _wardmap_error)

    @app.get("/healthz", response_model=Health)
    def healthz() -> Health:
        return Health(status="ok")

    @app.get("/v1/robots", response_model=RobotList)
    def robots(store: StoreDep) -> RobotList:
        return RobotList(robots=[
            RobotOut(robot_id=r.robot_id, keyframes=r.keyframes, sessions=r.sessions,
                     first_seen_s=r.first_seen_s, last_seen_s=r.last_seen_s)
            for r in store.robots()
        ])

    @app.get("/v1/keyframes", response_model=KeyframeList, responses={400: {"model": ErrorOut}})
    def keyframes(
        store: StoreDep,
        robot: Annotated[str, Query(min_length=1, max_length=64)],
        limit: Annotated[int, Query(ge=1, le=MAX_PAGE)] = 100,
        cursor: Annotated[str | None, Query(max_length=512)] = None,
    ) -> KeyframeList:
        after = None
        if cursor is not None:
            try:
                after = decode_cursor(cursor)
            except ValueError as exc:
                raise HTTPException(400, f"bad cursor {cursor[:80]!r}") from exc
        page = store.keyframes(robot, after=after, limit=limit)
        return KeyframeList(
            keyframes=[
                KeyframeOut(robot_id=r.robot_id, session_id=r.session_id, seq=r.seq, stamp=r.stamp,
                            received_s=r.received_s, pose_source=r.pose_source, payload_bytes=r.payload_bytes)
                for r in page.rows
            ],
            next_cursor=None if page.next_cursor is None else encode_cursor(*page.next_cursor),
        )

    @app.get(
        "/v1/robots/{robot_id}/trajectory",
        response_model=None,
        responses={200: {"model": TrajectoryOut}, 404: {"model": ErrorOut}},
    )
    def trajectory(
        store: StoreDep,
        robot_id: str,
        format: Annotated[Literal["tum", "json"], Query()] = "json",
    ) -> Any:
        stamps, T = store.trajectory(robot_id)
        if len(stamps) == 0:
            raise HTTPException(404, f"unknown robot {robot_id!r}")
        if format == "tum":
            lines = ["# timestamp tx ty tz qx qy qz qw"]
            for stamp, M in zip(stamps, T, strict=True):
                row = transform_to_tum(M)
                lines.append(f"{stamp:.6f} " + " ".join(f"{v:.9g}" for v in row))
            return PlainTextResponse("\n".join(lines) + "\n")
        poses = []
        for stamp, M in zip(stamps, T, strict=True):
            row = transform_to_tum(M)
            poses.append(PoseOut(stamp=float(stamp), t=[float(v) for v in row[:3]],
                                 q_xyzw=[float(v) for v in row[3:]]))
        return TrajectoryOut(robot_id=robot_id, poses=poses)

    @app.get(
        "/v1/objects",
        response_model=None,
        responses={
            200: {"model": ObjectList},
            422: {"model": ErrorOut, "description": "a bad filter (message in detail)"},
        },
    )
    # async: the work is short and mostly GIL-bound Python, so a worker-thread hop only adds latency.
    async def objects(
        objects: ObjectMapDep,
        category: Annotated[str | None, Query(max_length=64, description="knowledge-graph class")] = None,
        near: Annotated[
            str | None,
            Query(max_length=200, description="world point `x,y,z` in metres: nearest first, with distance"),
        ] = None,
        radius: Annotated[
            float | None, Query(description="metres (>= 0) around `near`; needs `near`")
        ] = None,
        min_confidence: Annotated[float | None, Query(description="in [0, 1]")] = None,
        robot: Annotated[str | None, Query(max_length=64, description="seen by this robot")] = None,
        limit: Annotated[int, Query(ge=1, le=MAX_LIMIT)] = DEFAULT_LIMIT,
        offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
        include_unconfirmed: Annotated[
            Flag, Query(description="also objects association has not confirmed (`confirmed` false)")
        ] = "false",
    ) -> JSONResponse:
        """Objects matching every filter; nearest centre first when `near` is given, else by id."""
        try:
            centre = None if near is None else parse_near(near)
            page = objects.find(ObjectQuery(category, centre, radius, min_confidence, robot, limit, offset,
                                            include_unconfirmed == "true"))
        except ObjectMapError as exc:
            raise HTTPException(422, str(exc)) from exc
        return JSONResponse({
            "objects": [object_to_wire(map_object(hit.record, hit.distance_m)) for hit in page.hits],
            "limit": limit, "offset": offset, "next_offset": page.next_offset,
        })

    @app.get(
        "/v1/objects/{object_id}",
        response_model=ObjectDetailOut,
        responses={404: {"model": ErrorOut}, 422: {"model": ErrorOut}},
    )
    def object_detail(
        objects: ObjectMapDep,
        object_id: int,
        observations: Annotated[int, Query(ge=0, le=MAX_OBSERVATIONS)] = 100,
    ) -> ObjectDetailOut:
        """One object with its latest observations and the keyframes they came from."""
        try:
            detail = objects.get(object_id, max_observations=observations)
        except ObjectMapError as exc:
            raise HTTPException(422, str(exc)) from exc
        if detail is None:
            raise HTTPException(404, f"unknown object {object_id}")
        return ObjectDetailOut(
            object=ObjectOut.model_validate(object_to_wire(map_object(detail.record))),
            observations=[
                ObservationOut(
                    observation_id=o.observation_id, robot_id=o.robot_id, session_id=o.session_id,
                    seq=o.seq, stamp=o.stamp, added_s=o.added_s, category=o.category,
                    confidence=o.confidence, box_xyxy=_vec(o.box_xyxy),
                    position=_vec(o.T_world_object[:3, 3]),
                    q_xyzw=_vec(rotation_to_quat(o.T_world_object[:3, :3])), size=_vec(o.size),
                )
                for o in detail.observations
            ],
            keyframes=[
                KeyframeRefOut(robot_id=k.robot_id, session_id=k.session_id, seq=k.seq, stamp=k.stamp,
                               stored=k.stored)
                for k in detail.keyframes
            ],
        )

    @app.get("/v1/categories", response_model=CategoryList)
    def categories(
        objects: ObjectMapDep,
        include_unconfirmed: Annotated[Flag, Query(description="also count unconfirmed objects")] = "false",
    ) -> CategoryList:
        """Every knowledge-graph class with its number of (confirmed) objects in the map."""
        counts = objects.categories(include_unconfirmed == "true")
        out = []
        for name, n in counts.items():
            try:
                mobility: str | None = str(objects.knowledge.mobility(name))
            except KnowledgeGraphError:
                mobility = None
            out.append(CategoryOut(name=name, mobility=mobility, count=n))
        return CategoryList(categories=out, total=sum(counts.values()))

    @app.get("/metrics", response_class=PlainTextResponse)
    def metrics(store: StoreDep, ingest: IngestDep, objects: ObjectMapDep, request: Request) -> str:
        counters = ingest.counters() if ingest is not None else None
        pipeline: MapPipeline | None = getattr(request.app.state, "pipeline", None)
        text = _prometheus(counters, store.rejections(), store.stats().robots)
        text += (
            "# HELP wardmap_map_objects Objects in the map; confirmed=\"false\": kept, left out of queries.\n"
            "# TYPE wardmap_map_objects gauge\n"
            f'wardmap_map_objects{{confirmed="true"}} {objects.count(unconfirmed=False)}\n'
            f'wardmap_map_objects{{confirmed="false"}} {objects.count(unconfirmed=True)}\n'
        )
        return text + (_pipeline_metrics(pipeline.counters()) if pipeline is not None else "")

    return app


async def _wardmap_error(request: Request, exc: Exception) -> JSONResponse:
    """The one place a WardmapError becomes an HTTP status: bad store arguments are 400."""
    status = 400 if isinstance(exc, StoreError) else 500
    if status == 500:
        log.error("%s %s failed: %s", request.method, request.url.path, exc)
    return JSONResponse({"detail": str(exc)}, status_code=status)


def _label(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _pipeline_metrics(c: PipelineCounters) -> str:
    """The mapping stage's counters, Prometheus text format."""
    rows = [
        ("wardmap_mapping_backlog", "gauge", "Stored keyframes the mapping stage has not processed yet.",
         [("", c.backlog)]),
        ("wardmap_mapping_keyframes_total", "counter", "Keyframes run through perception by this process.",
         [("", c.processed)]),
        ("wardmap_mapping_measurements_total", "counter", "Object measurements stored by this process.",
         [("", c.measurements)]),
        ("wardmap_mapping_associated_total", "counter", "Keyframes fed to association (sessions on the map).",
         [("", c.mapped)]),
        ("wardmap_mapping_unanchored_total", "counter",
         "Keyframes of sessions without T_map_odom: measured, not mapped.", [("", c.unanchored)]),
        ("wardmap_mapping_failures_total", "counter", "Keyframes perception skipped, by error type.",
         [(f'{{reason="{_label(r)}"}}', n) for r, n in sorted(c.failures.items())]),
        ("wardmap_mapping_landmarks", "gauge", "Landmarks the associator holds.", [("", c.landmarks)]),
        ("wardmap_mapping_restarts_total", "counter",
         "Unexpected errors the mapping stage recovered from (see the server log).", [("", c.restarts)]),
        ("wardmap_mapping_idle_sessions_closed_total", "counter",
         "Sessions whose last keyframe group was mapped because they went quiet (close_idle_s).",
         [("", c.closed_idle)]),
        ("wardmap_mapping_floating_left_out_total", "counter",
         "Instances perception left out for floating above the floor (perception.floor_gap_m).",
         [("", c.floating)]),
        ("wardmap_mapping_wall_pieces_left_out_total", "counter",
         "Instances perception left out for lying on a surface taller than any object of their class "
         "(perception.max_top_m).",
         [("", c.wall_pieces)]),
        ("wardmap_mapping_floor_pieces_left_out_total", "counter",
         "Instances perception left out for lying flat on the floor, lower than any object of their "
         "class (perception.min_top_m).",
         [("", c.floor_pieces)]),
        ("wardmap_mapping_beyond_range_total", "counter",
         "Stored measurements association left out for lying beyond association.max_range_m.",
         [("", c.beyond_range)]),
        ("wardmap_mapping_instances_skipped_total", "counter",
         "Instances perception found but could not measure (stored keyframes), by kind.",
         [(f'{{kind="{k}"}}', c.skipped.get(k, 0)) for k in SKIP_KINDS]),
    ]
    out = []
    for name, kind, help_text, samples in rows:
        out.append(f"# HELP {name} {help_text}")
        out.append(f"# TYPE {name} {kind}")
        out.extend(f"{name}{labels} {value}" for labels, value in samples)
    return "\n".join(out) + "\n"


def _prometheus(counters: IngestCounters | None, rejections: dict[str, int], robots: int) -> str:
    """Prometheus text exposition format 0.0.4. Rejections are the store's persistent counts."""
    c = counters or IngestCounters(0, 0, 0, 0, 0, 0)
    out = []

    def metric(name: str, kind: str, help_text: str, samples: list[tuple[str, int]]) -> None:
        out.append(f"# HELP {name} {help_text}")
        out.append(f"# TYPE {name} {kind}")
        out.extend(f"{name}{labels} {value}" for labels, value in samples)

    metric("wardmap_keyframes_received_total", "counter",
           "Keyframe samples taken from zenoh by this server process.", [("", c.received)])
    metric("wardmap_keyframes_stored_total", "counter",
           "Keyframes newly stored by this server process.", [("", c.stored)])
    metric("wardmap_keyframes_duplicates_total", "counter",
           "Keyframes received again after they were stored (acked duplicate).", [("", c.duplicates)])
    metric("wardmap_rejections_total", "counter",
           "Rejected samples by reason, persistent in the store.",
           [(f'{{reason="{_label(reason)}"}}', n) for reason, n in sorted(rejections.items())])
    metric("wardmap_ingest_queue_depth", "gauge",
           "Samples taken from the zenoh channel and not yet processed.", [("", c.queue_depth)])
    metric("wardmap_ack_failures_total", "counter", "Acks that could not be published.",
           [("", c.ack_failures)])
    metric("wardmap_robots", "gauge", "Robots with at least one stored keyframe.", [("", robots)])
    return "\n".join(out) + "\n"

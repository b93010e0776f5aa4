"""The map server's REST API (FastAPI).

:func:`create_app` builds the app; its lifespan opens the keyframe store (and starts an
optional :class:`~wardmap.server.ingest.Ingest`) and closes them on shutdown, so importing
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
from typing import Annotated, Any, Literal

from fastapi import Depends, FastAPI, HTTPException, Query, Request
from fastapi.responses import JSONResponse, PlainTextResponse
from pydantic import BaseModel

from wardmap.server.ingest import Ingest, IngestCounters
from wardmap.server.store import MAX_PAGE, KeyframeStore, StoreError, open_store
from wardmap.shared.errors import WardmapError
from wardmap.shared.se3 import transform_to_tum

log = logging.getLogger(__name__)

__all__ = ["create_app"]

IngestFactory = Callable[[KeyframeStore], Ingest]


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


StoreDep = Annotated[KeyframeStore, Depends(get_store)]
IngestDep = Annotated[Ingest | None, Depends(get_ingest)]


# --------------------------------------------------------------------------- app


def create_app(store_url: str, *, ingest_factory: IngestFactory | None = None) -> FastAPI:
    """The FastAPI app serving the keyframe store at ``store_url``.

    Args:
        store_url: ``sqlite:///PATH`` (see :func:`~wardmap.server.store.open_store`); opened
            in the lifespan, not here.
        ingest_factory: builds the :class:`Ingest` from the open store; it is started after
            the store opened and stopped before the store closes. None: API only.
    """

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        store = open_store(store_url)
        ingest: Ingest | None = None
        try:
            if ingest_factory is not None:
                ingest = ingest_factory(store)
                ingest.start()
            app.state.store = store
            app.state.ingest = ingest
            yield
        finally:
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

    @app.get("/metrics", response_class=PlainTextResponse)
    def metrics(store: StoreDep, ingest: IngestDep) -> str:
        counters = ingest.counters() if ingest is not None else None
        return _prometheus(counters, store.rejections(), store.stats().robots)

    return app


async def _wardmap_error(request: Request, exc: Exception) -> JSONResponse:
    """The one place a WardmapError becomes an HTTP status: bad store arguments are 400."""
    status = 400 if isinstance(exc, StoreError) else 500
    if status == 500:
        log.error("%s %s failed: %s", request.method, request.url.path, exc)
    return JSONResponse({"detail": str(exc)}, status_code=status)


def _label(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


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

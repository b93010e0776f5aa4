"""What the routes get from the server, as FastAPI dependencies.

The composition root (:class:`~wardmap.server.app.MapServer`) builds and starts the server's
parts; the app's lifespan (:func:`~wardmap.server.api.main.create_app`) asks it for the
running :class:`Services` and keeps them on ``app.state`` until shutdown. A route declares
only the parts it uses, e.g. ``objects: ObjectMapDep`` (``Annotated[ObjectMap,
Depends(get_objectmap)]``), so a test can see from its signature what it touches.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Annotated, Protocol

from fastapi import Depends, Request
from prometheus_client import CollectorRegistry

from wardmap.server.api.readiness import ReadinessLog
from wardmap.server.ingest import Ingest
from wardmap.server.mapping import MapPipeline
from wardmap.server.mapping.role import MappingRole
from wardmap.server.mapping.workers import PerceptionWorkers
from wardmap.server.objectmap import ObjectMap
from wardmap.server.store import MapStore
from wardmap.server.telemetry import ServerTelemetry

__all__ = [
    "IngestDep",
    "MetricsDep",
    "ObjectMapDep",
    "PipelineDep",
    "ServerLifecycle",
    "Services",
    "StoreDep",
]


@dataclass(frozen=True)
class Services:
    """The running parts the REST API reads; built and owned by the composition root.

    Attributes:
        store: the open keyframe store.
        objects: the object map on it.
        ingest: the keyframe ingest, or None when the server has no Zenoh (API only).
        pipeline: a mapping stage that always runs in this process (tests); see ``mapping``.
        mapping: the writer-lease role that runs the mapping stage here only while this server
            holds the store's writer lease (what the server builds; ``server/mapping/role.py``),
            or None. Neither: keyframes are stored but not mapped.
        readiness: logs why ``/readyz`` says not ready, once per change.
        router_connected: whether the server's Zenoh session has a router now (thread safe,
            fast), or None when the server has no Zenoh.
        telemetry: the histograms and per-robot series the parts record into.
        workers: this server's perception worker processes (``server/mapping/workers.py``), or
            None when it runs none.
    """

    store: MapStore
    objects: ObjectMap
    ingest: Ingest | None = None
    pipeline: MapPipeline | None = None
    mapping: MappingRole | None = None
    readiness: ReadinessLog = field(default_factory=ReadinessLog)
    router_connected: Callable[[], bool] | None = None
    telemetry: ServerTelemetry = field(default_factory=ServerTelemetry)
    workers: PerceptionWorkers | None = None

    def running_pipeline(self) -> MapPipeline | None:
        """The mapping stage running in this process now: the role's while this server holds the
        writer lease (None while a standby), else :attr:`pipeline`."""
        return self.mapping.pipeline if self.mapping is not None else self.pipeline


class ServerLifecycle(Protocol):
    """What the app's lifespan starts and stops (the composition root, ``server/app.py``)."""

    def start(self) -> Services:
        """Open and start every part; on failure, stop what started and raise."""
        ...

    def stop(self) -> None:
        """Stop every part in reverse order (idempotent)."""
        ...


# The getters are ``async`` although they only read attributes: FastAPI runs a plain ``def``
# dependency in its worker thread pool, and each such hop costs about a millisecond a request.
async def get_services(request: Request) -> Services:
    services: Services | None = getattr(request.app.state, "services", None)
    if services is None:  # only outside the lifespan: a route called before start-up
        raise RuntimeError("the map server is not started")
    return services


ServicesDep = Annotated[Services, Depends(get_services)]


async def get_store(services: ServicesDep) -> MapStore:
    return services.store


async def get_objectmap(services: ServicesDep) -> ObjectMap:
    return services.objects


async def get_ingest(services: ServicesDep) -> Ingest | None:
    return services.ingest


async def get_pipeline(services: ServicesDep) -> MapPipeline | None:
    return services.running_pipeline()


async def get_metrics(request: Request) -> CollectorRegistry:
    registry: CollectorRegistry = request.app.state.metrics
    return registry


StoreDep = Annotated[MapStore, Depends(get_store)]
ObjectMapDep = Annotated[ObjectMap, Depends(get_objectmap)]
IngestDep = Annotated[Ingest | None, Depends(get_ingest)]
PipelineDep = Annotated[MapPipeline | None, Depends(get_pipeline)]
MetricsDep = Annotated[CollectorRegistry, Depends(get_metrics)]
"""The app's own Prometheus registry (never the global one), filled at scrape time."""

"""The FastAPI app: routes, the one error handler, and a lifespan that starts the server.

:func:`create_app` includes one router per resource (``routes/``) and opens nothing. Its
lifespan calls the composition root's ``start()`` (``server/app.py``: it opens the store,
the Zenoh session and starts ingest, map service and mapping), keeps the running
:class:`~wardmap.server.api.deps.Services` on ``app.state`` for the dependencies
(``deps.py``) together with the app's own Prometheus registry (the parts' counters and the
process's :class:`~wardmap.server.telemetry.ServerTelemetry`; each request's time per route
is observed by ``api/timing.py``), and calls ``stop()`` at shutdown.
:class:`~wardmap.shared.errors.WardmapError` maps to HTTP in one place (:func:`_wardmap_error`).

Two routers: :data:`public_router` (the probes ``/healthz`` and ``/readyz``; only what carries
no map data belongs here) and :data:`data_router`, whose dependency
(:func:`~wardmap.server.api.auth.require_token`) asks every route on it for a bearer token:
``read`` for GET, ``admin`` for anything that changes state. New routes go on the data router.
The lifespan sets the auth policy (``app.state.auth``). No CORS headers are sent: browsers
refuse cross-origin reads of the API.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles

from wardmap.server.api.auth import AUTH_RESPONSES, ApiAuth, require_token
from wardmap.server.api.deps import ServerLifecycle, Services
from wardmap.server.api.prometheus import ServerCollector, metrics_registry
from wardmap.server.api.routes import (
    categories,
    docs,
    events,
    health,
    keyframes,
    metrics,
    objects,
    robots,
    web,
)
from wardmap.server.api.timing import RouteTiming
from wardmap.server.store import StoreDamagedError, StoreError, StoreUnavailableError
from wardmap.shared.errors import WardmapError

log = logging.getLogger(__name__)

__all__ = ["create_app", "data_router", "public_router"]

public_router = APIRouter()
"""Routes anyone may call: probes, and pages or assets that carry no map data."""
public_router.include_router(health.router)

data_router = APIRouter(dependencies=[Depends(require_token)], responses=AUTH_RESPONSES)
"""Every route that reads or changes the map: each needs a token (``api/auth.py``)."""
for _module in (robots, keyframes, objects, categories, metrics, events):
    data_router.include_router(_module.router)


def create_app(server: ServerLifecycle, *, require_tokens: bool = True) -> FastAPI:
    """The FastAPI app over ``server``, which its lifespan starts and stops.

    Args:
        server: the composition root (:class:`~wardmap.server.app.MapServer`); nothing is
            opened here, only in the lifespan.
        require_tokens: data routes need a bearer token checked against the store; False
            only for insecure-loopback mode (``run_server`` checks the address).
    """

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        services = server.start()
        try:
            app.state.auth = ApiAuth(services.store if require_tokens else None)
            if require_tokens and not _has_tokens(services):
                log.warning("no REST API tokens exist: every data route answers 401 until one is "
                            "created with `wardmap token create --scope read --db URL`")
            app.state.services = services
            app.state.metrics = metrics_registry(
                ServerCollector(services.store, services.objects, services.ingest, services.pipeline,
                                services.mapping, services.workers)
            )
            services.telemetry.register(app.state.metrics)
            yield
        finally:
            app.state.services = None
            app.state.auth = None
            server.stop()

    # /docs and /redoc come from the packaged copies (routes/docs.py), not FastAPI's CDN pages.
    app = FastAPI(title="wardmap map server", version="1", lifespan=lifespan, docs_url=None, redoc_url=None)
    app.add_exception_handler(WardmapError, _wardmap_error)
    app.add_middleware(RouteTiming)
    app.include_router(public_router)
    app.include_router(data_router)
    app.include_router(web.router)  # the page and API docs: public, no data
    app.include_router(docs.router)
    app.mount("/static", StaticFiles(packages=[("wardmap.server.api", "static")]), name="static")
    return app


def _has_tokens(services: Services) -> bool:
    """Whether any token exists (True when the store cannot say: it logged why)."""
    try:
        return any(t.revoked_s is None for t in services.store.tokens())
    except StoreError:
        return True


async def _wardmap_error(request: Request, exc: Exception) -> JSONResponse:
    """The one place a WardmapError becomes an HTTP status: a store that cannot serve now
    (damaged, locked, full: the store logged how to repair) is 503, bad store arguments 400."""
    if isinstance(exc, StoreDamagedError | StoreUnavailableError):
        status = 503
    elif isinstance(exc, StoreError):
        status = 400
    else:
        status = 500
    if status == 500:
        log.error("%s %s failed: %s", request.method, request.url.path, exc)
    return JSONResponse({"detail": str(exc)}, status_code=status)

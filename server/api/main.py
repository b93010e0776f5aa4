"""The FastAPI app: routes, the one error handler, and a lifespan that starts the server.

:func:`create_app` includes one router per resource (``routes/``) and opens nothing. Its
lifespan calls the composition root's ``start()`` (``server/app.py``: it opens the store,
the Zenoh session and starts ingest, map service and mapping), keeps the running
:class:`~wardmap.server.api.deps.Services` on ``app.state`` for the dependencies
(``deps.py``) together with the app's own Prometheus registry, and calls ``stop()`` at
shutdown. :class:`~wardmap.shared.errors.WardmapError` maps to HTTP in one place
(:func:`_wardmap_error`).
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import APIRouter, FastAPI, Request
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles

from wardmap.server.api.deps import ServerLifecycle
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
from wardmap.server.store import StoreDamagedError, StoreError, StoreUnavailableError
from wardmap.shared.errors import WardmapError

log = logging.getLogger(__name__)

__all__ = ["api_router", "create_app"]

api_router = APIRouter()
for _module in (health, robots, keyframes, objects, categories, metrics, events):
    api_router.include_router(_module.router)


def create_app(server: ServerLifecycle) -> FastAPI:
    """The FastAPI app over ``server``, which its lifespan starts and stops.

    Args:
        server: the composition root (:class:`~wardmap.server.app.MapServer`); nothing is
            opened here, only in the lifespan.
    """

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        services = server.start()
        try:
            app.state.services = services
            app.state.metrics = metrics_registry(
                ServerCollector(services.store, services.objects, services.ingest, services.pipeline)
            )
            yield
        finally:
            app.state.services = None
            server.stop()

    # /docs and /redoc come from the packaged copies (routes/docs.py), not FastAPI's CDN pages.
    app = FastAPI(title="wardmap map server", version="1", lifespan=lifespan, docs_url=None, redoc_url=None)
    app.add_exception_handler(WardmapError, _wardmap_error)
    app.include_router(api_router)
    app.include_router(web.router)  # the page and API docs: public, no data
    app.include_router(docs.router)
    app.mount("/static", StaticFiles(packages=[("wardmap.server.api", "static")]), name="static")
    return app


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

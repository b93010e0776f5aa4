"""Per-route request time of the REST API, as ASGI middleware (``wardmap_http_request_seconds``).

The label is the route's template (``/v1/objects/{object_id}``), never the raw path, so the
number of series stays bounded whatever clients ask for: a path no route matched is
``unmatched``, a mounted app (``/static``) its mount path. The histogram lives on the running
server's :class:`~wardmap.server.telemetry.ServerTelemetry` (``app.state.services``); requests
outside the lifespan are not timed.
"""

from __future__ import annotations

import time
from typing import Any

from starlette.types import ASGIApp, Receive, Scope, Send

__all__ = ["RouteTiming", "route_label"]


def route_label(scope: Scope) -> str:
    """The route template Starlette matched for ``scope`` (after the app ran), else ``unmatched``."""
    route: Any = scope.get("route")
    path = getattr(route, "path", None)
    if isinstance(path, str):
        return path
    root = scope.get("root_path", "")
    return root if isinstance(root, str) and root else "unmatched"


class RouteTiming:
    """ASGI middleware: observes each HTTP request's time (to the end of its response body)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        try:
            await self.app(scope, receive, send)
        finally:
            services = getattr(getattr(scope.get("app"), "state", None), "services", None)
            if services is not None:
                histogram = services.telemetry.rest_seconds
                histogram.labels(method=scope["method"], route=route_label(scope)).observe(
                    time.perf_counter() - started)

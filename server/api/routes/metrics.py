"""``GET /metrics``: the server's counters in the Prometheus text format (``api/prometheus.py``)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import PlainTextResponse, Response

from wardmap.server.api.deps import MetricsDep
from wardmap.server.api.prometheus import CONTENT_TYPE, exposition

router = APIRouter()


@router.get("/metrics", response_class=PlainTextResponse)
def metrics(registry: MetricsDep) -> Response:
    return Response(exposition(registry), media_type=CONTENT_TYPE)

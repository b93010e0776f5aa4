"""``GET /healthz``: the liveness probe."""

from __future__ import annotations

from fastapi import APIRouter

from wardmap.server.api.schemas import Health

router = APIRouter()


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    return Health(status="ok")

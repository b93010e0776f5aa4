"""``GET /healthz``: the liveness probe (the process answers); ``GET /readyz``: the readiness
probe (503 while no router is connected, keyframes cannot be stored, or the mapping stage is
stopped or too far behind; the body names a fixed category, the server logs the full reason:
``server/api/readiness.py``; with a mapping stage it also says whether this server is the
writer or a standby, and the writer's name)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from wardmap.server.api.deps import ServicesDep
from wardmap.server.api.readiness import check, public_reason
from wardmap.server.api.schemas import Health, Readiness

router = APIRouter()


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    return Health(status="ok")


@router.get("/readyz", response_model=Readiness, responses={503: {"model": Readiness}})
def readyz(services: ServicesDep) -> JSONResponse:
    """Ready by :func:`~wardmap.server.api.readiness.check`. A plain ``def``: the probe may wait
    about 1 s on a locked database, off the event loop."""
    ok, why = check(services)
    services.readiness.note(ok, why)
    body: dict[str, str | None] = {"status": "ok" if ok else public_reason(why)}
    if services.mapping is not None:
        lease = services.mapping.state()
        body.update(mapping="writer" if lease.held else "standby", writer=lease.holder)
    return JSONResponse(body, status_code=200 if ok else 503)

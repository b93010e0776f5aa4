"""``GET /healthz``: the liveness probe; ``GET /readyz``: the readiness probe (503 while
keyframes cannot be stored).

Both are public, so the 503 body names only a fixed category (:func:`public_reason`), never
the store's own text (it can hold the database file's path); the server logs the full reason,
once each time it changes."""

from __future__ import annotations

import logging
import threading

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from wardmap.server.api.deps import ServicesDep
from wardmap.server.api.schemas import Health, Readiness

log = logging.getLogger(__name__)

router = APIRouter()

# (words in the full reason, public reason); the first match wins.
_CATEGORIES = (
    (("ingest is not running",), "ingest is not running"),
    (("damaged", "malformed", "corrupt"), "keyframe store damaged"),
    (("no space", "full"), "keyframe store full"),
    (("locked", "busy"), "keyframe store locked"),
    (("closed",), "keyframe store closed"),
)


def public_reason(why: str) -> str:
    """The short, fixed reason ``/readyz`` returns for the full reason ``why``: one of
    ``ingest is not running``, ``keyframe store damaged|full|locked|closed``, else
    ``keyframe store cannot write``. Never contains text of ``why`` itself."""
    low = why.lower()
    for words, reason in _CATEGORIES:
        if any(w in low for w in words):
            return reason
    return "keyframe store cannot write"


class _ReasonLog:
    """Logs the full not-ready reason once each time it changes (probes poll every few seconds)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last: str | None = None  # the last reason logged; None while ready

    def note(self, ok: bool, why: str) -> None:
        with self._lock:
            now = None if ok else why
            if now == self._last:
                return
            self._last = now
        if ok:
            log.info("ready again: keyframes can be stored")
        else:
            log.warning("not ready (/readyz 503): %s", why)


_reasons = _ReasonLog()


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    return Health(status="ok")


@router.get("/readyz", response_model=Readiness, responses={503: {"model": Readiness}})
def readyz(services: ServicesDep) -> JSONResponse:
    """Ready when keyframes can be stored now: the ingest runs and the store can write
    (``Ingest.ready``; without ingest, ``KeyframeStore.writable``). A plain ``def``: the
    probe may wait about 1 s on a locked database, off the event loop."""
    if services.ingest is not None:
        ok, why = services.ingest.ready()
    else:
        ok, why = services.store.writable()
    _reasons.note(ok, why)
    return JSONResponse({"status": "ok" if ok else public_reason(why)}, status_code=200 if ok else 503)

"""When the server is ready, what the public readiness probe may say, and the log of why not.

:func:`check` is ``/readyz``'s rule: ready when the Zenoh session has a router, keyframes can
be stored (the ingest runs and the store can write), and the mapping stage runs with no more
than ``[pipeline] ready_max_backlog`` stored keyframes waiting for it; each part the server
runs without (no Zenoh, no mapping stage) is left out. A standby (another server holds the
writer lease and maps, ``server/mapping/role.py``) is ready: it stores keyframes and serves.

``/readyz`` is public (orchestrators call it without credentials), so its 503 body names only
a fixed category (:func:`public_reason`), never the store's own text, which can hold the
database file's path. :class:`ReadinessLog` logs the full reason instead, once each time it
changes (probes poll every few seconds).
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from wardmap.server.api.deps import Services

log = logging.getLogger(__name__)

# (words in the full reason, public reason); the first match wins.
_CATEGORIES = (
    (("no zenoh router",), "zenoh router not connected"),
    (("mapping stage is not running",), "mapping stage not running"),
    (("mapping backlog",), "mapping backlog too long"),
    (("ingest is not running",), "ingest is not running"),
    (("damaged", "malformed", "corrupt"), "keyframe store damaged"),
    (("no space", "full"), "keyframe store full"),
    (("locked", "busy"), "keyframe store locked"),
    (("closed",), "keyframe store closed"),
)


def public_reason(why: str) -> str:
    """The short, fixed reason ``/readyz`` returns for the full reason ``why``: one of
    ``zenoh router not connected``, ``mapping stage not running``, ``mapping backlog too long``,
    ``ingest is not running``, ``keyframe store damaged|full|locked|closed``, else
    ``keyframe store cannot write``. Never contains text of ``why`` itself."""
    low = why.lower()
    for words, reason in _CATEGORIES:
        if any(w in low for w in words):
            return reason
    return "keyframe store cannot write"


def check(services: Services) -> tuple[bool, str]:
    """``(True, "ok")`` when ``services`` are ready (the module docstring's rule), else
    ``(False, why)`` with the first failing part's full reason (for the log; the probe answers
    :func:`public_reason` of it). Never raises; may wait about 1 s on a locked database."""
    if services.router_connected is not None and not services.router_connected():
        return False, "no zenoh router connected to the server's session"
    if services.ingest is not None:
        ok, why = services.ingest.ready()
    else:
        ok, why = services.store.writable()
    if not ok:
        return False, why
    if services.mapping is not None and not services.mapping.running():
        return False, "mapping stage is not running (its writer-lease thread stopped; see the server log)"
    pipeline = services.running_pipeline()  # None on a standby: it serves, another server maps
    if pipeline is not None:
        if not pipeline.running():
            return False, "mapping stage is not running (see the server log)"
        backlog, bound = pipeline.counters().backlog, pipeline.cfg.ready_max_backlog
        if backlog > bound:
            return False, f"mapping backlog of {backlog} keyframes over pipeline.ready_max_backlog={bound}"
    return True, "ok"


class ReadinessLog:
    """Logs the full not-ready reason once each time it changes, and once when ready again.
    Thread safe (the probe runs in FastAPI's worker threads)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last: str | None = None  # the last reason logged; None while ready

    def note(self, ok: bool, why: str) -> None:
        """Record one probe's outcome ``(ok, why)``; log it if it differs from the last."""
        now = None if ok else why
        with self._lock:
            if now == self._last:
                return
            self._last = now
        if now is None:
            log.info("ready again")
        else:
            log.warning("not ready (/readyz 503): %s", now)

"""What the public readiness probe may say, and the log of why it is not ready.

``/readyz`` is public (orchestrators call it without credentials), so its 503 body names only
a fixed category (:func:`public_reason`), never the store's own text, which can hold the
database file's path. :class:`ReadinessLog` logs the full reason instead, once each time it
changes (probes poll every few seconds).
"""

from __future__ import annotations

import logging
import threading

log = logging.getLogger(__name__)

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
            log.info("ready again: keyframes can be stored")
        else:
            log.warning("not ready (/readyz 503): %s", now)

"""Limits of the map server's HTTP server (uvicorn, h11): what one client can hold, and logs
that cannot flood.

- :class:`GuardedH11Protocol`: uvicorn's h11 protocol with a connection cap
  (:data:`MAX_CONNECTIONS`, fewer when the open-file limit is low: :func:`connection_cap`; a
  connection beyond it is closed at once, before anything is read, so idle sockets cannot use
  up the process's file descriptors) and a header timeout
  (:data:`HEADER_TIMEOUT_S`: a connection that has not sent a whole request head that long
  after it opened, or after its last response, is closed; uvicorn's own keep-alive timer is
  cancelled by any byte, so a client sending one byte at a time would hold it forever).
- :data:`LIMIT_CONCURRENCY`: passed to uvicorn, which answers 503 while that many connections
  or requests are open.
- :class:`ThrottledLog`: a logging filter that lets one record of each message through per
  :data:`LOG_INTERVAL_S` and says how many it held back, without a traceback; and
  :func:`throttled_exception_handler` for the event loop, whose accept loop reports every
  failed ``accept()`` (e.g. out of file descriptors) with a traceback.

:func:`~wardmap.server.app.run_server` installs all of them; nothing here runs at import.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from typing import Any, Final

from uvicorn.protocols.http.h11_impl import H11Protocol

__all__ = [
    "FD_RESERVE",
    "HEADER_TIMEOUT_S",
    "LIMIT_CONCURRENCY",
    "LOG_INTERVAL_S",
    "MAX_CONNECTIONS",
    "NOISY_MESSAGES",
    "GuardedH11Protocol",
    "ThrottledLog",
    "connection_cap",
    "guarded_protocol",
    "throttled_exception_handler",
]

log = logging.getLogger(__name__)

MAX_CONNECTIONS: Final = 512
"""Open HTTP connections at most; one more is closed as soon as it is accepted."""
LIMIT_CONCURRENCY: Final = 256
"""uvicorn's ``limit_concurrency``: 503 while this many connections or requests are open."""
HEADER_TIMEOUT_S: Final = 10.0
"""Seconds a connection may take to send a whole request head (from its opening or its last
response)."""
LOG_INTERVAL_S: Final = 10.0
"""One record per message per this many seconds from :class:`ThrottledLog`."""


FD_RESERVE: Final = 256
"""File descriptors kept for everything but HTTP connections (database, zenoh, models, logs)."""


def connection_cap() -> int:
    """How many HTTP connections this process can hold: :data:`MAX_CONNECTIONS`, raising the
    soft ``RLIMIT_NOFILE`` towards the hard one when needed, or fewer (at least 16) when the
    limits leave less than :data:`FD_RESERVE` descriptors besides. Out of descriptors, asyncio's
    accept loop fails and retries in a tight loop (hundreds of thousands of times a second)."""
    import resource

    want = MAX_CONNECTIONS + FD_RESERVE
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < want:
        new_soft = want if hard == resource.RLIM_INFINITY else min(want, hard)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (new_soft, hard))
            soft = new_soft
        except (ValueError, OSError) as exc:
            log.warning("cannot raise the open-file limit from %d: %s", soft, exc)
    if soft == resource.RLIM_INFINITY or soft >= want:
        return MAX_CONNECTIONS
    cap = max(16, soft - FD_RESERVE)
    log.warning("open-file limit %d: at most %d HTTP connections (raise it to %d for %d)",
                soft, cap, want, MAX_CONNECTIONS)
    return cap


class GuardedH11Protocol(H11Protocol):
    """uvicorn's h11 protocol with a connection cap and :data:`HEADER_TIMEOUT_S`; pass
    ``uvicorn.Config(http=guarded_protocol(connection_cap()))``."""

    max_connections: int = MAX_CONNECTIONS
    _header_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        if len(self.connections) > self.max_connections:
            self.logger.warning("HTTP connection refused: %d connections open (at most %d)",
                                len(self.connections) - 1, self.max_connections)
            transport.abort()
            return
        self._arm_header_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_header_timer()
        super().connection_lost(exc)

    def handle_events(self) -> None:
        cycle = self.cycle
        super().handle_events()
        if self.cycle is not cycle:  # a request head arrived: the app has it now
            self._cancel_header_timer()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm_header_timer()

    def _arm_header_timer(self) -> None:
        self._cancel_header_timer()
        self._header_timer = self.loop.call_later(HEADER_TIMEOUT_S, self._header_timeout)

    def _cancel_header_timer(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _header_timeout(self) -> None:
        self._header_timer = None
        if (self.cycle is None or self.cycle.response_complete) and not self.transport.is_closing():
            self.logger.debug("HTTP connection closed: no request head within %.0f s", HEADER_TIMEOUT_S)
            self.transport.close()


NOISY_MESSAGES: Final = frozenset({
    "Invalid HTTP request received.",
    "Exceeded concurrency limit.",
    "HTTP connection refused: %d connections open (at most %d)",
})
"""uvicorn's (and :class:`GuardedH11Protocol`'s) per-request warnings a hostile client can repeat."""


def guarded_protocol(max_connections: int) -> type[GuardedH11Protocol]:
    """:class:`GuardedH11Protocol` with its connection cap set to ``max_connections``."""
    return type("GuardedH11Protocol", (GuardedH11Protocol,), {"max_connections": max_connections})


class ThrottledLog(logging.Filter):
    """Let through the first record of each message (its unformatted ``msg``) per ``interval_s``;
    count the others and add the count to the next one let through. Tracebacks are dropped
    (a repeated failure's traceback says nothing new). Only messages in ``messages`` are
    throttled (None: all). Thread safe."""

    def __init__(self, interval_s: float = LOG_INTERVAL_S, clock: Any = time.monotonic,
                 messages: frozenset[str] | None = None) -> None:
        super().__init__()
        self._messages = messages
        self._interval_s = interval_s
        self._clock = clock
        self._lock = threading.Lock()
        self._next: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        key = str(record.msg)
        if self._messages is not None and key not in self._messages:
            return True
        now = self._clock()
        with self._lock:
            if now < self._next.get(key, float("-inf")):
                self._held[key] = self._held.get(key, 0) + 1
                return False
            self._next[key] = now + self._interval_s
            held = self._held.pop(key, 0)
        if record.exc_info and record.exc_info[1] is not None:
            record.msg = f"{record.msg}: {record.exc_info[1]!r}"
        record.exc_info = None
        record.exc_text = None
        if held:
            record.msg = f"{record.msg} ({held} more like it in the last {self._interval_s:.0f} s)"
        return True


def throttled_exception_handler(throttle: ThrottledLog) -> Any:
    """An event-loop exception handler that logs through ``throttle`` (no traceback), for
    ``loop.set_exception_handler``: asyncio reports each failed ``accept()`` this way."""

    def handler(loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        exc = context.get("exception")
        text = str(context.get("message", "event loop error"))
        if exc is not None:
            text += f": {exc!r}"
        message = "HTTP server: " + text.replace("%", "%%")
        record = log.makeRecord(log.name, logging.ERROR, __file__, 0, message, (), None)
        if log.isEnabledFor(logging.ERROR) and throttle.filter(record):
            log.handle(record)

    return handler

"""Stop a long-running command cleanly on SIGTERM/SIGINT (the edge agent, router, server)."""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType

__all__ = ["on_stop_signals"]

log = logging.getLogger(__name__)


@contextmanager
def on_stop_signals(stop: Callable[[], None], what: str) -> Iterator[None]:
    """Inside the block, SIGTERM and SIGINT call ``stop()`` (and log ``stopping <what>``).

    Only the main thread can install handlers; elsewhere the block runs without them. The
    previous handlers are restored on exit.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, _frame: FrameType | None) -> None:
        log.info("received %s, stopping %s", signal.Signals(signum).name, what)
        stop()

    previous = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)

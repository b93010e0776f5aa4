"""systemd's readiness protocol (``sd_notify``): one datagram to ``$NOTIFY_SOCKET``.

A unit with ``Type=notify`` is started (and units ordered after it start) only once the service
sends ``READY=1``; ``STOPPING=1`` tells systemd the service is shutting down; with ``WatchdogSec=`` systemd
restarts a service that sends no ``WATCHDOG=1`` for that long (:func:`start_watchdog`). The
protocol is
one ``AF_UNIX`` datagram of ``KEY=VALUE`` lines to the socket named by ``NOTIFY_SOCKET`` (a path,
or ``@name`` for the abstract namespace); see sd_notify(3). Outside systemd (no
``NOTIFY_SOCKET``) nothing is sent. The CLI calls it from the commands' ready callbacks.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
from collections.abc import Callable

log = logging.getLogger(__name__)

__all__ = ["notify", "start_watchdog", "watchdog_period_s"]


def notify(state: str) -> bool:
    """Send ``state`` (e.g. ``"READY=1"``) to systemd; True if sent, False without
    ``NOTIFY_SOCKET`` or when the socket refuses it (logged: systemd then times the unit out)."""
    address = os.environ.get("NOTIFY_SOCKET", "")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.connect(address)
            sock.sendall(state.encode())
    except OSError as exc:
        log.warning("cannot notify systemd (%s) of %s: %s", os.environ.get("NOTIFY_SOCKET"), state, exc)
        return False
    return True


def watchdog_period_s() -> float | None:
    """How often to send ``WATCHDOG=1`` (half of ``$WATCHDOG_USEC``, seconds), or None when
    systemd asks for no watchdog for this process (unset, or ``$WATCHDOG_PID`` is another's)."""
    usec, pid = os.environ.get("WATCHDOG_USEC", ""), os.environ.get("WATCHDOG_PID", "")
    if not usec.isdigit() or int(usec) <= 0 or (pid and pid != str(os.getpid())):
        return None
    return int(usec) / 2e6


def start_watchdog(alive: Callable[[], bool], stop: threading.Event | None = None) -> threading.Thread | None:
    """When systemd asks for a watchdog, send ``WATCHDOG=1`` every :func:`watchdog_period_s`
    while ``alive()`` says the service works (e.g. its HTTP loop answers), from a daemon thread
    that ends when ``stop`` is set (or with the process); once ``alive()`` fails, no ping is sent
    and systemd restarts the service after ``WatchdogSec``. None (no thread) without a watchdog."""
    period = watchdog_period_s()
    if period is None:
        return None
    stop = stop if stop is not None else threading.Event()

    def ping() -> None:
        while True:
            if alive():
                notify("WATCHDOG=1")
            else:
                log.warning("not alive: no watchdog ping to systemd")
            if stop.wait(period):
                return

    thread = threading.Thread(target=ping, name="sd-watchdog", daemon=True)
    thread.start()
    return thread

"""systemd's readiness protocol (``sd_notify``): one datagram to ``$NOTIFY_SOCKET``.

A unit with ``Type=notify`` is started (and units ordered after it start) only once the service
sends ``READY=1``; ``STOPPING=1`` tells systemd the service is shutting down. The protocol is
one ``AF_UNIX`` datagram of ``KEY=VALUE`` lines to the socket named by ``NOTIFY_SOCKET`` (a path,
or ``@name`` for the abstract namespace); see sd_notify(3). Outside systemd (no
``NOTIFY_SOCKET``) nothing is sent. The CLI calls it from the commands' ready callbacks.
"""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger(__name__)

__all__ = ["notify"]


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

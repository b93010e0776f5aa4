"""The map server's Zenoh session: the one helper that opens it.

A server process holds **one** client session (docs/ARCHITECTURE.md, "Processes"): the
composition root (:class:`~wardmap.server.app.MapServer`) opens it with
:func:`open_session` and hands it to the :class:`~wardmap.server.ingest.Ingest` and the
:class:`~wardmap.server.mapserve.MapServe`, which declare their subscriber, queryable and
publishers on it and undeclare them when they stop. The root closes the session after both
stopped: undeclare first, then close, and close every session, or the process hangs at exit.

The config comes from :func:`~wardmap.shared.zenoh_config.client_config` (pure, in
``shared/``); only this module (and the router, ``server/router.py``) turns a config into a
session. zenoh is imported when a session is opened, never at import.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

from wardmap.shared.errors import WardmapError
from wardmap.shared.zenoh_config import client_config

__all__ = ["ZenohSessionError", "first_line", "has_router", "open_session"]


class ZenohSessionError(WardmapError):
    """The server's Zenoh session cannot be opened (e.g. no router answers at the endpoints)."""


def first_line(exc: BaseException) -> str:
    """Zenoh error text on one line, without its Rust source location (`` at /path/file.rs:NN.``).

    Parse errors of config files span several lines (``--> 2:1``, a code excerpt,
    ``= expected ...``); only the location and the explanation are kept.
    """
    lines = [ln.strip() for ln in str(exc).strip().splitlines() if ln.strip()]
    if not lines:
        return type(exc).__name__
    picked = [ln for ln in lines if ln.startswith(("-->", "= "))] if len(lines) > 1 else lines
    text = " ".join(picked or lines[:1])
    cut = text.rfind(" at /")
    return text[:cut].rstrip() if cut > 0 else text


def open_session(connect: Sequence[str]) -> Any:
    """A ``zenoh.Session`` in client mode connected to the routers at ``connect``.

    Shared memory and multicast scouting are off (``client_config``). The caller owns the
    session: it closes it (``session.close()`` or a ``with`` block) after undeclaring what it
    declared on it.

    Raises:
        ConfigError: a bad endpoint (checked before zenoh is touched).
        ZenohSessionError: zenoh cannot open the session (e.g. no router at ``connect``).
    """
    config = client_config(connect)
    import zenoh

    try:
        return zenoh.open(zenoh.Config.from_json5(json.dumps(config)))
    except zenoh.ZError as exc:
        raise ZenohSessionError(f"cannot connect to {', '.join(connect)}: {first_line(exc)}") from exc


def has_router(session: Any) -> bool:
    """Whether ``session`` is connected to at least one router now (``session.info.routers_zid()``).

    A client session loses its router as soon as the router's TCP link closes and finds it again
    when the router returns (zenoh reconnects by itself); ``bench/health.py`` measures both
    through ``/readyz`` (BENCHMARKS.md). False once the session is closed.
    """
    import zenoh

    try:
        return any(True for _ in session.info.routers_zid())
    except zenoh.ZError:
        return False

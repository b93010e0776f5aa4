"""The map server's Zenoh session: the one helper that opens it.

A server process holds **one** client session (docs/ARCHITECTURE.md, "Processes"): the
composition root (:class:`~wardmap.server.app.MapServer`) opens it with
:func:`open_session` and hands it to the :class:`~wardmap.server.ingest.Ingest` and the
:class:`~wardmap.server.mapserve.MapServe`, which declare their subscriber, queryable and
publishers on it and undeclare them when they stop. The root closes the session after both
stopped: undeclare first, then close, and close every session, or the process hangs at exit.

The config comes from :func:`~wardmap.shared.zenoh_config.client_config` (pure, in
``shared/``) through :func:`~wardmap.shared.zenoh_load.load_zenoh_config`; only this module
(and the router, ``server/router.py``) turns a config into a session on the server side.
zenoh is imported when a session is opened, never at import.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from wardmap.shared.errors import WardmapError
from wardmap.shared.zenoh_config import ZenohOptions, client_config
from wardmap.shared.zenoh_load import connect_hint, load_zenoh_config
from wardmap.shared.zenoh_load import zenoh_error_line as first_line

__all__ = ["ZenohSessionError", "check_session_config", "first_line", "has_router", "open_session"]


class ZenohSessionError(WardmapError):
    """The server's Zenoh session cannot be opened (e.g. no router answers at the endpoints)."""


def check_session_config(connect: Sequence[str], options: ZenohOptions | None = None) -> None:
    """Raise what :func:`open_session` would raise for its config, without connecting.

    Raises:
        ConfigError: a bad endpoint, config file or TLS file.
    """
    load_zenoh_config(client_config(connect, options=options), options)


def open_session(connect: Sequence[str], options: ZenohOptions | None = None) -> Any:
    """A ``zenoh.Session`` in client mode connected to the routers at ``connect``.

    Shared memory and multicast scouting are off (``client_config``). ``options`` adds the
    TLS files (the site CA; this server's certificate and key for mutual TLS) and a zenoh
    config file laid under wardmap's values (``shared/zenoh_load.py``). The caller owns the
    session: it closes it (``session.close()`` or a ``with`` block) after undeclaring what it
    declared on it.

    Raises:
        ConfigError: a bad endpoint, config file or TLS file (checked before connecting).
        ZenohSessionError: zenoh cannot open the session (e.g. no router at ``connect``).
    """
    config = load_zenoh_config(client_config(connect, options=options), options)
    import zenoh

    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise ZenohSessionError(
            f"cannot connect to {', '.join(connect)}: {first_line(exc)}{connect_hint(connect)}"
        ) from exc


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

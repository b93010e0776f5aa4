"""The wardmap Zenoh router: one zenoh session in router mode, nothing else.

Robots and map servers connect to it by explicit ``tcp/``, ``tls/`` or ``quic/HOST:PORT``
endpoints (multicast scouting and shared memory are off by default, see :func:`router_config`).
With TLS files it listens with mutual TLS, and a site config file (``--zenoh-config``, e.g.
the ``acl.json5`` of ``wardmap certs``) adds access control (docs/security.md). This module
is the only place the router opens a zenoh session; the CLI (``wardmap router``) is a thin
wrapper around :func:`run_router`.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence

from wardmap.server.zenoh_session import ZenohSessionError, first_line, has_router, open_session
from wardmap.shared.errors import WardmapError
from wardmap.shared.signals import on_stop_signals
from wardmap.shared.zenoh_config import ZenohOptions, router_config
from wardmap.shared.zenoh_load import load_zenoh_config, zenoh_error_line

log = logging.getLogger(__name__)

__all__ = ["RouterError", "check_router", "run_router"]


class RouterError(WardmapError):
    """The Zenoh router cannot start (e.g. a listen port is already in use)."""


def run_router(
    listen: Sequence[str],
    *,
    options: ZenohOptions | None = None,
    stop: threading.Event | None = None,
    on_ready: Callable[[list[str]], None] | None = None,
    connect: Sequence[str] = (),
) -> None:
    """Run a Zenoh router listening on ``listen`` until ``stop`` is set or SIGTERM/SIGINT.

    Args:
        listen: endpoints ``tcp/``, ``tls/`` or ``quic/HOST:PORT`` to listen on (at least one).
        connect: other routers' endpoints to join into one mesh (retried until they answer).
        options: TLS files (the router's certificate and key; with a CA, mutual TLS) and an
            optional zenoh JSON5/JSON/YAML config file laid under wardmap's values.
        stop: event that ends the router when set; signals set it too when this runs in
            the main thread.
        on_ready: called once with the listen endpoints after the router is open.

    Raises:
        ConfigError: bad endpoint or config file, a ``tls/`` or ``quic/`` endpoint without certificate and
            key, a missing TLS file.
        RouterError: zenoh cannot open the router (e.g. address already in use).
    """
    import zenoh

    stop = stop if stop is not None else threading.Event()
    conf = load_zenoh_config(router_config(listen, options=options, connect=connect), options)
    endpoints = list(listen)
    with on_stop_signals(stop.set, "the router"):
        try:
            session = zenoh.open(conf)
        except zenoh.ZError as exc:
            msg = zenoh_error_line(exc)
            if "address already in use" in msg.lower():
                raise RouterError(f"cannot listen on {', '.join(endpoints)}: address already in use") from exc
            raise RouterError(f"cannot start zenoh router on {', '.join(endpoints)}: {msg}") from exc
        with session:
            log.info("zenoh router %s listening on %s%s", session.info.zid(), ", ".join(endpoints),
                     f", joining {', '.join(connect)}" if connect else "")
            if on_ready is not None:
                on_ready(endpoints)
            stop.wait()
            log.info("closing zenoh router")
    log.info("zenoh router closed")


def check_router(endpoint: str, options: ZenohOptions | None = None) -> str:
    """The health check of a router (``wardmap router --check``): open a client session to
    ``endpoint`` (with ``options``' TLS files for a ``tls/`` endpoint) and see a router on it;
    returns the router's id.

    Raises:
        ConfigError: a bad endpoint or TLS file.
        RouterError: nothing answers at ``endpoint``, or what answers is no router.
    """
    try:
        session = open_session([endpoint], options)
    except ZenohSessionError as exc:
        why = first_line(exc.__cause__) if exc.__cause__ is not None else str(exc)
        raise RouterError(f"no zenoh router answers at {endpoint}: {why}") from exc
    with session:
        if not has_router(session):
            raise RouterError(f"no zenoh router at {endpoint} (a peer or client answered)")
        return str(next(iter(session.info.routers_zid())))

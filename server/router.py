"""The wardmap Zenoh router: one zenoh session in router mode, nothing else.

Robots and map servers connect to it by explicit ``tcp/HOST:PORT`` endpoints (multicast
scouting and shared memory are off by default, see :func:`router_config`). This module
is the only place the router touches zenoh; the CLI (``wardmap router``) is a thin
wrapper around :func:`run_router`.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from wardmap.server.zenoh_session import ZenohSessionError, first_line, has_router, open_session
from wardmap.shared.errors import ConfigError, WardmapError
from wardmap.shared.signals import on_stop_signals
from wardmap.shared.zenoh_config import config_leaves, router_config

log = logging.getLogger(__name__)

__all__ = ["RouterError", "check_router", "run_router"]


class RouterError(WardmapError):
    """The Zenoh router cannot start (e.g. a listen port is already in use)."""


def _load_config(listen: Sequence[str], config_file: Path | None) -> Any:
    """Build the ``zenoh.Config``: the user's file (if any), then wardmap's values on top.

    ``mode``, ``listen/endpoints`` and wardmap's defaults (shared memory off, multicast
    scouting off) win over the file; each value of the file that they replace is logged
    as a warning, so nothing is overridden silently.
    """
    import zenoh

    ours = router_config(listen)
    if config_file is None:
        return zenoh.Config.from_json5(json.dumps(ours))
    path = Path(config_file)
    if not path.is_file():
        raise ConfigError(f"zenoh config file not found: {path}")
    try:
        conf = zenoh.Config.from_file(str(path))
    except zenoh.ZError as exc:
        raise ConfigError(f"bad zenoh config file {path}: {first_line(exc)}") from exc
    for key, value in config_leaves(ours):
        before = conf.get_json(key)
        if before is not None and before != value and key != "listen/endpoints":
            log.warning(
                "%s sets %s=%s; wardmap router uses %s", path, key, json.dumps(before), json.dumps(value)
            )
        conf.insert_json5(key, json.dumps(value))
    return conf


def run_router(
    listen: Sequence[str],
    *,
    config_file: Path | None = None,
    stop: threading.Event | None = None,
    on_ready: Callable[[list[str]], None] | None = None,
) -> None:
    """Run a Zenoh router listening on ``listen`` until ``stop`` is set or SIGTERM/SIGINT.

    Args:
        listen: endpoints ``tcp/HOST:PORT`` to listen on (at least one).
        config_file: optional zenoh JSON5/JSON/YAML config laid under wardmap's values.
        stop: event that ends the router when set; signals set it too when this runs in
            the main thread.
        on_ready: called once with the listen endpoints after the router is open.

    Raises:
        ConfigError: bad endpoint or config file.
        RouterError: zenoh cannot open the router (e.g. address already in use).
    """
    import zenoh

    stop = stop if stop is not None else threading.Event()
    conf = _load_config(listen, config_file)
    endpoints = list(listen)
    with on_stop_signals(stop.set, "the router"):
        try:
            session = zenoh.open(conf)
        except zenoh.ZError as exc:
            msg = first_line(exc)
            if "address already in use" in msg.lower():
                raise RouterError(f"cannot listen on {', '.join(endpoints)}: address already in use") from exc
            raise RouterError(f"cannot start zenoh router on {', '.join(endpoints)}: {msg}") from exc
        with session:
            log.info("zenoh router %s listening on %s", session.info.zid(), ", ".join(endpoints))
            if on_ready is not None:
                on_ready(endpoints)
            stop.wait()
            log.info("closing zenoh router")
    log.info("zenoh router closed")


def check_router(endpoint: str) -> str:
    """The health check of a router (``wardmap router --check``): open a client session to
    ``endpoint`` and see a router on it; returns the router's id.

    Raises:
        ConfigError: a bad endpoint.
        RouterError: nothing answers at ``endpoint``, or what answers is no router.
    """
    try:
        session = open_session([endpoint])
    except ZenohSessionError as exc:
        why = first_line(exc.__cause__) if exc.__cause__ is not None else str(exc)
        raise RouterError(f"no zenoh router answers at {endpoint}: {why}") from exc
    with session:
        if not has_router(session):
            raise RouterError(f"no zenoh router at {endpoint} (a peer or client answered)")
        return str(next(iter(session.info.routers_zid())))

"""Turn a wardmap config dict (``shared/zenoh_config.py``) into a ``zenoh.Config``.

The one adapter the router (``server/router.py``), the map server (``server/zenoh_session.py``)
and the edge agent (``edge/agent.py``) share: an optional Zenoh config file of the site
(:attr:`~wardmap.shared.zenoh_config.ZenohOptions.config`, e.g. the ACL that ``wardmap certs``
writes) is read first and wardmap's values are laid on top, each value of the file they
replace logged as a warning, so nothing is overridden silently. Before zenoh sees the config,
:func:`load_zenoh_config` checks that every ``tls/`` or ``quic/`` endpoint has the files it
needs and that every TLS file it names exists: a missing CA is one clear line here, not a
handshake that fails later as "Unable to connect". zenoh is imported when a config is built,
never at import.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from wardmap.shared.errors import ConfigError
from wardmap.shared.zenoh_config import ZenohOptions, config_leaves

log = logging.getLogger(__name__)

__all__ = ["TLS_FILE_KEYS", "TLS_PROTOCOLS", "connect_hint", "load_zenoh_config", "zenoh_error_line"]

TLS_FILE_KEYS = (
    "root_ca_certificate",
    "listen_certificate",
    "listen_private_key",
    "connect_certificate",
    "connect_private_key",
)
"""Keys of ``transport/link/tls`` that name PEM files (checked to exist)."""

TLS_PROTOCOLS = ("tls/", "quic/")
"""Endpoint prefixes whose links use the ``transport/link/tls`` files."""

_NEEDS = {
    "connect": (("root_ca_certificate", "--tls-ca"),),
    "listen": (("listen_certificate", "--tls-cert"), ("listen_private_key", "--tls-key")),
}


def zenoh_error_line(exc: BaseException) -> str:
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


def connect_hint(connect: Sequence[str]) -> str:
    """What to append to a failed connect to ``connect``: over ``tls/`` or ``quic/`` a refused handshake
    (unknown CA, no or foreign client certificate, wrong host name) shows only as a timeout."""
    if not any(str(e).startswith(TLS_PROTOCOLS) for e in connect):
        return ""
    return (
        "; over TLS check that the router's certificate names that host and is signed by "
        "--tls-ca, and that this process's --tls-cert comes from the router's CA"
    )


def load_zenoh_config(ours: Mapping[str, Any], options: ZenohOptions | None = None) -> Any:
    """The ``zenoh.Config`` of ``ours`` laid over the file ``options.config`` (if set).

    Args:
        ours: a config dict from :func:`~wardmap.shared.zenoh_config.router_config` or
            :func:`~wardmap.shared.zenoh_config.client_config` (its ``mode`` says which side).
        options: the process's Zenoh options; only ``config`` is read here (the TLS files are
            already in ``ours``).

    Raises:
        ConfigError: the file is missing or malformed, a ``tls/`` or ``quic/`` endpoint lacks its CA (client)
            or certificate and key (router), or a named TLS file does not exist.
    """
    import zenoh

    path = Path(options.config) if options is not None and options.config else None
    if path is None:
        conf = zenoh.Config.from_json5(json.dumps(ours))
    else:
        if not path.is_file():
            raise ConfigError(f"zenoh config file not found: {path}")
        try:
            conf = zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise ConfigError(f"bad zenoh config file {path}: {zenoh_error_line(exc)}") from exc
        defaults = zenoh.Config()
        for key, value in config_leaves(ours):
            before = json.loads(conf.get_json(key))
            set_by_file = before != json.loads(defaults.get_json(key))
            if set_by_file and before != value and not key.endswith("/endpoints"):
                log.warning("%s sets %s=%s; wardmap uses %s", path, key, json.dumps(before),
                            json.dumps(value))
            conf.insert_json5(key, json.dumps(value))
    _check_tls(conf, "listen" if ours.get("mode") == "router" else "connect", path)
    return conf


def _check_tls(conf: Any, side: str, path: Path | None) -> None:
    """Raise ConfigError when a ``tls/`` or ``quic/`` endpoint of ``side`` lacks a file, or a
    named file is missing."""
    tls = json.loads(conf.get_json("transport/link/tls"))
    endpoints = json.loads(conf.get_json(f"{side}/endpoints"))
    if isinstance(endpoints, Mapping):  # zenoh allows {router: [...], peer: [...]} per mode
        endpoints = [e for group in endpoints.values() for e in group]
    tls_endpoints = [e for e in endpoints if str(e).startswith(TLS_PROTOCOLS)]
    where = f" or transport/link/tls/ in {path}" if path is not None else ""
    for key, flag in _NEEDS[side] if tls_endpoints else ():
        if not tls.get(key):
            raise ConfigError(f"{tls_endpoints[0]} needs {flag} FILE{where} ({key})")
    for key in TLS_FILE_KEYS:
        name = tls.get(key)
        if name and not Path(name).is_file():
            raise ConfigError(f"TLS file not found: {name} (transport/link/tls/{key})")

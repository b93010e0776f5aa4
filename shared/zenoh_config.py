"""Zenoh configuration dicts and wardmap key expressions (pure: no zenoh import).

The dicts built here are JSON-compatible (hence JSON5-compatible) Zenoh configs: the
adapters that own a session (``server/router.py``, the edge daemon) hand them to
``zenoh.Config.from_json5(json.dumps(cfg))`` or insert them leaf by leaf with
:func:`config_leaves`. Keeping them here lets both sides and the tests agree on one
layout without importing zenoh.

Key expressions (docs/ARCHITECTURE.md, "Conventions") all start with
``wardmap/v1/``; one robot owns the subtree ``wardmap/v1/robot/<robot_id>/``; the map server
owns ``wardmap/v1/robots/<robot_id>/`` (what it tells that robot, e.g. its correction).
"""

from __future__ import annotations

import copy
import re
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, Literal

from wardmap.shared.errors import ConfigError
from wardmap.shared.wire import MAX_MESSAGE_BYTES

__all__ = [
    "ALL_CORRECTIONS",
    "ALL_KEYFRAMES",
    "ALL_LIVELINESS",
    "KEY_PREFIX",
    "ack_key",
    "client_config",
    "config_leaves",
    "correction_key",
    "heartbeat_key",
    "keyframe_key",
    "liveliness_key",
    "robot_id_from_key",
    "router_config",
    "validate_endpoint",
    "validate_robot_id",
]

KEY_PREFIX = "wardmap/v1"
"""Every wardmap key expression starts with this prefix."""

ALL_KEYFRAMES = f"{KEY_PREFIX}/robot/*/keyframe"
"""Subscription key for the keyframes of every robot."""

ALL_LIVELINESS = f"{KEY_PREFIX}/robot/*/alive"
"""Liveliness-subscriber key for the presence tokens of every robot."""

ALL_CORRECTIONS = f"{KEY_PREFIX}/robots/*/correction"
"""Key of the server's correction queryable: the corrections of every robot."""

MAX_ZENOH_MESSAGE_BYTES = MAX_MESSAGE_BYTES + 64 * 1024
"""Largest message any wardmap session or router reassembles (``transport/link/rx/
max_message_size``; zenoh's default is 1 GiB): the wire's limit plus room for zenoh's own
framing. Zenoh drops a larger message at the receiving link before it is reassembled, so a
50 MB payload never reaches ingest's queue (``wire.encode`` never makes one)."""

_ROBOT_ID_RE = re.compile(r"[A-Za-z0-9_.-]{1,64}")
_ROBOT_KEY_RE = re.compile(rf"{re.escape(KEY_PREFIX)}/robot/([A-Za-z0-9_.-]{{1,64}})/[A-Za-z0-9_.-]+")
# tcp/HOST:PORT with HOST a DNS name, an IPv4 address or a bracketed IPv6 address.
_ENDPOINT_RE = re.compile(
    r"tcp/(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9])?):(?P<port>\d+)"
)


# --------------------------------------------------------------------------- validation


def validate_endpoint(endpoint: str) -> str:
    """Check one Zenoh endpoint of the form ``tcp/HOST:PORT`` (port 1-65535).

    Returns the endpoint unchanged; raises :class:`ConfigError` naming the endpoint and
    the expected form otherwise.
    """
    if not isinstance(endpoint, str):
        raise ConfigError(
            f"endpoint must be a string like 'tcp/127.0.0.1:7447', got {type(endpoint).__name__}"
        )
    m = _ENDPOINT_RE.fullmatch(endpoint)
    if m is None:
        raise ConfigError(f"bad endpoint {endpoint!r}: expected 'tcp/HOST:PORT', e.g. 'tcp/127.0.0.1:7447'")
    port = int(m.group("port"))
    if not 1 <= port <= 65535:
        raise ConfigError(f"bad endpoint {endpoint!r}: port must be in 1..65535, got {port}")
    return endpoint


def _validate_endpoints(endpoints: Sequence[str], what: str) -> list[str]:
    if isinstance(endpoints, str):
        raise ConfigError(f"{what} endpoints must be a list of strings, got a single string {endpoints!r}")
    out = [validate_endpoint(e) for e in endpoints]
    if not out:
        raise ConfigError(f"{what} needs at least one endpoint like 'tcp/127.0.0.1:7447'")
    if len(set(out)) != len(out):
        raise ConfigError(f"{what} endpoints contain duplicates: {out}")
    return out


def validate_robot_id(robot_id: str) -> str:
    """Check a robot id: 1-64 characters from ``[A-Za-z0-9_.-]``; returns it unchanged."""
    if not isinstance(robot_id, str) or _ROBOT_ID_RE.fullmatch(robot_id) is None:
        raise ConfigError(f"bad robot id {robot_id!r}: expected 1-64 characters from [A-Za-z0-9_.-]")
    return robot_id


# --------------------------------------------------------------------------- configs


def _common(shm: bool, multicast_scouting: bool) -> dict[str, Any]:
    return {
        "scouting": {"multicast": {"enabled": bool(multicast_scouting)}},
        "transport": {
            "shared_memory": {"enabled": bool(shm)},
            "link": {"rx": {"max_message_size": MAX_ZENOH_MESSAGE_BYTES}},
        },
    }


def _deep_merge(base: dict[str, Any], extra: Mapping[str, Any], path: str = "") -> dict[str, Any]:
    """Return ``base`` updated recursively with ``extra`` (new dicts; inputs untouched)."""
    out = copy.deepcopy(base)
    for key, value in extra.items():
        if not isinstance(key, str) or not key or "/" in key:
            raise ConfigError(f"extra config key {path + str(key)!r} must be a non-empty name without '/'")
        if isinstance(value, Mapping) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value, f"{path}{key}/")
        else:
            out[key] = copy.deepcopy(dict(value) if isinstance(value, Mapping) else value)
    return out


def router_config(
    listen: Sequence[str],
    *,
    shm: bool = False,
    multicast_scouting: bool = False,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Config dict of a Zenoh router listening on ``listen`` (``tcp/HOST:PORT`` each).

    Shared memory and multicast scouting are off unless asked for: robots reach their
    router by explicit endpoints (docs/ARCHITECTURE.md, "Scale"). ``extra`` is merged
    in recursively (e.g. ``{"adminspace": {"enabled": True}}``) but may not change
    ``mode`` or ``listen``.
    """
    cfg: dict[str, Any] = {
        "mode": "router",
        "listen": {"endpoints": _validate_endpoints(listen, "router listen")},
        **_common(shm, multicast_scouting),
    }
    if extra:
        for fixed in ("mode", "listen"):
            if fixed in extra:
                raise ConfigError(f"router extra config may not set {fixed!r}; it is fixed by the arguments")
        cfg = _deep_merge(cfg, extra)
    return cfg


def client_config(
    connect: Sequence[str],
    *,
    mode: Literal["client", "peer"] = "client",
    shm: bool = False,
    multicast_scouting: bool = False,
) -> dict[str, Any]:
    """Config dict of a session (``mode`` client or peer) connecting to ``connect``.

    Shared memory and multicast scouting are off unless asked for.
    """
    if mode not in ("client", "peer"):
        raise ConfigError(f"bad session mode {mode!r}: expected 'client' or 'peer'")
    return {
        "mode": mode,
        "connect": {"endpoints": _validate_endpoints(connect, f"{mode} connect")},
        **_common(shm, multicast_scouting),
    }


def config_leaves(cfg: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    """Yield ``(path, value)`` for every non-dict leaf, paths joined by ``/``.

    The paths are the ones ``zenoh.Config.insert_json5`` takes, so a dict can be laid
    over a config loaded from a file: ``{"listen": {"endpoints": [...]}}`` yields
    ``("listen/endpoints", [...])``. Lists are leaves.
    """
    for key, value in cfg.items():
        path = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            yield from config_leaves(value, f"{path}/")
        else:
            yield path, value


# --------------------------------------------------------------------------- key expressions


def _robot_key(robot_id: str, leaf: str) -> str:
    return f"{KEY_PREFIX}/robot/{validate_robot_id(robot_id)}/{leaf}"


def keyframe_key(robot_id: str) -> str:
    """Key on which robot ``robot_id`` publishes its keyframes."""
    return _robot_key(robot_id, "keyframe")


def ack_key(robot_id: str) -> str:
    """Key on which the server acknowledges keyframes of robot ``robot_id``."""
    return _robot_key(robot_id, "ack")


def heartbeat_key(robot_id: str) -> str:
    """Key on which robot ``robot_id`` publishes its heartbeat (status) messages."""
    return _robot_key(robot_id, "heartbeat")


def liveliness_key(robot_id: str) -> str:
    """Key of the liveliness token that shows robot ``robot_id`` is connected."""
    return _robot_key(robot_id, "alive")


def correction_key(robot_id: str) -> str:
    """Key on which the server publishes the corrections (``wardmap.correction``) of robot
    ``robot_id``, in the server-owned subtree ``wardmap/v1/robots/<robot_id>/``."""
    return f"{KEY_PREFIX}/robots/{validate_robot_id(robot_id)}/correction"


def robot_id_from_key(key_expr: str) -> str:
    """Robot id in a concrete key ``wardmap/v1/robot/<robot_id>/<leaf>``.

    Raises :class:`ConfigError` when the key is not a robot key.
    """
    m = _ROBOT_KEY_RE.fullmatch(str(key_expr))
    if m is None:
        raise ConfigError(
            f"not a wardmap robot key: {key_expr!r} (expected '{KEY_PREFIX}/robot/<id>/<leaf>')"
        )
    return m.group(1)

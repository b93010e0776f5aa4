"""Zenoh configuration dicts and wardmap key expressions (pure: no zenoh import).

The dicts built here are JSON-compatible (hence JSON5-compatible) Zenoh configs: the
adapters that own a session (``server/router.py``, the edge daemon) hand them to
``zenoh.Config.from_json5(json.dumps(cfg))`` or insert them leaf by leaf with
:func:`config_leaves`. Keeping them here lets both sides and the tests agree on one
layout without importing zenoh.

Key expressions (docs/ARCHITECTURE.md, "Conventions") all start with
``wardmap/v1/``; one robot owns the subtree ``wardmap/v1/robot/<robot_id>/``; the map server
owns ``wardmap/v1/robots/<robot_id>/`` (what it tells that robot, e.g. its correction) and
``wardmap/v1/map/``. :func:`access_control` turns this layout into the router's ACL.
"""

from __future__ import annotations

import copy
import dataclasses
import re
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, Literal

from wardmap.shared.errors import ConfigError
from wardmap.shared.wire import MAX_MESSAGE_BYTES

__all__ = [
    "ALL_CORRECTIONS",
    "ALL_HEARTBEATS",
    "ALL_KEYFRAMES",
    "ALL_LIVELINESS",
    "KEY_PREFIX",
    "MAP_OBJECTS_KEY",
    "MAP_UPDATES_KEY",
    "ZenohOptions",
    "access_control",
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

ALL_HEARTBEATS = f"{KEY_PREFIX}/robot/*/heartbeat"
"""Subscription key for the heartbeats of every robot."""

ALL_LIVELINESS = f"{KEY_PREFIX}/robot/*/alive"
"""Liveliness-subscriber key for the presence tokens of every robot."""

ALL_CORRECTIONS = f"{KEY_PREFIX}/robots/*/correction"
"""Key of the server's correction queryable: the corrections of every robot."""

MAP_OBJECTS_KEY = f"{KEY_PREFIX}/map/objects"
"""Key of the server's object-map queryable (``shared/mapwire.py``, ``OBJECTS_KEY``)."""

MAP_UPDATES_KEY = f"{KEY_PREFIX}/map/updates"
"""Key on which the server publishes object-map changes (``shared/mapwire.py``, ``UPDATES_KEY``)."""

MAX_ZENOH_MESSAGE_BYTES = MAX_MESSAGE_BYTES + 64 * 1024
"""Largest message any wardmap session or router reassembles (``transport/link/rx/
max_message_size``; zenoh's default is 1 GiB): the wire's limit plus room for zenoh's own
framing. Zenoh drops a larger message at the receiving link before it is reassembled, so a
50 MB payload never reaches ingest's queue (``wire.encode`` never makes one)."""

_ROBOT_ID_RE = re.compile(r"[A-Za-z0-9_.-]{1,64}")
_ROBOT_KEY_RE = re.compile(rf"{re.escape(KEY_PREFIX)}/robot/([A-Za-z0-9_.-]{{1,64}})/[A-Za-z0-9_.-]+")
# tcp/, tls/ or quic/HOST:PORT with HOST a DNS name, an IPv4 address or a bracketed IPv6 address.
_ENDPOINT_RE = re.compile(
    r"(?P<proto>tcp|tls|quic)/(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9](?:[A-Za-z0-9.-]*[A-Za-z0-9])?):(?P<port>\d+)"
)


# --------------------------------------------------------------------------- validation


def validate_endpoint(endpoint: str) -> str:
    """Check one Zenoh endpoint ``tcp/HOST:PORT``, ``tls/HOST:PORT`` or ``quic/HOST:PORT`` (port
    1-65535). ``tls/`` and ``quic/`` take the TLS files of :class:`ZenohOptions`.

    Returns the endpoint unchanged; raises :class:`ConfigError` naming the endpoint and
    the expected form otherwise.
    """
    if not isinstance(endpoint, str):
        raise ConfigError(
            f"endpoint must be a string like 'tcp/127.0.0.1:7447', got {type(endpoint).__name__}"
        )
    m = _ENDPOINT_RE.fullmatch(endpoint)
    if m is None:
        raise ConfigError(
            f"bad endpoint {endpoint!r}: expected 'tcp/HOST:PORT', 'tls/HOST:PORT' or 'quic/HOST:PORT', "
            "e.g. 'tcp/127.0.0.1:7447'"
        )
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


@dataclasses.dataclass(frozen=True)
class ZenohOptions:
    """How a process reaches Zenoh beyond its endpoints: the ``[zenoh]`` table of
    ``deploy/server.toml`` and ``deploy/edge.toml``, and the ``--zenoh-config`` / ``--tls-*``
    flags of ``wardmap router|server|edge`` (docs/security.md). Empty strings mean "not set".

    For a client (server, edge) the TLS files authenticate the router (``tls_ca``) and this
    process to the router (``tls_cert`` + ``tls_key``, mutual TLS). For the router they are
    its listen certificate and key, and with ``tls_ca`` it demands a client certificate
    signed by that CA from everyone who connects.
    """

    config: str = dataclasses.field(
        default="", metadata={"doc": "zenoh JSON5 config file laid under wardmap's values"}
    )
    tls_ca: str = dataclasses.field(default="", metadata={"doc": "PEM file of the site CA (ca.crt)"})
    tls_cert: str = dataclasses.field(default="", metadata={"doc": "PEM certificate of this process"})
    tls_key: str = dataclasses.field(default="", metadata={"doc": "PEM private key of tls_cert"})

    def __post_init__(self) -> None:
        if bool(self.tls_cert) != bool(self.tls_key):
            raise ValueError("tls_cert and tls_key go together: give both or neither")

    def tls(self, side: Literal["connect", "listen"]) -> dict[str, Any]:
        """The ``transport/link/tls`` table these options set (empty when none is set).

        ``side`` ``connect``: a client's CA and client certificate (``enable_mtls`` with a
        certificate); ``listen``: the router's certificate, and ``enable_mtls`` when a CA
        to check clients against is given too.
        """
        tls: dict[str, Any] = {}
        if self.tls_ca:
            tls["root_ca_certificate"] = self.tls_ca
        if self.tls_cert:
            tls[f"{side}_certificate"] = self.tls_cert
            tls[f"{side}_private_key"] = self.tls_key
            if side == "connect" or self.tls_ca:
                tls["enable_mtls"] = True
        return tls


def _common(shm: bool, multicast_scouting: bool, tls: Mapping[str, Any] | None = None) -> dict[str, Any]:
    link: dict[str, Any] = {"rx": {"max_message_size": MAX_ZENOH_MESSAGE_BYTES}}
    if tls:
        link["tls"] = dict(tls)
    return {
        "scouting": {"multicast": {"enabled": bool(multicast_scouting)}},
        "transport": {"shared_memory": {"enabled": bool(shm)}, "link": link},
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
    options: ZenohOptions | None = None,
    extra: Mapping[str, Any] | None = None,
    connect: Sequence[str] = (),
) -> dict[str, Any]:
    """Config dict of a Zenoh router listening on ``listen`` (``tcp/`` or ``tls/HOST:PORT`` each).

    Shared memory and multicast scouting are off unless asked for: robots reach their
    router by explicit endpoints (docs/ARCHITECTURE.md, "Scale"). ``connect``: other routers
    to join into one mesh (zenoh retries them until they answer, and after they go away).
    ``options`` adds the listen side's TLS files (:meth:`ZenohOptions.tls`), and with
    ``connect`` the same files as this router's client side towards the other routers (the
    certificate must allow client authentication, as ``wardmap certs`` makes it). ``extra`` is
    merged in recursively (e.g. ``{"adminspace": {"enabled": True}}``) but may not change
    ``mode``, ``listen`` or ``connect``.
    """
    tls = options.tls("listen") if options is not None else None
    if connect and options is not None:
        tls = {**(tls or {}), **options.tls("connect")}
    cfg: dict[str, Any] = {
        "mode": "router",
        "listen": {"endpoints": _validate_endpoints(listen, "router listen")},
        **_common(shm, multicast_scouting, tls),
    }
    if connect:
        cfg["connect"] = {"endpoints": _validate_endpoints(connect, "router connect")}
    if extra:
        for fixed in ("mode", "listen", "connect"):
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
    options: ZenohOptions | None = None,
) -> dict[str, Any]:
    """Config dict of a session (``mode`` client or peer) connecting to ``connect``.

    Shared memory and multicast scouting are off unless asked for. ``options`` adds the
    connect side's TLS files (:meth:`ZenohOptions.tls`).
    """
    if mode not in ("client", "peer"):
        raise ConfigError(f"bad session mode {mode!r}: expected 'client' or 'peer'")
    tls = options.tls("connect") if options is not None else None
    return {
        "mode": mode,
        "connect": {"endpoints": _validate_endpoints(connect, f"{mode} connect")},
        **_common(shm, multicast_scouting, tls),
    }


_EVERY_MESSAGE = (
    "put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
    "liveliness_token", "liveliness_query", "declare_liveliness_subscriber",
)


def _allow(rule_id: str, messages: Sequence[str], flow: str, key_exprs: Sequence[str]) -> dict[str, Any]:
    return {"id": rule_id, "messages": list(messages), "flows": [flow], "permission": "allow",
            "key_exprs": list(key_exprs)}


def access_control(robots: Sequence[str], servers: Sequence[str]) -> dict[str, Any]:
    """The router's ``access_control`` table for a fleet (Zenoh 1.x ACL, default deny).

    Subjects are TLS client certificates by common name (``cert_common_names``), so the
    router must listen on ``tls/`` with mutual TLS. What each may do, as seen from the router
    (``ingress``: from that process; ``egress``: to it):

    - a **server** (CN in ``servers``): every message on ``wardmap/v1/**`` both ways: it
      subscribes to keyframes, publishes acks, corrections and map updates and declares
      the map and correction queryables.
    - **robot** R (CN in ``robots``, a robot id): puts only its own keyframes and heartbeats
      (``wardmap/v1/robot/R/keyframe|heartbeat``), declares its liveliness token, subscribes
      to its own acks and corrections and to the map updates, queries its corrections and
      the map; it receives only those (acks, corrections, replies, updates). It never
      publishes acks or map updates, never answers a query, never sees another robot's keys.
    - anyone else (no certificate, an unknown name): nothing (``default_permission`` deny).

    Raises:
        ConfigError: a bad robot id, a name in both lists, or an empty fleet.
    """
    robot_ids = [validate_robot_id(r) for r in robots]
    server_names = [validate_robot_id(s) for s in servers]
    both = sorted(set(robot_ids) & set(server_names))
    if both:
        raise ConfigError(f"names both robot and server: {', '.join(both)}")
    if len(set(robot_ids)) != len(robot_ids) or len(set(server_names)) != len(server_names):
        raise ConfigError("the fleet lists a name twice")
    if not robot_ids and not server_names:
        raise ConfigError("the fleet is empty: issue server and robot certificates first")
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    if server_names:
        rules += [_allow("server_in", _EVERY_MESSAGE, "ingress", [f"{KEY_PREFIX}/**"]),
                  _allow("server_out", _EVERY_MESSAGE, "egress", [f"{KEY_PREFIX}/**"])]
        subjects.append({"id": "servers", "cert_common_names": server_names})
        policies.append({"id": "servers", "rules": ["server_in", "server_out"], "subjects": ["servers"]})
    for rid in robot_ids:
        own = [keyframe_key(rid), heartbeat_key(rid)]
        inbound = [ack_key(rid), correction_key(rid)]
        prefix = f"robot_{rid}"
        own_rules = [
            _allow(f"{prefix}_put", ["put"], "ingress", own),
            _allow(f"{prefix}_token", ["liveliness_token"], "ingress", [liveliness_key(rid)]),
            _allow(f"{prefix}_subscribe", ["declare_subscriber"], "ingress", [*inbound, MAP_UPDATES_KEY]),
            _allow(f"{prefix}_query", ["query"], "ingress", [correction_key(rid), MAP_OBJECTS_KEY]),
            _allow(f"{prefix}_receive", ["put"], "egress", [*inbound, MAP_UPDATES_KEY]),
            _allow(f"{prefix}_replies", ["reply"], "egress", [correction_key(rid), MAP_OBJECTS_KEY]),
            # The server's declarations reach the robot (a client publishes or queries only
            # what it knows a match for); a declaration must lie inside a rule's key.
            _allow(f"{prefix}_interest", ["declare_subscriber"], "egress", [ALL_KEYFRAMES, ALL_HEARTBEATS]),
            _allow(f"{prefix}_queryables", ["declare_queryable"], "egress",
                   [ALL_CORRECTIONS, MAP_OBJECTS_KEY]),
        ]
        rules += own_rules
        subjects.append({"id": prefix, "cert_common_names": [rid]})
        policies.append({"id": prefix, "rules": [r["id"] for r in own_rules], "subjects": [prefix]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


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

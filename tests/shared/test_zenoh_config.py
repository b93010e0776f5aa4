"""Tests of wardmap.shared.zenoh_config: config dicts, endpoint and robot-id validation, keys."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from wardmap.shared.errors import ConfigError
from wardmap.shared.wire import MAX_MESSAGE_BYTES
from wardmap.shared.zenoh_config import (
    ALL_KEYFRAMES,
    ALL_LIVELINESS,
    KEY_PREFIX,
    MAP_OBJECTS_KEY,
    MAP_UPDATES_KEY,
    ZenohOptions,
    access_control,
    ack_key,
    client_config,
    config_leaves,
    correction_key,
    heartbeat_key,
    keyframe_key,
    liveliness_key,
    robot_id_from_key,
    router_config,
    validate_endpoint,
)


def test_router_config_defaults_off() -> None:
    """A router config listens where asked, with shared memory and multicast scouting off."""
    cfg = router_config(["tcp/127.0.0.1:7447", "tcp/[::1]:7448"])
    assert cfg["mode"] == "router"
    assert cfg["listen"] == {"endpoints": ["tcp/127.0.0.1:7447", "tcp/[::1]:7448"]}
    assert cfg["scouting"]["multicast"]["enabled"] is False
    assert cfg["transport"]["shared_memory"]["enabled"] is False
    assert json.loads(json.dumps(cfg)) == cfg  # JSON (hence JSON5) serialisable


def test_router_config_joins_other_routers() -> None:
    """``connect`` makes a mesh: the other routers' endpoints, checked like listen's; extra may
    not change them; without it the router connects to nothing."""
    cfg = router_config(["tcp/127.0.0.1:7447"], connect=["tcp/10.0.0.2:7447"])
    assert cfg["connect"] == {"endpoints": ["tcp/10.0.0.2:7447"]}
    assert "connect" not in router_config(["tcp/127.0.0.1:7447"])
    with pytest.raises(ConfigError, match="router connect"):
        router_config(["tcp/127.0.0.1:7447"], connect=["tcp/a:1", "tcp/a:1"])
    with pytest.raises(ConfigError, match="connect"):
        router_config(["tcp/127.0.0.1:7447"], extra={"connect": {"endpoints": []}})


def test_router_config_flags_and_extra_merge() -> None:
    """Flags switch shm/scouting on; extra merges recursively without losing siblings."""
    cfg = router_config(
        ["tcp/0.0.0.0:7447"],
        shm=True,
        multicast_scouting=True,
        extra={
            "transport": {"link": {"tx": {"queue": {"size": {"data": 8}}}}},
            "adminspace": {"enabled": True},
        },
    )
    assert cfg["transport"]["shared_memory"]["enabled"] is True
    assert cfg["transport"]["link"]["tx"]["queue"]["size"]["data"] == 8
    assert cfg["scouting"]["multicast"]["enabled"] is True
    assert cfg["adminspace"] == {"enabled": True}


def test_router_config_extra_is_not_aliased() -> None:
    """Mutating the returned dict leaves the caller's extra dict untouched."""
    extra = {"adminspace": {"enabled": True}}
    cfg = router_config(["tcp/127.0.0.1:7447"], extra=extra)
    cfg["adminspace"]["enabled"] = False
    assert extra == {"adminspace": {"enabled": True}}


@pytest.mark.parametrize("key", ["mode", "listen"])
def test_router_config_extra_cannot_override_fixed_keys(key: str) -> None:
    """extra may not change mode or listen: those come from the arguments."""
    with pytest.raises(ConfigError, match=key):
        router_config(["tcp/127.0.0.1:7447"], extra={key: "peer"})


def test_client_config_modes() -> None:
    """Client and peer configs connect to the given endpoints with shm and scouting off."""
    for mode in ("client", "peer"):
        cfg = client_config(["tcp/127.0.0.1:7447"], mode=mode)
        assert cfg["mode"] == mode
        assert cfg["connect"] == {"endpoints": ["tcp/127.0.0.1:7447"]}
        assert cfg["scouting"]["multicast"]["enabled"] is False
        assert cfg["transport"]["shared_memory"]["enabled"] is False
    with pytest.raises(ConfigError, match="mode"):
        client_config(["tcp/127.0.0.1:7447"], mode="router")


@pytest.mark.parametrize(
    "endpoint",
    ["tcp/127.0.0.1:1", "tcp/localhost:65535", "tcp/router-1.ward3.example.org:7447", "tcp/[::1]:7447",
     "tls/router-1.ward3.example.org:7447", "tls/[::1]:7447", "quic/127.0.0.1:7447"],
)
def test_valid_endpoints(endpoint: str) -> None:
    """Well-formed tcp, tls and quic endpoints pass through unchanged."""
    assert validate_endpoint(endpoint) == endpoint


@pytest.mark.parametrize(
    ("endpoint", "match"),
    [
        ("tcp/127.0.0.1:0", "1..65535"),
        ("tcp/127.0.0.1:65536", "1..65535"),
        ("tcp/127.0.0.1", "tcp/HOST:PORT"),
        ("127.0.0.1:7447", "tcp/HOST:PORT"),
        ("udp/127.0.0.1:7447", "'tls/HOST:PORT' or 'quic/HOST:PORT'"),
        ("tcp/:7447", "tcp/HOST:PORT"),
        ("tcp/127.0.0.1:74a7", "tcp/HOST:PORT"),
        ("tcp/127.0.0.1:7447 ", "tcp/HOST:PORT"),
        ("", "tcp/HOST:PORT"),
    ],
)
def test_bad_endpoints(endpoint: str, match: str) -> None:
    """Malformed endpoints and out-of-range ports raise ConfigError naming the expected form."""
    with pytest.raises(ConfigError, match=match):
        validate_endpoint(endpoint)


def test_endpoint_lists_are_checked() -> None:
    """Empty lists, a bare string and duplicates are rejected; one bad entry fails the list."""
    with pytest.raises(ConfigError, match="at least one"):
        router_config([])
    with pytest.raises(ConfigError, match="single string"):
        client_config("tcp/127.0.0.1:7447")
    with pytest.raises(ConfigError, match="duplicates"):
        router_config(["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7447"])
    with pytest.raises(ConfigError, match="port"):
        client_config(["tcp/127.0.0.1:7447", "tcp/127.0.0.1:99999"])


def test_config_leaves_paths() -> None:
    """Leaves are the slash paths zenoh's insert_json5 takes; lists are leaves."""
    leaves = dict(config_leaves(router_config(["tcp/127.0.0.1:7447"])))
    assert leaves == {
        "mode": "router",
        "listen/endpoints": ["tcp/127.0.0.1:7447"],
        "scouting/multicast/enabled": False,
        "transport/shared_memory/enabled": False,
        "transport/link/rx/max_message_size": MAX_MESSAGE_BYTES + 64 * 1024,
    }


def test_robot_keys() -> None:
    """Per-robot keys live under wardmap/v1/robot/<id>/ and round-trip to the robot id."""
    keys = [keyframe_key("r1"), ack_key("r1"), heartbeat_key("r1"), liveliness_key("r1")]
    assert keys == [
        "wardmap/v1/robot/r1/keyframe",
        "wardmap/v1/robot/r1/ack",
        "wardmap/v1/robot/r1/heartbeat",
        "wardmap/v1/robot/r1/alive",
    ]
    assert all(k.startswith(KEY_PREFIX + "/") for k in keys)
    assert len(set(keys)) == len(keys)
    assert ALL_KEYFRAMES == "wardmap/v1/robot/*/keyframe"
    assert ALL_LIVELINESS == "wardmap/v1/robot/*/alive"
    robot = "Ward-3_bot.07"
    assert robot_id_from_key(keyframe_key(robot)) == robot
    assert robot_id_from_key(liveliness_key("x" * 64)) == "x" * 64


@pytest.mark.parametrize("robot_id", ["", "a/b", "r*", "r$1", "r 1", "x" * 65, "**", "r?", "r#"])
def test_bad_robot_ids(robot_id: str) -> None:
    """Robot ids outside [A-Za-z0-9_.-]{1,64} (wildcards, slashes, too long) raise ConfigError."""
    for make in (keyframe_key, ack_key, heartbeat_key, liveliness_key):
        with pytest.raises(ConfigError, match="robot id"):
            make(robot_id)


@pytest.mark.parametrize(
    "key", ["wardmap/v1/robot/*/keyframe", "wardmap/v2/robot/r1/keyframe", "other/r1", ""]
)
def test_robot_id_from_bad_key(key: str) -> None:
    """Wildcard, foreign-version and non-robot keys are not robot keys."""
    with pytest.raises(ConfigError, match="not a wardmap robot key"):
        robot_id_from_key(key)


def test_module_is_pure() -> None:
    """Importing the module does not import zenoh (shared/ is pure)."""
    code = "import sys, wardmap.shared.zenoh_config; sys.exit('zenoh' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 0


# --------------------------------------------------------------------------- TLS and ACL


def test_tls_endpoints_and_options_on_both_sides() -> None:
    """``tls/`` endpoints pass; a client gets the CA and its certificate with mutual TLS on,
    a router its listen certificate, and mutual TLS only when it has a CA to check clients."""
    opts = ZenohOptions(tls_ca="ca.crt", tls_cert="me.crt", tls_key="me.key")
    client = client_config(["tls/router.ward.local:7447"], options=opts)
    assert client["transport"]["link"]["tls"] == {
        "root_ca_certificate": "ca.crt", "connect_certificate": "me.crt",
        "connect_private_key": "me.key", "enable_mtls": True,
    }
    router = router_config(["tls/0.0.0.0:7447"], options=opts)
    assert router["transport"]["link"]["tls"] == {
        "root_ca_certificate": "ca.crt", "listen_certificate": "me.crt",
        "listen_private_key": "me.key", "enable_mtls": True,
    }
    no_ca = ZenohOptions(tls_cert="r.crt", tls_key="r.key")
    server_auth_only = router_config(["tls/0.0.0.0:7447"], options=no_ca)
    assert "enable_mtls" not in server_auth_only["transport"]["link"]["tls"]
    assert "tls" not in client_config(["tcp/127.0.0.1:7447"], options=ZenohOptions())["transport"]["link"]
    with pytest.raises(ValueError, match="go together"):
        ZenohOptions(tls_ca="ca.crt", tls_cert="me.crt")


def _rules_of(acl: dict, subject: str) -> list[dict]:
    (policy,) = [p for p in acl["policies"] if p["subjects"] == [subject]]
    return [r for r in acl["rules"] if r["id"] in policy["rules"]]


def test_access_control_confines_each_robot_to_its_own_keys() -> None:
    """Every key a robot may put, declare or query from (ingress) lies in its own subtrees or is
    a map read; it never may put acks, corrections or map updates, reply, or declare a
    queryable; what it receives (egress puts and replies) is its own or the map's; servers
    may do everything under ``wardmap/v1``; the default is deny; subjects are cert names."""
    acl = access_control(["robot_0", "robot_1"], ["server"])
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert {s["id"]: s["cert_common_names"] for s in acl["subjects"]} == {
        "servers": ["server"], "robot_robot_0": ["robot_0"], "robot_robot_1": ["robot_1"],
    }
    assert all(r["permission"] == "allow" for r in acl["rules"])
    for rid in ("robot_0", "robot_1"):
        rules = _rules_of(acl, f"robot_{rid}")
        mine = (f"{KEY_PREFIX}/robot/{rid}/", f"{KEY_PREFIX}/robots/{rid}/")
        granted = {
            (m, f, k) for r in rules for m in r["messages"] for f in r["flows"] for k in r["key_exprs"]
        }
        ingress_puts = {k for m, f, k in granted if f == "ingress" and m == "put"}
        assert ingress_puts == {keyframe_key(rid), heartbeat_key(rid)}
        assert not {(m, f) for m, f, _ in granted} & {
            ("reply", "ingress"), ("declare_queryable", "ingress"), ("delete", "ingress"),
        }
        for m, f, k in granted:
            if f == "ingress" or m in ("put", "reply"):
                assert k.startswith(mine) or k in (MAP_OBJECTS_KEY, MAP_UPDATES_KEY), (m, f, k)
        assert ("put", "egress", ack_key(rid)) in granted
        assert ("put", "egress", correction_key(rid)) in granted
    server_rules = _rules_of(acl, "servers")
    assert {k for r in server_rules for k in r["key_exprs"]} == {f"{KEY_PREFIX}/**"}
    assert {f for r in server_rules for f in r["flows"]} == {"ingress", "egress"}
    assert json.loads(json.dumps(acl)) == acl


@pytest.mark.parametrize(
    ("robots", "servers", "match"),
    [(["bad id"], [], "bad robot id"), (["a"], ["a"], "both robot and server"),
     (["a", "a"], [], "twice"), ([], [], "empty")],
)
def test_access_control_bad_fleets(robots: list[str], servers: list[str], match: str) -> None:
    """A bad name, a name in both roles, a repeated name or an empty fleet: ConfigError."""
    with pytest.raises(ConfigError, match=match):
        access_control(robots, servers)

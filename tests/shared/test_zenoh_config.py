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
    ack_key,
    client_config,
    config_leaves,
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
    ["tcp/127.0.0.1:1", "tcp/localhost:65535", "tcp/router-1.ward3.example.org:7447", "tcp/[::1]:7447"],
)
def test_valid_endpoints(endpoint: str) -> None:
    """Well-formed tcp endpoints pass through unchanged."""
    assert validate_endpoint(endpoint) == endpoint


@pytest.mark.parametrize(
    ("endpoint", "match"),
    [
        ("tcp/127.0.0.1:0", "1..65535"),
        ("tcp/127.0.0.1:65536", "1..65535"),
        ("tcp/127.0.0.1", "tcp/HOST:PORT"),
        ("127.0.0.1:7447", "tcp/HOST:PORT"),
        ("udp/127.0.0.1:7447", "tcp/HOST:PORT"),
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

"""The server's one Zenoh session helper (``server/zenoh_session.py``)."""

from __future__ import annotations

import pytest
from procs import free_port

pytest.importorskip("zenoh")

from wardmap.server.zenoh_session import ZenohSessionError, first_line, open_session
from wardmap.shared.errors import ConfigError

pytestmark = pytest.mark.timeout(60)


def test_unreachable_router_is_a_clear_error() -> None:
    with pytest.raises(ZenohSessionError, match=r"cannot connect to tcp/127\.0\.0\.1:"):
        open_session([f"tcp/127.0.0.1:{free_port()}"])


def test_bad_endpoint_fails_before_zenoh() -> None:
    with pytest.raises(ConfigError, match="expected 'tcp/HOST:PORT'"):
        open_session(["udp/127.0.0.1:7447"])


def test_first_line_drops_the_rust_location() -> None:
    err = RuntimeError("Unable to connect to any of [tcp/1.2.3.4:1]! at /root/zenoh/src/net.rs:42.")
    assert first_line(err) == "Unable to connect to any of [tcp/1.2.3.4:1]!"
    assert first_line(RuntimeError("  ")) == "RuntimeError"
    multi = RuntimeError("bad config\n --> 2:1\n  |\n2 | x\n  = expected identifier")
    assert first_line(multi) == "--> 2:1 = expected identifier"

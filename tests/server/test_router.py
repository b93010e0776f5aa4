"""Tests of wardmap.server.router.run_router in-process: stop event, config file, start-up errors."""

from __future__ import annotations

import json
import logging
import socket
import threading
from pathlib import Path

import pytest

zenoh = pytest.importorskip("zenoh")

from wardmap.server.router import RouterError, run_router  # noqa: E402  (after the importorskip guard)
from wardmap.shared.errors import ConfigError  # noqa: E402
from wardmap.shared.zenoh_config import ZenohOptions, client_config  # noqa: E402

pytestmark = pytest.mark.timeout(60)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_router_in_thread_with_config_file(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A router on a worker thread, under a JSON5 file enabling multicast scouting, serves a client,
    warns that wardmap overrides the file's scouting value (and only that: the values the file
    leaves at zenoh's defaults are not the file's), and returns once ``stop`` is set."""
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    conf_file = tmp_path / "zenoh.json5"
    conf_file.write_text("{\n  // user file\n  scouting: { multicast: { enabled: true } },\n}\n")
    stop, ready = threading.Event(), threading.Event()
    seen: list[list[str]] = []
    errors: list[BaseException] = []

    def on_ready(endpoints: list[str]) -> None:
        seen.append(endpoints)
        ready.set()

    def target() -> None:
        try:
            run_router([endpoint], options=ZenohOptions(config=str(conf_file)), stop=stop, on_ready=on_ready)
        except BaseException as exc:  # surfaced to the test thread below
            errors.append(exc)
            ready.set()

    caplog.set_level(logging.WARNING, logger="wardmap.shared.zenoh_load")
    worker = threading.Thread(target=target)
    worker.start()
    try:
        assert ready.wait(15), "router not ready"
        assert not errors, errors
        assert seen == [[endpoint]]
        with zenoh.open(zenoh.Config.from_json5(json.dumps(client_config([endpoint])))) as client:
            assert len(list(client.info.routers_zid())) == 1
    finally:
        stop.set()
        worker.join(10)
    assert not worker.is_alive()
    assert not errors, errors
    warned = [r.getMessage() for r in caplog.records if r.name == "wardmap.shared.zenoh_load"]
    assert len(warned) == 1 and "scouting/multicast/enabled" in warned[0], warned


def test_port_in_use_raises_router_error() -> None:
    """A taken port becomes a RouterError (a WardmapError) that says so, not a zenoh.ZError."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        endpoint = f"tcp/127.0.0.1:{holder.getsockname()[1]}"
        with pytest.raises(RouterError, match="address already in use"):
            run_router([endpoint], stop=threading.Event())


@pytest.mark.parametrize(
    ("name", "text", "match"),
    [
        ("missing.json5", None, "not found"),
        ("broken.json5", "{ mode: ", "bad zenoh config file"),
        ("unknown.json5", "{ nosuch: 1 }", "nosuch"),
        ("zenoh.txt", "{}", "Unsupported file type"),
    ],
)
def test_bad_config_file_raises_config_error(tmp_path: Path, name: str, text: str | None, match: str) -> None:
    """Missing, unparsable, unknown-key and wrong-extension config files raise ConfigError."""
    path = tmp_path / name
    if text is not None:
        path.write_text(text)
    with pytest.raises(ConfigError, match=match):
        run_router(["tcp/127.0.0.1:1"], options=ZenohOptions(config=str(path)), stop=threading.Event())

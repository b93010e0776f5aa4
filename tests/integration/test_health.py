"""The server's probes and start-up against real processes: a ``wardmap router`` subprocess that
is killed and started again, and a ``wardmap server`` subprocess (default mapping stage, tokens
required; the probes need none). ``/readyz``'s rule: ``server/api/readiness.py``.

The tests wait on ready lines, log lines and the probe's own answers (polled every 50 ms, the
event under test), never on fixed sleeps.
"""

from __future__ import annotations

import json
import queue
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from factories import keyframe
from peers import ALL_ACKS, matched_publisher, open_client
from procs import (
    Proc,
    assert_stops_cleanly,
    child_env,
    free_port,
    kill_proc,
    one_line_error,
    read_line,
    spawn_logged,
    start,
    stop,
    stop_proc,
    wardmap,
    wardmap_cmd,
)

pytest.importorskip("zenoh")

from wardmap.shared.wire import AckMsg, decode_ack, encode
from wardmap.shared.zenoh_config import keyframe_key

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]

READY_TIMEOUT_S = 60.0


def _router(endpoint: str) -> subprocess.Popen[str]:
    cmd = wardmap_cmd("router", "--listen", endpoint)
    return start(cmd, f"router listening on {endpoint}", READY_TIMEOUT_S)


def _server_cmd(endpoint: str, db: Path, port: int) -> list[str]:
    return wardmap_cmd("server", "--connect", endpoint, "--db", f"sqlite:///{db}",
                       "--http", f"127.0.0.1:{port}")


def _until(check: Callable[[], bool], timeout_s: float) -> float:
    """Poll ``check`` every 50 ms until it is true; the seconds it took (fails after ``timeout_s``)."""
    t0 = time.monotonic()
    while not check():
        if time.monotonic() - t0 > timeout_s:
            pytest.fail(f"not within {timeout_s} s")
        time.sleep(0.05)
    return time.monotonic() - t0


def _ready(http: httpx.Client) -> tuple[int, str]:
    """``(HTTP status, the body's status)``; the body also says this lone server is the writer."""
    r = http.get("/readyz")
    body = r.json()
    assert body["mapping"] == "writer", body
    return r.status_code, body["status"]


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def server_proc(endpoint: str, tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """A router, then a server connected to it, after both ready lines; yields the router
    process (the test kills it) and the server's base URL."""
    router = _router(endpoint)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    server = start(_server_cmd(endpoint, tmp_path / "map.db", port), f"server ready: {url}", READY_TIMEOUT_S)
    try:
        yield router, url
    finally:
        stop(server)
        stop(router)


def test_readyz_follows_the_router(server_proc: tuple[subprocess.Popen[str], str], endpoint: str) -> None:
    """Ready with its router; the router SIGKILLed: ``/readyz`` answers 503 "zenoh router not
    connected" within 2 s while ``/healthz`` stays 200; a router started again on the same
    endpoint: ready (200) again within 10 s, and ready means it: a keyframe published through
    the new router is acked ``stored``."""
    router, url = server_proc
    with httpx.Client(base_url=url, timeout=5) as http:
        _until(lambda: _ready(http)[0] == 200, 30)
        router.send_signal(signal.SIGKILL)
        router.wait(timeout=10)
        took = _until(lambda: _ready(http)[0] == 503, 5)
        assert took < 2.0, took
        assert _ready(http) == (503, "zenoh router not connected")
        assert http.get("/healthz").status_code == 200
        again = _router(endpoint)
        try:
            _until(lambda: _ready(http) == (200, "ok"), 10)
            acks: queue.Queue[AckMsg] = queue.Queue()
            with (
                open_client(endpoint) as session,
                session.declare_subscriber(ALL_ACKS, lambda s: acks.put(decode_ack(s.payload.to_bytes()))),
            ):
                msg = keyframe(np.random.default_rng(3), robot_id="r1")
                matched_publisher(session, keyframe_key("r1"), 10).put(encode(msg))
                ack = acks.get(timeout=10)
            assert (ack.robot_id, ack.seq, ack.status) == ("r1", msg.seq, "stored")
        finally:
            stop(again)


def _stderr_has(proc: Proc, text: str) -> Callable[[], bool]:
    def check() -> bool:
        if proc.popen.poll() is not None:
            pytest.fail(f"server exited ({proc.popen.returncode}): {proc.stderr()[-2000:]}")
        return text in proc.stderr()
    return check


def test_a_server_started_before_its_router_waits_for_it(endpoint: str, tmp_path: Path) -> None:
    """No router yet: the server does not exit; it logs a "waiting for a zenoh router" warning
    per attempt (at least two, 1 s apart, no traceback); once a router listens it prints its ready
    line and ``/readyz`` answers 200; SIGTERM then exits 0."""
    port = free_port()
    server = spawn_logged(_server_cmd(endpoint, tmp_path / "map.db", port), tmp_path, "server")
    try:
        _until(lambda: _stderr_has(server, "attempt 2 failed")(), 60)
        waits = [ln for ln in server.stderr().splitlines() if "waiting for a zenoh router" in ln]
        assert len(waits) >= 2, server.stderr()
        assert endpoint in waits[0]
        router = _router(endpoint)
        try:
            assert server.popen.stdout is not None
            line = read_line(server.popen.stdout, 60)
            assert line == f"server ready: http://127.0.0.1:{port}\n", server.stderr()
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=5) as http:
                _until(lambda: _ready(http)[0] == 200, 30)
            assert_stops_cleanly(server)
        finally:
            stop(router)
    finally:
        kill_proc(server)
    assert "Traceback" not in server.stderr()


def test_sigterm_while_waiting_for_the_router_exits_0(endpoint: str, tmp_path: Path) -> None:
    """A server still waiting for its router ends on SIGTERM with exit code 0 and no traceback;
    with ``--log-format json`` every stderr line is one JSON object."""
    cmd = [*_server_cmd(endpoint, tmp_path / "map.db", free_port()), "--log-format", "json"]
    server = spawn_logged(cmd, tmp_path, "server")
    try:
        _until(_stderr_has(server, "waiting for a zenoh router"), 60)
        assert stop_proc(server, timeout_s=20) == 0, server.stderr()
    finally:
        kill_proc(server)
    records = [json.loads(line) for line in server.stderr().splitlines()]
    assert records and all(isinstance(r, dict) for r in records)
    assert any(r["level"] == "WARNING" and "waiting for a zenoh router" in r["message"] for r in records)
    assert "Traceback" not in server.stderr()


def test_router_check_and_systemd_readiness(endpoint: str, tmp_path: Path) -> None:
    """A router started with ``NOTIFY_SOCKET`` sends systemd ``READY=1`` once it listens;
    ``wardmap router --check`` exits 0 naming it, and 1 with one error line once it is gone."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as notify_sock:
        notify_sock.bind(str(tmp_path / "notify"))
        notify_sock.settimeout(READY_TIMEOUT_S)
        env = {**child_env(), "NOTIFY_SOCKET": str(tmp_path / "notify")}
        router = subprocess.Popen(wardmap_cmd("router", "--listen", endpoint), stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, env=env)
        try:
            assert notify_sock.recv(64) == b"READY=1"
            ok = wardmap("router", "--check", endpoint, timeout_s=60)
            assert ok.returncode == 0, ok.stderr
            assert ok.stdout.startswith("zenoh router ") and endpoint in ok.stdout
        finally:
            stop(router)
    gone = wardmap("router", "--check", endpoint, timeout_s=60)
    one_line_error(gone, f"no zenoh router answers at {endpoint}", "router")


def test_server_tells_systemd_it_is_ready_and_alive(endpoint: str, tmp_path: Path) -> None:
    """Under a ``Type=notify`` unit with ``WatchdogSec`` (stood in for by ``NOTIFY_SOCKET`` and
    ``WATCHDOG_USEC`` = 1 s): the server sends ``READY=1`` once ready, then ``WATCHDOG=1`` while its
    HTTP loop answers."""
    router = _router(endpoint)
    port = free_port()
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as notify_sock:
        notify_sock.bind(str(tmp_path / "notify"))
        notify_sock.settimeout(READY_TIMEOUT_S)
        env = {**child_env(), "NOTIFY_SOCKET": str(tmp_path / "notify"), "WATCHDOG_USEC": "1000000"}
        server = subprocess.Popen(_server_cmd(endpoint, tmp_path / "map.db", port), stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, env=env)
        try:
            assert notify_sock.recv(64) == b"READY=1"
            notify_sock.settimeout(5)
            assert [notify_sock.recv(64) for _ in range(2)] == [b"WATCHDOG=1"] * 2
        finally:
            stop(server)
            stop(router)

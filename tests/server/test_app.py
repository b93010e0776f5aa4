"""The composition root (``server/app.py`` :class:`MapServer`) with a real router on loopback.

It opens one Zenoh session per server, hands it to the ingest and the map service, and at
stop undeclares everything before it closes the session and then the store; a failed start
stops what already started. Sessions are spied on through the one helper that opens them.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from procs import free_port

zenoh = pytest.importorskip("zenoh")

import wardmap.server.app as app_module  # noqa: E402  (after the importorskip guard)
from wardmap.server.app import MapServer, ServerError  # noqa: E402
from wardmap.server.decoded import DecodedCache  # noqa: E402
from wardmap.server.ingest import Ingest  # noqa: E402
from wardmap.server.mapserve import MapServe  # noqa: E402
from wardmap.server.router import run_router  # noqa: E402
from wardmap.server.zenoh_session import ZenohSessionError, open_session  # noqa: E402
from wardmap.shared.errors import ConfigError  # noqa: E402
from wardmap.shared.mapwire import OBJECTS_KEY, ObjectsReply, decode_map_message  # noqa: E402
from wardmap.shared.zenoh_config import client_config  # noqa: E402

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def router() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    stop, ready = threading.Event(), threading.Event()
    worker = threading.Thread(
        target=run_router, args=([endpoint],), kwargs={"stop": stop, "on_ready": lambda _e: ready.set()},
        daemon=True,
    )
    worker.start()
    try:
        assert ready.wait(15)
        yield endpoint
    finally:
        stop.set()
        worker.join(10)


class _SpySession:
    """A real session that records when it is closed."""

    def __init__(self, real: Any, events: list[str]) -> None:
        self._real = real
        self._events = events

    def __getattr__(self, name: str) -> Any:
        return getattr(self._real, name)

    def close(self) -> None:
        self._events.append("session closed")
        self._real.close()


@pytest.fixture
def events(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """What happened, in order: sessions opened and closed, parts stopped."""
    log: list[str] = []
    sessions: list[_SpySession] = []

    def spy_open(connect: Any, options: Any = None) -> _SpySession:
        sessions.append(_SpySession(open_session(connect, options), log))
        log.append("session opened")
        return sessions[-1]

    def record_stop(cls: Any, name: str) -> None:
        real = cls.stop

        def stop(self: Any, *args: Any, **kw: Any) -> None:
            log.append(f"{name} stopped")
            real(self, *args, **kw)

        monkeypatch.setattr(cls, "stop", stop)

    monkeypatch.setattr(app_module, "open_session", spy_open)
    record_stop(Ingest, "ingest")
    record_stop(MapServe, "mapserve")
    return log


class _Backend:
    def __init__(self, events: list[str]) -> None:
        self.events = events

    def set_publish(self, publish: object) -> None:
        self.events.append("corrections wired")


class _Pipeline:
    def __init__(self, events: list[str], fail: bool = False) -> None:
        self.events, self.fail = events, fail
        self.backend = _Backend(events)
        self.decoded = DecodedCache()  # what ingest hands on

    def start(self) -> None:
        if self.fail:
            raise ConfigError("pipeline cannot start")
        self.events.append("pipeline started")

    def stop(self) -> None:
        self.events.append("pipeline stopped")

    def running(self) -> bool:
        return True


def test_one_session_shared_and_closed_last(router: str, tmp_path: Path, events: list[str]) -> None:
    """Ingest and map service run on one session; stop undeclares (pipeline, map service,
    ingest) before the session closes; a robot's query is answered meanwhile."""
    server = MapServer(f"sqlite:///{tmp_path / 'm.db'}", connect=[router],
                       pipeline_factory=lambda store, objects, decoded: _Pipeline(events))  # type: ignore[arg-type,return-value]
    services = server.start()
    assert services.ingest is not None and server.services is services
    assert events == ["session opened", "corrections wired", "pipeline started"]
    with zenoh.open(zenoh.Config.from_json5(json.dumps(client_config([router])))) as robot:
        (reply,) = list(robot.get(OBJECTS_KEY, timeout=10))
        assert isinstance(decode_map_message(reply.ok.payload.to_bytes()), ObjectsReply)
    server.stop()
    assert events[3:] == ["pipeline stopped", "mapserve stopped", "ingest stopped", "session closed"]
    server.stop()  # idempotent
    assert len(events) == 7 and server.services is None


def test_failed_start_stops_what_started(router: str, tmp_path: Path, events: list[str]) -> None:
    """A part that fails to start: what started stops again in reverse order, the session is
    closed, the error propagates, and the server can be started again."""
    fail = [True]
    server = MapServer(f"sqlite:///{tmp_path / 'm.db'}", connect=[router],
                       pipeline_factory=lambda store, objects, decoded: _Pipeline(events, fail[0]))  # type: ignore[arg-type,return-value]
    with pytest.raises(ConfigError, match="pipeline cannot start"):
        server.start()
    assert events == ["session opened", "corrections wired", "mapserve stopped", "ingest stopped",
                      "session closed"]
    assert server.services is None
    fail[0] = False
    with server, pytest.raises(ServerError, match="already started"):
        server.start()
    assert events[-1] == "session closed" and events.count("session opened") == 2


def test_no_router_no_start(tmp_path: Path, events: list[str]) -> None:
    """No router at the endpoint: a clear error, nothing left open (the store reopens)."""
    url = f"sqlite:///{tmp_path / 'm.db'}"
    with pytest.raises(ZenohSessionError, match="cannot connect to"):
        MapServer(url, connect=[f"tcp/127.0.0.1:{free_port()}"]).start()
    with MapServer(url) as server:
        assert server.services is not None and server.services.ingest is None
    assert events == []


def test_start_waits_for_a_store_that_is_unavailable(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """With ``retry_until``, a store that is unavailable at start (a database server not up yet;
    stood in for by an ``open_store`` failing twice) is tried again with a warning per attempt and
    the server starts on the third; a permanent store error is not retried; setting the event while
    it waits ends the wait with ServerError."""
    from wardmap.server.store import StoreError, StoreUnavailableError, open_store

    monkeypatch.setattr(app_module, "RETRY_FIRST_S", 0.01)
    url = f"sqlite:///{tmp_path / 'm.db'}"
    calls: list[str] = []

    def flaky(u: str, password: str | None = None) -> Any:
        calls.append(u)
        if len(calls) <= 2:
            raise StoreUnavailableError("connection refused")
        return open_store(u)

    monkeypatch.setattr(app_module, "open_store", flaky)
    with caplog.at_level("WARNING", logger="wardmap.server.app"), \
            MapServer(url, retry_until=threading.Event()) as server:
        assert server.services is not None
    waits = [r.getMessage() for r in caplog.records if "waiting for the keyframe store" in r.getMessage()]
    assert len(calls) == 3 and len(waits) == 2 and "attempt 2 failed: connection refused" in waits[1]

    def bad(u: str, password: str | None = None) -> Any:
        raise StoreError("unknown store URL")

    monkeypatch.setattr(app_module, "open_store", bad)
    with pytest.raises(StoreError, match="unknown store URL"):
        MapServer(url, retry_until=threading.Event()).start()

    gave_up = threading.Event()
    monkeypatch.setattr(app_module, "open_store", lambda u, password=None: (gave_up.set(), flaky("x"))[1])
    calls.clear()
    server = MapServer(url, retry_until=gave_up)
    with pytest.raises(ServerError, match="stopped while waiting for the keyframe store"):
        server.start()
    assert server.start_cancelled and server.services is None


def test_bad_endpoint_fails_at_construction(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="bad endpoint"):
        MapServer(f"sqlite:///{tmp_path / 'm.db'}", connect=["localhost:7447"])


def test_http_socket_sets_tcp_nodelay_on_accepted_connections() -> None:
    """The REST socket says TCP (asyncio only sets TCP_NODELAY on such sockets) and an accepted
    connection has TCP_NODELAY on: keep-alive responses do not wait on Nagle's algorithm."""
    import socket

    listener = app_module._bind("127.0.0.1", 0)
    try:
        assert listener.proto == socket.IPPROTO_TCP
        with socket.create_connection(listener.getsockname()[:2], timeout=5):
            conn, _ = listener.accept()
            with conn:
                assert conn.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0
    finally:
        listener.close()


def test_insecure_loopback_binds_only_to_loopback() -> None:
    """``loopback_only`` (``--insecure-loopback``) binds 127.0.0.1 and localhost, and refuses
    the wildcard address with a message that says why."""
    for host in ("127.0.0.1", "localhost"):
        app_module._bind(host, 0, loopback_only=True).close()
    with pytest.raises(ServerError, match=r"--insecure-loopback refused on '0\.0\.0\.0'"):
        app_module._bind("0.0.0.0", 0, loopback_only=True)
    assert app_module.is_loopback("127.0.0.1") and not app_module.is_loopback("0.0.0.0")

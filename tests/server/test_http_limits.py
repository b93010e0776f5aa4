"""The HTTP server's limits (``server/http_limits.py``) on a real ``run_server`` over loopback: a
connection that never finishes its request head is closed after the header timeout (even one
byte at a time), connections beyond the cap are closed at once while those within it are
served, keep-alive requests are answered, and repeated log records are throttled."""

from __future__ import annotations

import logging
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

import wardmap.server.http_limits as limits
from wardmap.server.http_limits import ThrottledLog

TIMEOUT_S = 20.0


@pytest.fixture
def served(router: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[str, int]]:
    """``run_server`` (insecure-loopback) with a 1 s header timeout and a cap of 4 connections;
    yields its host and port."""
    from wardmap.server.app import run_server

    monkeypatch.setattr(limits, "HEADER_TIMEOUT_S", 1.0)
    monkeypatch.setattr(limits, "MAX_CONNECTIONS", 4)
    stop, ready = threading.Event(), threading.Event()
    urls: list[str] = []
    errors: list[BaseException] = []

    def target() -> None:
        try:
            run_server([router], f"sqlite:///{tmp_path / 'm.db'}", "127.0.0.1", 0, stop=stop,
                       on_ready=lambda url: (urls.append(url), ready.set()), insecure_loopback=True)
        except BaseException as exc:  # surfaced below
            errors.append(exc)
            ready.set()

    worker = threading.Thread(target=target, daemon=True)
    worker.start()
    try:
        assert ready.wait(TIMEOUT_S) and not errors, errors
        host, port = urls[0].removeprefix("http://").rsplit(":", 1)
        yield host, int(port)
    finally:
        stop.set()
        worker.join(TIMEOUT_S)


def _closed_by_server(sock: socket.socket, timeout_s: float) -> bool:
    """Whether the server closes ``sock`` within ``timeout_s`` (reads until EOF)."""
    sock.settimeout(timeout_s)
    try:
        while sock.recv(4096):
            pass
    except TimeoutError:
        return False
    except ConnectionResetError:
        return True
    return True


def test_an_unfinished_request_head_is_closed_after_the_header_timeout(served: tuple[str, int]) -> None:
    """A client that sends half a request head, then a byte now and then, is disconnected after
    the header timeout (uvicorn's keep-alive timer alone would wait forever)."""
    with socket.create_connection(served, timeout=5) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
        sock.sendall(b"X")
        assert _closed_by_server(sock, 5.0)
    with httpx.Client(base_url=f"http://{served[0]}:{served[1]}", timeout=5) as http:
        assert [http.get("/healthz").status_code for _ in range(20)] == [200] * 20  # keep-alive


def test_connections_beyond_the_cap_are_closed_at_once(served: tuple[str, int]) -> None:
    """With 4 idle connections open a fifth is closed before it sends anything; the first four
    are still served."""
    idle = [socket.create_connection(served, timeout=5) for _ in range(4)]
    try:
        with socket.create_connection(served, timeout=5) as extra:
            assert _closed_by_server(extra, 0.9)  # well before the 1 s header timeout
        for sock in idle:
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            assert sock.recv(4096).startswith(b"HTTP/1.1 200")
    finally:
        for sock in idle:
            sock.close()


def test_throttled_log_lets_one_record_through_per_interval() -> None:
    """Per message: the first record passes without its traceback, the next ones within the
    interval are held and counted in the next record that passes; other messages pass."""
    now = [0.0]
    throttle = ThrottledLog(interval_s=10.0, clock=lambda: now[0], messages=frozenset({"boom %d"}))

    def record(msg: str, exc: BaseException | None = None) -> logging.LogRecord:
        exc_info = None if exc is None else (type(exc), exc, None)
        return logging.LogRecord("x", logging.WARNING, __file__, 1, msg, (1,), exc_info)

    first = record("boom %d", OSError(24, "Too many open files"))
    assert throttle.filter(first) and first.exc_info is None and "Too many open files" in str(first.msg)
    assert [throttle.filter(record("boom %d")) for _ in range(5)] == [False] * 5
    assert throttle.filter(record("other %d"))  # not a throttled message
    now[0] = 10.5
    later = record("boom %d")
    assert throttle.filter(later) and "(5 more like it in the last 10 s)" in str(later.msg)

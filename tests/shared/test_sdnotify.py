"""``wardmap.shared.sdnotify``: the datagram systemd's ``Type=notify`` waits for, received on a
real unix datagram socket (a path, and the abstract namespace)."""

from __future__ import annotations

import contextlib
import os
import socket
import threading
from pathlib import Path

import pytest

from wardmap.shared.sdnotify import notify, start_watchdog, watchdog_period_s


@pytest.mark.parametrize("abstract", [False, True])
def test_ready_reaches_the_notify_socket(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                         abstract: bool) -> None:
    """``READY=1`` arrives as one datagram on the socket ``NOTIFY_SOCKET`` names."""
    name = f"@wardmap-test-{os.getpid()}" if abstract else str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name[1:] if abstract else name)
        sock.settimeout(5)
        monkeypatch.setenv("NOTIFY_SOCKET", name)
        assert notify("READY=1")
        assert sock.recv(64) == b"READY=1"


def test_without_systemd_nothing_is_sent(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """No ``NOTIFY_SOCKET``: False; a socket that is gone: False, and no exception."""
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert not notify("READY=1")
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "gone"))
    assert not notify("READY=1")


def test_watchdog_pings_only_while_alive(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With ``WATCHDOG_USEC`` (100 ms: a ping every 50 ms) the thread sends ``WATCHDOG=1`` while
    ``alive()`` is true and nothing once it is false; no thread without ``WATCHDOG_USEC`` or when
    ``WATCHDOG_PID`` names another process."""
    path = str(tmp_path / "notify")
    alive = threading.Event()
    alive.set()
    stop = threading.Event()
    refused = threading.Event()  # set by the first check that says "not alive"

    def check() -> bool:
        if alive.is_set():
            return True
        refused.set()
        return False

    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(path)
        sock.settimeout(5)
        monkeypatch.setenv("NOTIFY_SOCKET", path)
        monkeypatch.setenv("WATCHDOG_USEC", "100000")
        monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
        assert watchdog_period_s() == pytest.approx(0.05)
        thread = start_watchdog(check, stop)
        assert thread is not None
        try:
            assert [sock.recv(64) for _ in range(2)] == [b"WATCHDOG=1", b"WATCHDOG=1"]
            alive.clear()
            assert refused.wait(5)  # every ping of an earlier check was sent before this one
            sock.setblocking(False)
            with contextlib.suppress(BlockingIOError):
                while sock.recv(64):
                    pass
            sock.settimeout(0.3)  # six periods
            with pytest.raises(TimeoutError):
                sock.recv(64)
        finally:
            stop.set()
            thread.join(5)
    assert not thread.is_alive()
    monkeypatch.setenv("WATCHDOG_PID", "1")
    assert watchdog_period_s() is None and start_watchdog(lambda: True) is None
    monkeypatch.delenv("WATCHDOG_USEC")
    monkeypatch.delenv("WATCHDOG_PID")
    assert watchdog_period_s() is None

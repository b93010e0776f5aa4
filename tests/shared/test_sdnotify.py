"""``wardmap.shared.sdnotify``: the datagram systemd's ``Type=notify`` waits for, received on a
real unix datagram socket (a path, and the abstract namespace)."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from wardmap.shared.sdnotify import notify


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

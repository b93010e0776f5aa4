"""Helpers for tests that run wardmap commands as real processes (shared by tests/integration)."""

from __future__ import annotations

import os
import queue
import socket
import subprocess
import threading
from typing import IO


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def child_env() -> dict[str, str]:
    """The environment for a child process: zenoh's RUST_LOG removed so stderr is wardmap's own."""
    env = dict(os.environ)
    env.pop("RUST_LOG", None)
    return env


def read_line(stream: IO[str], timeout_s: float) -> str | None:
    """The next line of ``stream``, read on a helper thread; None on timeout or EOF."""
    lines: queue.Queue[str] = queue.Queue(maxsize=1)
    threading.Thread(target=lambda: lines.put(stream.readline()), daemon=True).start()
    try:
        return lines.get(timeout=timeout_s) or None
    except queue.Empty:
        return None


def stop(proc: subprocess.Popen[str], timeout_s: float = 15.0) -> None:
    """Terminate ``proc`` if it still runs; kill it if it ignores SIGTERM; close its pipes."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
    for stream in (proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()


def wardmap(*args: str, timeout_s: float = 300.0) -> subprocess.CompletedProcess[str]:
    """Run ``python -m wardmap.cli ARGS`` to completion, text output captured."""
    import sys

    return subprocess.run(
        [sys.executable, "-m", "wardmap.cli", *args], capture_output=True, text=True, timeout=timeout_s
    )


def one_line_error(p: subprocess.CompletedProcess[str], needle: str, command: str | None = None) -> None:
    """Exit code 1, no traceback, exactly one stderr line containing ``needle`` (and starting
    with ``wardmap COMMAND: error:`` when ``command`` is given)."""
    assert p.returncode == 1, p.stderr
    assert "Traceback" not in p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, p.stderr
    if command is not None:
        assert lines[0].startswith(f"wardmap {command}: error:"), lines[0]
    assert needle in lines[0], lines[0]

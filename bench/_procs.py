"""Real ``wardmap`` processes for the benchmarks: a free port, start and wait for the ready line, stop."""

from __future__ import annotations

import os
import socket
import subprocess
import sys


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start(args: list[str], expect: str) -> subprocess.Popen[str]:
    """Start ``wardmap ARGS`` and wait for its ready line ``expect`` (exit on any other line)."""
    env = {k: v for k, v in os.environ.items() if k != "RUST_LOG"}
    proc = subprocess.Popen([sys.executable, "-m", "wardmap.cli", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, env=env)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if line.strip() != expect:
        proc.kill()
        raise SystemExit(f"{' '.join(args)}: not ready ({line!r})")
    return proc


def stop(proc: subprocess.Popen[str], timeout_s: float = 15.0) -> None:
    """SIGTERM ``proc`` if it runs; SIGKILL it after ``timeout_s``."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)

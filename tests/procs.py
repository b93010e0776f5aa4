"""Helpers for tests that run wardmap commands as real processes (shared by tests/integration)
and read what they answer."""

from __future__ import annotations

import json
import os
import queue
import shlex
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import pytest


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def child_env() -> dict[str, str]:
    """The environment for a child process: zenoh's RUST_LOG removed so stderr is wardmap's own;
    Python's fault handler on, so a crash (e.g. an abort in a native thread) leaves every
    thread's stack on stderr for :func:`assert_stops_cleanly` to show."""
    env = dict(os.environ)
    env.pop("RUST_LOG", None)
    env["PYTHONFAULTHANDLER"] = "1"
    return env


def read_line(stream: IO[str], timeout_s: float) -> str | None:
    """The next line of ``stream``, read on a helper thread; None on timeout or EOF."""
    lines: queue.Queue[str] = queue.Queue(maxsize=1)
    threading.Thread(target=lambda: lines.put(stream.readline()), daemon=True).start()
    try:
        return lines.get(timeout=timeout_s) or None
    except queue.Empty:
        return None


def start(cmd: list[str], expect: str, timeout_s: float) -> subprocess.Popen[str]:
    """Start ``cmd`` (stdout and stderr piped, :func:`child_env`) and wait up to ``timeout_s`` for
    its ready line ``expect``; on another line, EOF or timeout kill it and fail the test with
    its stderr."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=child_env())
    assert proc.stdout is not None
    line = read_line(proc.stdout, timeout_s)
    if line is None or line.strip() != expect:
        proc.kill()
        _, err = proc.communicate(timeout=5)
        pytest.fail(f"{shlex.join(cmd)} not ready within {timeout_s} s ({line!r}); stderr: {err[-2000:]!r}")
    return proc


def sigkill_after(cmd: list[str], n: int) -> tuple[list[int], int]:
    """Run ``cmd``, a child that prints one integer per committed write, and SIGKILL it once it
    has printed ``n``. Returns every integer it printed (any after the ``n``-th included) and its
    exit code; fails the test if it exits before printing ``n``."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    reported: list[int] = []
    try:
        while len(reported) < n:
            line = proc.stdout.readline()
            if not line:
                pytest.fail(f"child exited early: {proc.wait()} {proc.stderr.read() if proc.stderr else ''}")
            reported.append(int(line))
        os.kill(proc.pid, signal.SIGKILL)
        reported += [int(ln) for ln in proc.stdout.read().split()]
    finally:
        proc.kill()
        proc.wait()
        proc.stdout.close()
        if proc.stderr is not None:
            proc.stderr.close()
    return reported, proc.returncode


@contextmanager
def router_process(timeout_s: float) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """A ``wardmap router`` subprocess on a free loopback port, once its ready line came (within
    ``timeout_s``); yields it and its endpoint ``tcp/127.0.0.1:PORT``, stops it on exit."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = start(wardmap_cmd("router", "--listen", endpoint), f"router listening on {endpoint}", timeout_s)
    try:
        yield proc, endpoint
    finally:
        stop(proc)


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


def wardmap_cmd(*args: str) -> list[str]:
    """The command line ``python -m wardmap.cli ARGS`` (this interpreter)."""
    return [sys.executable, "-m", "wardmap.cli", *args]


def wardmap(*args: str, timeout_s: float = 300.0) -> subprocess.CompletedProcess[str]:
    """Run ``python -m wardmap.cli ARGS`` to completion, text output captured."""
    return subprocess.run(wardmap_cmd(*args), capture_output=True, text=True, timeout=timeout_s)


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


def prometheus_samples(text: str) -> dict[str, float]:
    """The samples of a Prometheus text exposition (``GET /metrics``): ``name{labels}`` -> value."""
    out = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            out[name] = float(value)
    return out


@dataclass
class Proc:
    """A subprocess whose stderr goes to a file (a full pipe must never block it)."""

    popen: subprocess.Popen[str]
    stderr_path: Path

    def stderr(self) -> str:
        return self.stderr_path.read_text(errors="replace")


def spawn_logged(cmd: list[str], log_dir: Path, name: str) -> Proc:
    """Start ``cmd`` with :func:`child_env`, stdout piped, stderr to a file in ``log_dir``."""
    err_path = log_dir / f"{name}.{time.monotonic_ns()}.stderr"
    with err_path.open("w") as err:
        popen = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True, env=child_env())
    return Proc(popen, err_path)


def kill_proc(proc: Proc) -> None:
    """SIGKILL ``proc`` if it still runs, and close its stdout."""
    if proc.popen.poll() is None:
        proc.popen.kill()
        proc.popen.wait(timeout=10)
    if proc.popen.stdout is not None:
        proc.popen.stdout.close()


def stop_proc(proc: Proc, timeout_s: float = 15.0) -> int:
    """SIGTERM ``proc`` if it still runs (SIGKILL if it ignores it); its exit code."""
    if proc.popen.poll() is None:
        proc.popen.terminate()
        try:
            proc.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.popen.kill()
            proc.popen.wait(timeout=5)
    if proc.popen.stdout is not None:
        proc.popen.stdout.close()
    return int(proc.popen.returncode)


def assert_stops_cleanly(proc: Proc, timeout_s: float = 15.0) -> None:
    """:func:`stop_proc`, then fail with the end of its stderr unless it exited 0."""
    code = stop_proc(proc, timeout_s)
    assert code == 0, f"exit code {code}; stderr ends: {proc.stderr()[-3000:]!r}"


def edge_summary(proc: Proc, timeout_s: float) -> dict[str, Any]:
    """Wait for a ``wardmap edge`` whose ready line was read to finish on its own; its JSON
    summary, the one line left on its stdout. Fails the test on a timeout, an exit code other
    than 0 or a traceback."""
    try:
        out, _ = proc.popen.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        kill_proc(proc)
        pytest.fail(f"edge did not finish within {timeout_s} s; stderr: {proc.stderr()[-2000:]!r}")
    assert proc.popen.returncode == 0, proc.stderr()[-2000:]
    assert "Traceback" not in proc.stderr()
    lines = out.strip().splitlines()
    assert len(lines) == 1, out
    summary: dict[str, Any] = json.loads(lines[0])
    return summary

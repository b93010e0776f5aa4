"""``wardmap edge`` as a process: a real router subprocess, the agent as a subprocess, and a tiny
acker (``peers.Acker``, a zenoh client in the test process that stands in for the server's
ingest). Tests of the agent in this process: tests/edge/test_agent.py.

Every session is a client with shared memory and multicast scouting off, connected to the
router on 127.0.0.1; the tests wait on the router's ready line, the agent's stdout,
heartbeats and threading events, never on sleeps.
"""

from __future__ import annotations

import contextlib
import json
import queue
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from peers import Acker, open_client
from procs import child_env as _env
from procs import read_line as _read_line
from procs import router_process, wardmap_cmd
from procs import stop as _stop

pytest.importorskip("zenoh")

from wardmap.edge.outbox import Outbox
from wardmap.shared.wire import decode_heartbeat
from wardmap.shared.zenoh_config import heartbeat_key

pytestmark = [pytest.mark.integration, pytest.mark.timeout(90)]

READY_TIMEOUT_S = 15.0
EVENT_TIMEOUT_S = 20.0
RUN_TIMEOUT_S = 60.0
OUTBOX_FILE = "outbox.sqlite"


def _edge_cmd(*args: str) -> list[str]:
    return wardmap_cmd("edge", "--privacy", "off", *args)  # privacy: tests/edge/test_privacy.py


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 40-frame simulated sequence (aisle_slow_1, seed 0), generated once."""
    from wardmap.sim.runner import generate

    path = tmp_path_factory.mktemp("edge") / "aisle"
    generate("aisle_slow_1", 0, path, frames=40)
    return path


@pytest.fixture(scope="module")
def router() -> Iterator[str]:
    """A ``wardmap router`` subprocess on a free loopback port, after its ready line; yields its endpoint."""
    with router_process(READY_TIMEOUT_S) as (_, endpoint):
        yield endpoint


def _summary(stdout: str) -> dict[str, Any]:
    lines = stdout.strip().splitlines()
    assert len(lines) == 2, stdout  # the ready line and the summary line
    assert lines[0].startswith("edge ") and " ready: session " in lines[0]
    assert lines[0].endswith("people in images: NOT REDACTED (privacy off)")  # said loudly
    summary: dict[str, Any] = json.loads(lines[1])
    return summary


def _outbox_keys(path: Path) -> list[tuple[str, str, int]]:
    with Outbox.open(path) as outbox:
        return [item.key for item in outbox.pending(10_000)]


def test_edge_sends_every_keyframe_and_outbox_ends_empty(dataset: Path, router: str, tmp_path: Path) -> None:
    """The whole 40-frame data set: every keyframe reaches the acker, is acked, the outbox ends empty."""
    outbox_dir = tmp_path / "outbox"
    with Acker(router) as acker:
        args = ("--robot", "r1", "--source", str(dataset), "--connect", router, "--outbox", str(outbox_dir))
        done = subprocess.run(
            _edge_cmd(*args),
            capture_output=True,
            text=True,
            timeout=RUN_TIMEOUT_S,
            env=_env(),
        )
        assert done.returncode == 0, done.stderr
        assert "Traceback" not in done.stderr
        # The simulated data set says it is a global shutter, and the edge says which model it uses.
        assert "edge r1 rolling-shutter readout: 0.0 ms (the calibration's [rgb] readout_s)" in done.stderr
        summary = _summary(done.stdout)
        session = summary["session_id"]
        expected = {(session, seq) for seq in range(summary["keyframes"])}
        assert acker.keys() >= expected  # every keyframe arrived (the agent waited for their acks)
    assert summary["frames"] == 40
    assert summary["keyframes"] >= 2
    assert summary["acked"] == summary["keyframes"]
    assert summary["pending"] == 0 and summary["flushed"] is True
    assert summary["rejected"] == {}
    assert {k for k in acker.keys() if k[0] == session} == expected  # noqa: SIM118 (a method, not a dict)
    assert _outbox_keys(outbox_dir / OUTBOX_FILE) == []
    # Every keyframe was sent once and acked: one latency sample each, publish -> ack.
    latency = summary["latency_ms"]
    assert latency["n"] == summary["keyframes"]
    assert 0 < latency["p50"] <= latency["p99"] <= latency["max"] < RUN_TIMEOUT_S * 1e3
    assert 0 < summary["bytes_per_keyframe"] <= 100_000  # the default size budget (docs/wire.md)


def test_edge_sim_source_renders_live_and_delivers(router: str, tmp_path: Path) -> None:
    """``--source sim:SCENARIO:SEED`` renders frames in the agent; keyframes carry the
    tracker's keypoints (at most max_keypoints) and arrive like a data set's."""
    outbox_dir = tmp_path / "outbox"
    with Acker(router) as acker:
        args = ("--robot", "r5", "--source", "sim:aisle_slow_1:0", "--connect", router,
                "--outbox", str(outbox_dir), "--max-frames", "12", "--labels", "oracle")
        done = subprocess.run(
            _edge_cmd(*args), capture_output=True, text=True, timeout=RUN_TIMEOUT_S, env=_env()
        )
        assert done.returncode == 0, done.stderr
        summary = _summary(done.stdout)
        expected = {(summary["session_id"], seq) for seq in range(summary["keyframes"])}
        assert acker.wait_for(expected, EVENT_TIMEOUT_S)
    assert summary["frames"] == 12 and summary["keyframes"] >= 2
    assert summary["acked"] == summary["keyframes"] and summary["pending"] == 0
    assert summary["thermal_keyframes"] >= 1  # the first keyframe always carries thermal


def test_edge_resumes_unacked_keyframes_after_sigterm(dataset: Path, router: str, tmp_path: Path) -> None:
    """No acker: keyframes stay in the outbox across SIGTERM; the next start re-sends them
    with their original (session, seq) and they are acked."""
    outbox_dir = tmp_path / "outbox"
    config = tmp_path / "edge.toml"
    config.write_text("[agent]\nflush_timeout_s = 1.0\nresend_after_s = 1.0\n")
    heartbeats: queue.Queue[bytes] = queue.Queue(maxsize=64)
    base = ("--robot", "r2", "--source", str(dataset), "--connect", router, "--outbox", str(outbox_dir))

    def on_heartbeat(sample: Any) -> None:
        with contextlib.suppress(queue.Full):  # drop-newest: the test only needs a recent one
            heartbeats.put_nowait(sample.payload.to_bytes())

    with open_client(router) as watcher, watcher.declare_subscriber(heartbeat_key("r2"), on_heartbeat):
        proc = subprocess.Popen(
            _edge_cmd(*base, "--rate", "10", "--config", str(config)),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=_env(),
        )
        try:
            assert proc.stdout is not None
            ready = _read_line(proc.stdout, READY_TIMEOUT_S)
            assert ready is not None and " ready: session " in ready
            while True:  # until a heartbeat reports at least two keyframes in the outbox
                hb = decode_heartbeat(heartbeats.get(timeout=EVENT_TIMEOUT_S))
                if hb.stats["keyframes"] >= 2 and hb.stats["pending"] >= 2:
                    break
            proc.send_signal(signal.SIGTERM)
            out, err = proc.communicate(timeout=RUN_TIMEOUT_S)
        finally:
            _stop(proc)
    assert proc.returncode == 0, err
    first = json.loads(out.strip().splitlines()[-1])
    assert first["frames"] < 40  # stopped by SIGTERM, not by the end of the data set
    assert first["acked"] == 0 and first["pending"] >= 2 and first["flushed"] is False
    old = _outbox_keys(outbox_dir / OUTBOX_FILE)
    assert len(old) == first["pending"]
    assert {(r, s) for r, s, _ in old} == {("r2", first["session_id"])}
    assert [seq for _, _, seq in old] == list(range(len(old)))

    with Acker(router) as acker:
        cmd = _edge_cmd(*base, "--max-frames", "1")
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=RUN_TIMEOUT_S, env=_env())
        assert done.returncode == 0, done.stderr
        second = _summary(done.stdout)
        assert acker.wait_for({(sid, seq) for _, sid, seq in old}, EVENT_TIMEOUT_S)
    assert second["session_id"] != first["session_id"]
    assert second["frames"] == 1
    assert second["resent"] >= len(old)  # attempts persist: the old items were sent by the first run
    assert second["acked"] == len(old) + second["keyframes"]
    assert second["pending"] == 0 and second["flushed"] is True
    assert _outbox_keys(outbox_dir / OUTBOX_FILE) == []


@pytest.mark.parametrize(
    ("robot", "source", "connect", "needle"),
    [
        ("r1", "{missing}", "tcp/127.0.0.1:7447", "is not a folder"),
        ("r1", "{dataset}", "tcp/nohost", "bad endpoint"),
        ("bad id!", "{dataset}", "tcp/127.0.0.1:7447", "bad robot id"),
        ("r1", "sim:no_such_scene", "tcp/127.0.0.1:7447", "unknown scenario"),
        ("r1", "sim:two_robots:0:robot_9", "tcp/127.0.0.1:7447", "has no robot"),
        ("r1", "sim:aisle_slow_1:x", "tcp/127.0.0.1:7447", "bad simulated source"),
    ],
)
def test_edge_bad_inputs_exit_1_with_one_line(
    dataset: Path, tmp_path: Path, robot: str, source: str, connect: str, needle: str
) -> None:
    """Bad robot id, endpoint or source: exit 1, one stderr line, nothing on stdout, no outbox made."""
    src = source.format(missing=tmp_path / "nope", dataset=dataset)
    outbox_dir = tmp_path / "outbox"
    done = subprocess.run(
        _edge_cmd("--robot", robot, "--source", src, "--connect", connect, "--outbox", str(outbox_dir)),
        capture_output=True,
        text=True,
        timeout=30,
        env=_env(),
    )
    assert done.returncode == 1
    assert done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith("wardmap edge: error:") and needle in lines[0]
    assert not outbox_dir.exists()

"""``wardmap edge --metrics-port`` as a process: a ``wardmap router`` subprocess, an acker in this
process standing in for the server (``peers.Acker``), and the agent's ``/metrics`` scraped over
HTTP while it runs, then SIGTERM. The metrics themselves: tests/edge/test_metrics.py."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from peers import Acker
from procs import free_port, prometheus_samples, router_process, spawn_logged, stop_proc, wardmap_cmd

pytest.importorskip("zenoh")

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]


@pytest.fixture
def router() -> Iterator[str]:
    with router_process(30.0) as (_, endpoint):
        yield endpoint


def test_edge_serves_its_metrics_while_it_runs(router: str, tmp_path: Path) -> None:
    """A simulated robot at 5 Hz with ``--metrics-port``: its stderr names the URL; the scrape
    (polled every 0.2 s, the event under test) shows tracked frames and acked keyframes' latency
    growing; SIGTERM exits 0 and the port is closed."""
    port = free_port()
    url = f"http://127.0.0.1:{port}/metrics"
    cmd = wardmap_cmd("edge", "--robot", "r7", "--source", "sim:aisle_slow_1:0", "--connect", router,
                      "--outbox", str(tmp_path / "outbox"), "--rate", "5", "--metrics-port", str(port),
                      "--metrics-host", "127.0.0.1", "--privacy", "off")
    with Acker(router):
        edge = spawn_logged(cmd, tmp_path, "edge")
        try:
            deadline = time.monotonic() + 120
            samples: dict[str, float] = {}
            while samples.get("wardmap_edge_ack_seconds_count", 0) < 2:
                assert time.monotonic() < deadline, edge.stderr()[-2000:]
                assert edge.popen.poll() is None, edge.stderr()[-2000:]
                with contextlib.suppress(httpx.TransportError):  # not listening yet
                    samples = prometheus_samples(httpx.get(url, timeout=5).text)
                time.sleep(0.2)
            assert f"edge r7 metrics: http://127.0.0.1:{port}/metrics" in edge.stderr()
            assert samples['wardmap_edge_frames_total{result="tracked"}'] >= 2
            assert samples['wardmap_edge_info{robot="r7"}'] == 1
            assert "wardmap_edge_outbox_depth" in samples
        finally:
            assert stop_proc(edge, timeout_s=30) == 0, edge.stderr()[-2000:]
    with pytest.raises(httpx.TransportError):
        httpx.get(url, timeout=2)

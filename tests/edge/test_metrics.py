"""The edge agent's Prometheus metrics (``wardmap.edge.metrics``): served over real HTTP by
``prometheus_client``'s exporter, and recorded by a real agent run against a router on a thread
with an acker standing in for the server (``peers``)."""

from __future__ import annotations

import socket
from pathlib import Path

import httpx
import pytest
from procs import prometheus_samples

from wardmap.edge.agent import AgentConfig, EdgeAgent
from wardmap.edge.metrics import EdgeMetrics
from wardmap.shared.errors import ConfigError, WardmapError


def test_metrics_are_served_and_the_port_is_released() -> None:
    """Frames, outbox depth and ack latency show at ``/metrics`` while served; the port is free
    again after the block; a taken port and a bad one are one clear error each."""
    m = EdgeMetrics("r1")
    m.frame(lost=False)
    m.frame(lost=False)
    m.frame(lost=True)
    m.outbox_depth.set(7)
    m.ack_seconds.observe(0.02)
    with m.serve(0, "127.0.0.1") as url:
        samples = prometheus_samples(httpx.get(f"{url}/metrics", timeout=5).text)
        port = int(url.rsplit(":", 1)[1])
        with pytest.raises(WardmapError, match="cannot serve metrics"), m.serve(port, "127.0.0.1"):
            pass
    assert samples['wardmap_edge_frames_total{result="tracked"}'] == 2
    assert samples['wardmap_edge_frames_total{result="lost"}'] == 1
    assert samples["wardmap_edge_outbox_depth"] == 7
    assert samples["wardmap_edge_ack_seconds_count"] == 1
    assert samples['wardmap_edge_info{robot="r1"}'] == 1
    with socket.socket() as s:  # released: a new listener may bind it (as servers do, reusing the address)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))
        s.listen()
    with pytest.raises(ConfigError, match="bad metrics port"), m.serve(70000):
        pass


@pytest.mark.timeout(120)
def test_an_agent_run_records_frames_and_ack_latency(tmp_path: Path) -> None:
    """Four simulated frames (aisle_slow_1, seed 0), every keyframe acked ``stored``: the frame
    counters add up to the frames tracked, one latency per acked keyframe, the outbox ends empty."""
    pytest.importorskip("zenoh")
    from peers import Acker, router_on_thread

    from wardmap.sim.live import LiveRun

    metrics = EdgeMetrics("r1")
    config = AgentConfig(max_frames=4, flush_timeout_s=20.0, heartbeat_period_s=0.05, privacy="off")
    with router_on_thread() as endpoint, Acker(endpoint, "stored") as _:
        summary = EdgeAgent("r1", LiveRun("aisle_slow_1", 0), [endpoint], tmp_path / "outbox.sqlite",
                            config=config, metrics=metrics).run()
    frames = {s.labels["result"]: s.value for fam in metrics.frames.collect() for s in fam.samples
              if s.name.endswith("_total")}
    assert frames["tracked"] + frames["lost"] == summary["frames"] == 4
    assert frames["lost"] == summary["lost_frames"]
    (count,) = [s.value for fam in metrics.ack_seconds.collect() for s in fam.samples
                if s.name.endswith("_count")]
    assert count == summary["acked"] == summary["keyframes"] >= 1

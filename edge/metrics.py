"""The edge agent's own Prometheus metrics, served on an optional port (``wardmap edge
--metrics-port N``; off by default).

What a robot's operator wants to see without the server: frames tracked and frames whose
tracking was lost, the outbox depth (keyframes stored on the robot and not acked yet), and the
publish -> ack latency (first publish of a keyframe to its ``stored``/``duplicate`` ack: the
network, the server's commit and the way back). The agent records into one :class:`EdgeMetrics`
(thread safe: ``prometheus_client``'s metric objects are); :meth:`EdgeMetrics.serve` runs
``prometheus_client``'s own HTTP exporter on a thread of its own. The metrics live on a registry
of their own, never the process-global one.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, start_http_server

from wardmap.shared.errors import ConfigError, WardmapError

__all__ = ["ACK_BUCKETS_S", "EdgeMetrics"]

ACK_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)
"""Histogram buckets of the publish -> ack latency (seconds); an outage shows up in the top ones."""


class EdgeMetrics:
    """The metrics of one edge agent; see the module docstring."""

    def __init__(self, robot_id: str) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.frames = Counter("wardmap_edge_frames", "Frames tracked (result=tracked) or with tracking lost "
                              "(result=lost; no pose, no keyframe).", ["result"], registry=self.registry)
        self.outbox_depth = Gauge("wardmap_edge_outbox_depth",
                                  "Keyframes in the outbox not acked yet (updated each heartbeat period).",
                                  registry=self.registry)
        self.ack_seconds = Histogram("wardmap_edge_ack_seconds",
                                     "First publish of a keyframe to its stored/duplicate ack, seconds.",
                                     buckets=ACK_BUCKETS_S, registry=self.registry)
        self.robot = Gauge("wardmap_edge_info", "Always 1; the robot this agent runs.", ["robot"],
                           registry=self.registry)
        self.robot.labels(robot=robot_id).set(1)
        for result in ("tracked", "lost"):
            self.frames.labels(result=result)

    def frame(self, lost: bool) -> None:
        """Count one frame the tracker processed."""
        self.frames.labels(result="lost" if lost else "tracked").inc()

    @contextlib.contextmanager
    def serve(self, port: int, host: str = "0.0.0.0") -> Iterator[str]:
        """Serve ``GET /metrics`` on ``host:port`` (port 0: any free port) until the block ends;
        yields ``http://HOST:PORT``.

        Raises:
            ConfigError: a port outside 0..65535.
            WardmapError: the port cannot be bound (e.g. in use).
        """
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise ConfigError(f"bad metrics port {port!r}: expected 0..65535")
        try:
            server, thread = start_http_server(port, addr=host, registry=self.registry)
        except OSError as exc:
            raise WardmapError(f"cannot serve metrics on {host}:{port}: {exc.strerror or exc}") from exc
        try:
            yield f"http://{host}:{server.server_port}"
        finally:
            server.shutdown()
            server.server_close()
            thread.join(5.0)

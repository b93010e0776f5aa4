"""The server's latency histograms, per-robot series and build info (``prometheus_client``).

The counters of ``api/prometheus.py`` are read from their owners at scrape time; what this
module holds is observed as it happens: how long a keyframe took to decode and store, its ack
to publish, each mapping stage per keyframe, each REST route per request, and when each robot
was last heard from. One :class:`ServerTelemetry` per server process (the composition root
builds it and hands it to ingest, the mapping stage and the app); its metric objects belong to
no registry until :meth:`ServerTelemetry.register` puts them on the app's own one, so two
servers in one process (tests) never share series.

Every metric object of ``prometheus_client`` is thread safe; the recording methods may be
called from any thread. Units: seconds (histograms, last-seen as unix time).
"""

from __future__ import annotations

import platform
import subprocess
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, Info

__all__ = ["LATENCY_BUCKETS_S", "MAPPING_STAGES", "ServerTelemetry", "build_info"]

LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
"""Histogram buckets (seconds): 1 ms (an ack) to 30 s (a rebuild of a large map)."""

MAPPING_STAGES = ("backend", "perception", "association", "rebuild")
"""Values of the ``stage`` label of ``wardmap_mapping_stage_seconds``."""

KEYFRAME_RESULTS = ("stored", "duplicate", "retry", "rejected")
"""Values of the ``result`` label of ``wardmap_robot_keyframes_total`` (the ack's status)."""


def build_info() -> dict[str, str]:
    """``version`` (the installed package's), ``git`` (``git describe --always --dirty`` of the
    source tree when it is a git checkout, else ``unknown``) and ``python`` (e.g. ``3.11.7``)."""
    try:
        pkg = version("wardmap")
    except PackageNotFoundError:
        pkg = "unknown"
    return {"version": pkg, "git": _git_describe(Path(__file__).resolve().parents[1]),
            "python": platform.python_version()}


def _git_describe(folder: Path) -> str:
    if not (folder / ".git").exists():  # an installed wheel: no history to describe
        return "unknown"
    try:
        out = subprocess.run(["git", "-C", str(folder), "describe", "--always", "--dirty"],
                             capture_output=True, text=True, timeout=2, check=False)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (out.stdout.strip() or "unknown") if out.returncode == 0 else "unknown"


class ServerTelemetry:
    """The observed metrics of one server process; see the module docstring."""

    def __init__(self) -> None:
        self.ingest_seconds = Histogram(
            "wardmap_ingest_seconds", "Time to decode, validate and store one keyframe (commit included).",
            buckets=LATENCY_BUCKETS_S, registry=None)
        self.ack_seconds = Histogram(
            "wardmap_ack_seconds", "Time to publish one ack on zenoh (after the commit).",
            buckets=LATENCY_BUCKETS_S, registry=None)
        self.mapping_seconds = Histogram(
            "wardmap_mapping_stage_seconds",
            "Time of one mapping step: backend (one keyframe into the pose graph), perception (one "
            "keyframe measured), association (one keyframe associated), rebuild (the whole object map).",
            ["stage"], buckets=LATENCY_BUCKETS_S, registry=None)
        self.rest_seconds = Histogram(
            "wardmap_http_request_seconds", "REST API request time by method and route template.",
            ["method", "route"], buckets=LATENCY_BUCKETS_S, registry=None)
        self.robot_last_seen = Gauge(
            "wardmap_robot_last_seen_seconds", "Unix time of the last keyframe received from each robot.",
            ["robot"], registry=None)
        self.robot_keyframes = Counter(
            "wardmap_robot_keyframes", "Keyframes received from each robot, by the status they were acked.",
            ["robot", "result"], registry=None)
        self.images_erased = Counter(
            "wardmap_images_erased", "Keyframe images erased by the retention job ([store] image_retention).",
            registry=None)
        self.image_retention_failures = Counter(
            "wardmap_image_retention_failures", "Runs of the image retention job the store failed.",
            registry=None)
        self.build = Info("wardmap_build", "The running server: package version, git describe, python.",
                          registry=None)

    def register(self, registry: CollectorRegistry) -> None:
        """Put every metric on ``registry`` (once per registry) and fill the build info."""
        self.build.info(build_info())
        for metric in (self.ingest_seconds, self.ack_seconds, self.mapping_seconds, self.rest_seconds,
                       self.robot_last_seen, self.robot_keyframes, self.images_erased,
                       self.image_retention_failures, self.build):
            registry.register(metric)

    def keyframe(self, robot_id: str, result: str, unix_s: float) -> None:
        """Count one keyframe of ``robot_id`` acked ``result`` and note when it came (unix seconds)."""
        self.robot_keyframes.labels(robot=robot_id, result=result).inc()
        self.robot_last_seen.labels(robot=robot_id).set(unix_s)

    def mapping(self, stage: str, seconds: float) -> None:
        """Observe one step of mapping ``stage`` (one of :data:`MAPPING_STAGES`)."""
        self.mapping_seconds.labels(stage=stage).observe(seconds)

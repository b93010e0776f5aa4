"""The server's counters in Prometheus form (``GET /metrics``), written by ``prometheus_client``.

:class:`ServerCollector` is a custom collector: it holds no metric objects of its own, and at
each scrape it reads the counters of the parts that own them (ingest, store, object map,
mapping stage) and yields them as metric families. Each app registers it on its own
:class:`~prometheus_client.CollectorRegistry` (:func:`metrics_registry`), never on the
process-global one, so two apps in one process (tests) never share or clash.

The metric names, types, help texts and labels are the server's public interface
(dashboards, alerts); they are listed once, in the ``*_metrics`` functions below.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping

from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, InfoMetricFamily, Metric
from prometheus_client.exposition import generate_latest
from prometheus_client.registry import Collector

from wardmap.server.backend.stage import BackendCounters
from wardmap.server.decoded import DecodedCounters
from wardmap.server.ingest import Ingest, IngestCounters
from wardmap.server.mapping import MapPipeline, PipelineCounters
from wardmap.server.mapping.role import LeaseState, MappingRole
from wardmap.server.mapping.workers import PerceptionWorkers, WorkerCounters
from wardmap.server.objectmap import ObjectMap
from wardmap.server.perception.measure import SKIP_KINDS
from wardmap.server.store import KeyframeStore

__all__ = [
    "CONTENT_TYPE",
    "ServerCollector",
    "exposition",
    "ingest_metrics",
    "lease_metrics",
    "map_metrics",
    "metrics_registry",
    "pipeline_metrics",
    "worker_metrics",
]

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
"""The Prometheus text format 0.0.4, which every Prometheus server reads."""


def _counter(name: str, help_text: str, value: float) -> CounterMetricFamily:
    return CounterMetricFamily(name, help_text, value=value)


def _gauge(name: str, help_text: str, value: float) -> GaugeMetricFamily:
    return GaugeMetricFamily(name, help_text, value=value)


def _by(label: str, family: type[CounterMetricFamily | GaugeMetricFamily], name: str, help_text: str,
        samples: Iterable[tuple[str, float]]) -> Metric:
    """A family with one sample per value of ``label``."""
    out = family(name, help_text, labels=[label])
    for value, n in samples:
        out.add_metric([value], n)
    return out


def ingest_metrics(c: IngestCounters | None, rejections: Mapping[str, int], robots: int) -> list[Metric]:
    """The ingest's counters (zeros without an ingest), the rejection counts by reason (stored
    and not yet written, each once), and the robots with a stored keyframe."""
    c = c or IngestCounters(0, 0, 0, 0, 0, 0)
    return [
        _counter("wardmap_keyframes_received_total",
                 "Keyframe samples taken from zenoh by this server process.", c.received),
        _counter("wardmap_keyframes_stored_total",
                 "Keyframes newly stored by this server process.", c.stored),
        _counter("wardmap_keyframes_duplicates_total",
                 "Keyframes received again after they were stored (acked duplicate).", c.duplicates),
        _by("reason", CounterMetricFamily, "wardmap_rejections_total",
            "Rejected samples by reason, persistent in the store.", sorted(rejections.items())),
        _gauge("wardmap_ingest_queue_depth",
               "Samples taken from the zenoh channel and not yet processed.", c.queue_depth),
        _counter("wardmap_ack_failures_total", "Acks that could not be published.", c.ack_failures),
        _counter("wardmap_keyframes_retry_later_total",
                 "Valid keyframes the store could not take now (acked retry; the robot resends).",
                 c.retry_later),
        _gauge("wardmap_robots", "Robots with at least one stored keyframe.", robots),
    ]


def map_metrics(confirmed: int, unconfirmed: int) -> list[Metric]:
    """The objects in the map, confirmed or not."""
    return [_by("confirmed", GaugeMetricFamily, "wardmap_map_objects",
                'Objects in the map; confirmed="false": kept, left out of queries.',
                [("true", confirmed), ("false", unconfirmed)])]


def lease_metrics(lease: LeaseState) -> list[Metric]:
    """Whether this server holds the writer lease (runs the mapping stage), and who does."""
    holder = InfoMetricFamily("wardmap_mapping_writer",
                              "The server holding the writer lease (runs the mapping stage), as this "
                              "server last saw it; absent when nobody holds it.", labels=["server"])
    if lease.holder is not None:
        holder.add_metric([lease.name], {"holder": lease.holder})
    return [
        _gauge("wardmap_mapping_lease_held",
               "1 when this server holds the writer lease and runs the mapping stage, 0 on a standby.",
               int(lease.held)),
        holder,
    ]


def pipeline_metrics(c: PipelineCounters) -> list[Metric]:
    """The mapping stage's counters."""
    return [
        _gauge("wardmap_mapping_backlog", "Stored keyframes the mapping stage has not processed yet.",
               c.backlog),
        _counter("wardmap_mapping_keyframes_total",
                 "Measured keyframes the mapping stage took in (measured by it or by a perception worker).",
                 c.processed),
        _counter("wardmap_mapping_measurements_total", "Object measurements stored by this process.",
                 c.measurements),
        _counter("wardmap_mapping_associated_total", "Keyframes fed to association (sessions on the map).",
                 c.mapped),
        _counter("wardmap_mapping_unanchored_total",
                 "Keyframes of sessions without T_map_odom: measured, not mapped.", c.unanchored),
        _by("reason", CounterMetricFamily, "wardmap_mapping_failures_total",
            "Keyframes perception skipped, by error type.", sorted(c.failures.items())),
        _gauge("wardmap_mapping_landmarks", "Landmarks the associator holds.", c.landmarks),
        _counter("wardmap_mapping_restarts_total",
                 "Unexpected errors the mapping stage recovered from (see the server log).", c.restarts),
        _counter("wardmap_mapping_idle_sessions_closed_total",
                 "Sessions whose last keyframe group was mapped because they went quiet (close_idle_s).",
                 c.closed_idle),
        _counter("wardmap_mapping_floating_left_out_total",
                 "Instances perception left out for floating above the floor (perception.floor_gap_m).",
                 c.floating),
        _counter("wardmap_mapping_wall_pieces_left_out_total",
                 "Instances perception left out for lying on a surface taller than any object of their class "
                 "(perception.max_top_m).", c.wall_pieces),
        _counter("wardmap_mapping_floor_pieces_left_out_total",
                 "Instances perception left out for lying flat on the floor, lower than any object of their "
                 "class (perception.min_top_m).", c.floor_pieces),
        _counter("wardmap_mapping_beyond_range_total",
                 "Stored measurements association left out for lying beyond association.max_range_m.",
                 c.beyond_range),
        _by("kind", CounterMetricFamily, "wardmap_mapping_instances_skipped_total",
            "Instances perception found but could not measure (stored keyframes), by kind.",
            [(k, c.skipped.get(k, 0)) for k in SKIP_KINDS]),
        _counter("wardmap_mapping_rebuilds_total",
                 "Object-map rebuilds after the back-end moved keyframes (loop closure, anchoring).",
                 c.rebuilds),
        _gauge("wardmap_mapping_map_epoch",
               "The map epoch (back-end moves of keyframes) whose object map is complete; -1 before start.",
               c.map_epoch),
        _gauge("wardmap_mapping_settled_rowid",
               "Keyframes up to this insertion number are associated and on the object map; -1 before start.",
               c.settled),
    ]


def decoded_metrics(c: DecodedCounters) -> list[Metric]:
    """The decoded-keyframe cache between ingest and the stages (``server/decoded.py``)."""
    return [
        _counter("wardmap_decoded_cache_hits_total",
                 "Keyframe messages a stage took as ingest decoded them.", c.hits),
        _counter("wardmap_decoded_from_store_total",
                 "Keyframe messages a stage decoded again from the store (after a restart or an eviction).",
                 c.from_store),
        _counter("wardmap_decoded_cache_evicted_total",
                 "Decoded keyframes dropped for the cache's byte bound before the mapping stage was done.",
                 c.evicted),
        _gauge("wardmap_decoded_cache_bytes", "Bytes the decoded-keyframe cache holds.", c.nbytes),
    ]


def backend_metrics(c: BackendCounters) -> list[Metric]:
    """The SLAM back-end's counters."""
    return [
        _gauge("wardmap_backend_backlog", "Stored keyframes the back-end has not put in the pose graph yet.",
               c.backlog),
        _counter("wardmap_backend_keyframes_total", "Keyframes this process added to the pose graph.",
                 c.processed),
        _gauge("wardmap_backend_graph_nodes", "Keyframes in the pose graph.", c.nodes),
        _counter("wardmap_backend_loop_closures_total", "Verified place matches accepted into the graph.",
                 c.loops),
        _counter("wardmap_backend_sessions_anchored_total", "Robot sessions anchored on the map.",
                 c.anchored),
        _counter("wardmap_backend_candidates_total", "Place-recognition candidates verified.", c.candidates),
        _by("reason", CounterMetricFamily, "wardmap_backend_candidates_rejected_total",
            "Place-recognition candidates rejected, by reason.", sorted(c.rejected.items())),
        _by("reason", CounterMetricFamily, "wardmap_backend_failures_total",
            "Keyframes the back-end skipped, by reason.", sorted(c.failures.items())),
        _counter("wardmap_backend_restarts_total",
                 "Unexpected errors the back-end recovered from (see the server log).", c.restarts),
        _gauge("wardmap_backend_index_bytes", "Memory of the place-recognition index.", c.index_bytes),
    ]


def worker_metrics(c: WorkerCounters) -> list[Metric]:
    """This server's perception workers (``server/mapping/workers.py``)."""
    return [
        _gauge("wardmap_perception_workers", "Perception worker processes configured on this server.",
               c.workers),
        _gauge("wardmap_perception_workers_alive", "Perception worker processes running now.", c.alive),
        _counter("wardmap_perception_claims_total", "Stored keyframes this server's workers claimed.",
                 c.claims),
        _counter("wardmap_perception_keyframes_total",
                 "Keyframes this server's workers measured and stored a result for.", c.measured),
        _counter("wardmap_perception_measurements_total", "Object measurements in those results.",
                 c.measurements),
        _counter("wardmap_perception_refused_total",
                 "Results not stored: another worker's (or the mapping stage's) came first.", c.refused),
        _by("reason", CounterMetricFamily, "wardmap_perception_failures_total",
            "Keyframes this server's workers stored as skipped, by reason.", sorted(c.failures.items())),
        _by("worker", CounterMetricFamily, "wardmap_perception_busy_seconds_total",
            "Seconds each worker spent on keyframes (claim to stored result).", sorted(c.busy_s.items())),
        _by("worker", CounterMetricFamily, "wardmap_perception_cpu_seconds_total",
            "CPU seconds each worker's process used on keyframes.", sorted(c.cpu_s.items())),
        _counter("wardmap_perception_worker_restarts_total",
                 "Worker processes started again after they died (see the server log).", c.restarts),
        _by("check", CounterMetricFamily, "wardmap_perception_left_out_total",
            "Instances the workers' floor checks left out, by check.",
            [("floating", c.floating), ("wall", c.wall_pieces), ("floor", c.floor_pieces)]),
        _by("kind", CounterMetricFamily, "wardmap_perception_instances_skipped_total",
            "Instances the workers found but could not measure, by kind.", sorted(c.skipped.items())),
    ]


class ServerCollector(Collector):
    """Yields the server's metrics at scrape time from the parts that count them."""

    def __init__(
        self, store: KeyframeStore, objects: ObjectMap, ingest: Ingest | None, pipeline: MapPipeline | None,
        mapping: MappingRole | None = None, workers: PerceptionWorkers | None = None,
    ) -> None:
        """``pipeline``: a mapping stage that always runs here; ``mapping``: the writer-lease role
        whose stage runs here only while it holds the lease (its metrics then, and the lease's);
        ``workers``: this server's perception workers (writer or standby)."""
        self._store = store
        self._objects = objects
        self._ingest = ingest
        self._pipeline = pipeline
        self._mapping = mapping
        self._workers = workers

    def collect(self) -> Iterator[Metric]:
        counters = self._ingest.counters() if self._ingest is not None else None
        rejections = self._ingest.rejections() if self._ingest is not None else self._store.rejections()
        yield from ingest_metrics(counters, rejections, self._store.stats().robots)
        yield from map_metrics(self._objects.count(unconfirmed=False), self._objects.count(unconfirmed=True))
        pipeline = self._pipeline
        if self._mapping is not None:
            yield from lease_metrics(self._mapping.state())
            pipeline = self._mapping.pipeline
        if pipeline is not None:
            yield from pipeline_metrics(pipeline.counters())
            yield from backend_metrics(pipeline.backend.counters())
            yield from decoded_metrics(pipeline.decoded.counters())
        if self._workers is not None:
            yield from worker_metrics(self._workers.counters())


def metrics_registry(collector: Collector) -> CollectorRegistry:
    """A registry of its own holding only ``collector`` (never the process-global registry)."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    return registry


class _Fixed(Collector):
    def __init__(self, metrics: Iterable[Metric]) -> None:
        self._metrics = list(metrics)

    def collect(self) -> Iterator[Metric]:
        return iter(self._metrics)


def exposition(source: CollectorRegistry | Iterable[Metric]) -> str:
    """The Prometheus text (format 0.0.4) of a registry, or of metric families as they are."""
    registry = source if isinstance(source, CollectorRegistry) else metrics_registry(_Fixed(source))
    return generate_latest(registry).decode()

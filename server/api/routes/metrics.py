"""``GET /metrics``: the server's counters in the Prometheus text format."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import PlainTextResponse

from wardmap.server.api.deps import IngestDep, ObjectMapDep, PipelineDep, StoreDep
from wardmap.server.ingest import IngestCounters
from wardmap.server.perception.measure import SKIP_KINDS
from wardmap.server.pipeline import PipelineCounters

router = APIRouter()


@router.get("/metrics", response_class=PlainTextResponse)
def metrics(store: StoreDep, ingest: IngestDep, objects: ObjectMapDep, pipeline: PipelineDep) -> str:
    counters = ingest.counters() if ingest is not None else None
    text = _prometheus(counters, store.rejections(), store.stats().robots)
    text += (
        "# HELP wardmap_map_objects Objects in the map; confirmed=\"false\": kept, left out of queries.\n"
        "# TYPE wardmap_map_objects gauge\n"
        f'wardmap_map_objects{{confirmed="true"}} {objects.count(unconfirmed=False)}\n'
        f'wardmap_map_objects{{confirmed="false"}} {objects.count(unconfirmed=True)}\n'
    )
    return text + (_pipeline_metrics(pipeline.counters()) if pipeline is not None else "")


def _label(value: str) -> str:
    return value.replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _pipeline_metrics(c: PipelineCounters) -> str:
    """The mapping stage's counters, Prometheus text format."""
    rows = [
        ("wardmap_mapping_backlog", "gauge", "Stored keyframes the mapping stage has not processed yet.",
         [("", c.backlog)]),
        ("wardmap_mapping_keyframes_total", "counter", "Keyframes run through perception by this process.",
         [("", c.processed)]),
        ("wardmap_mapping_measurements_total", "counter", "Object measurements stored by this process.",
         [("", c.measurements)]),
        ("wardmap_mapping_associated_total", "counter", "Keyframes fed to association (sessions on the map).",
         [("", c.mapped)]),
        ("wardmap_mapping_unanchored_total", "counter",
         "Keyframes of sessions without T_map_odom: measured, not mapped.", [("", c.unanchored)]),
        ("wardmap_mapping_failures_total", "counter", "Keyframes perception skipped, by error type.",
         [(f'{{reason="{_label(r)}"}}', n) for r, n in sorted(c.failures.items())]),
        ("wardmap_mapping_landmarks", "gauge", "Landmarks the associator holds.", [("", c.landmarks)]),
        ("wardmap_mapping_restarts_total", "counter",
         "Unexpected errors the mapping stage recovered from (see the server log).", [("", c.restarts)]),
        ("wardmap_mapping_idle_sessions_closed_total", "counter",
         "Sessions whose last keyframe group was mapped because they went quiet (close_idle_s).",
         [("", c.closed_idle)]),
        ("wardmap_mapping_floating_left_out_total", "counter",
         "Instances perception left out for floating above the floor (perception.floor_gap_m).",
         [("", c.floating)]),
        ("wardmap_mapping_wall_pieces_left_out_total", "counter",
         "Instances perception left out for lying on a surface taller than any object of their class "
         "(perception.max_top_m).",
         [("", c.wall_pieces)]),
        ("wardmap_mapping_floor_pieces_left_out_total", "counter",
         "Instances perception left out for lying flat on the floor, lower than any object of their "
         "class (perception.min_top_m).",
         [("", c.floor_pieces)]),
        ("wardmap_mapping_beyond_range_total", "counter",
         "Stored measurements association left out for lying beyond association.max_range_m.",
         [("", c.beyond_range)]),
        ("wardmap_mapping_instances_skipped_total", "counter",
         "Instances perception found but could not measure (stored keyframes), by kind.",
         [(f'{{kind="{k}"}}', c.skipped.get(k, 0)) for k in SKIP_KINDS]),
    ]
    out = []
    for name, kind, help_text, samples in rows:
        out.append(f"# HELP {name} {help_text}")
        out.append(f"# TYPE {name} {kind}")
        out.extend(f"{name}{labels} {value}" for labels, value in samples)
    return "\n".join(out) + "\n"


def _prometheus(counters: IngestCounters | None, rejections: dict[str, int], robots: int) -> str:
    """Prometheus text exposition format 0.0.4. Rejections are the store's persistent counts."""
    c = counters or IngestCounters(0, 0, 0, 0, 0, 0)
    out = []

    def metric(name: str, kind: str, help_text: str, samples: list[tuple[str, int]]) -> None:
        out.append(f"# HELP {name} {help_text}")
        out.append(f"# TYPE {name} {kind}")
        out.extend(f"{name}{labels} {value}" for labels, value in samples)

    metric("wardmap_keyframes_received_total", "counter",
           "Keyframe samples taken from zenoh by this server process.", [("", c.received)])
    metric("wardmap_keyframes_stored_total", "counter",
           "Keyframes newly stored by this server process.", [("", c.stored)])
    metric("wardmap_keyframes_duplicates_total", "counter",
           "Keyframes received again after they were stored (acked duplicate).", [("", c.duplicates)])
    metric("wardmap_rejections_total", "counter",
           "Rejected samples by reason, persistent in the store.",
           [(f'{{reason="{_label(reason)}"}}', n) for reason, n in sorted(rejections.items())])
    metric("wardmap_ingest_queue_depth", "gauge",
           "Samples taken from the zenoh channel and not yet processed.", [("", c.queue_depth)])
    metric("wardmap_ack_failures_total", "counter", "Acks that could not be published.",
           [("", c.ack_failures)])
    metric("wardmap_robots", "gauge", "Robots with at least one stored keyframe.", [("", robots)])
    return "\n".join(out) + "\n"

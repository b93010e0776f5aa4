"""The Prometheus exposition of the server's counters (``server/api/prometheus.py``).

The metric names, types and labels are a public interface (dashboards, alerts): the table
below is the contract, checked against what the collector yields.
"""

from __future__ import annotations

from typing import Any

from prometheus_client import REGISTRY

from wardmap.server.api.prometheus import (
    ServerCollector,
    backend_metrics,
    decoded_metrics,
    exposition,
    ingest_metrics,
    lease_metrics,
    map_metrics,
    metrics_registry,
    pipeline_metrics,
)
from wardmap.server.backend.stage import BackendCounters
from wardmap.server.decoded import DecodedCounters
from wardmap.server.ingest import IngestCounters
from wardmap.server.mapping import PipelineCounters
from wardmap.server.mapping.role import LeaseState
from wardmap.server.perception.measure import SKIP_KINDS

CONTRACT = {
    "wardmap_keyframes_received_total": ("counter", ()),
    "wardmap_keyframes_stored_total": ("counter", ()),
    "wardmap_keyframes_duplicates_total": ("counter", ()),
    "wardmap_rejections_total": ("counter", ("reason",)),
    "wardmap_ingest_queue_depth": ("gauge", ()),
    "wardmap_ack_failures_total": ("counter", ()),
    "wardmap_keyframes_retry_later_total": ("counter", ()),
    "wardmap_robots": ("gauge", ()),
    "wardmap_map_objects": ("gauge", ("confirmed",)),
    "wardmap_mapping_lease_held": ("gauge", ()),
    "wardmap_mapping_writer_info": ("gauge", ("holder", "server")),
    "wardmap_mapping_backlog": ("gauge", ()),
    "wardmap_mapping_keyframes_total": ("counter", ()),
    "wardmap_mapping_measurements_total": ("counter", ()),
    "wardmap_mapping_associated_total": ("counter", ()),
    "wardmap_mapping_unanchored_total": ("counter", ()),
    "wardmap_mapping_failures_total": ("counter", ("reason",)),
    "wardmap_mapping_landmarks": ("gauge", ()),
    "wardmap_mapping_restarts_total": ("counter", ()),
    "wardmap_mapping_idle_sessions_closed_total": ("counter", ()),
    "wardmap_mapping_floating_left_out_total": ("counter", ()),
    "wardmap_mapping_wall_pieces_left_out_total": ("counter", ()),
    "wardmap_mapping_floor_pieces_left_out_total": ("counter", ()),
    "wardmap_mapping_beyond_range_total": ("counter", ()),
    "wardmap_mapping_instances_skipped_total": ("counter", ("kind",)),
    "wardmap_mapping_rebuilds_total": ("counter", ()),
    "wardmap_mapping_map_epoch": ("gauge", ()),
    "wardmap_mapping_settled_rowid": ("gauge", ()),
    "wardmap_backend_backlog": ("gauge", ()),
    "wardmap_backend_keyframes_total": ("counter", ()),
    "wardmap_backend_graph_nodes": ("gauge", ()),
    "wardmap_backend_loop_closures_total": ("counter", ()),
    "wardmap_backend_sessions_anchored_total": ("counter", ()),
    "wardmap_backend_candidates_total": ("counter", ()),
    "wardmap_backend_candidates_rejected_total": ("counter", ("reason",)),
    "wardmap_backend_failures_total": ("counter", ("reason",)),
    "wardmap_backend_restarts_total": ("counter", ()),
    "wardmap_backend_index_bytes": ("gauge", ()),
    "wardmap_decoded_cache_hits_total": ("counter", ()),
    "wardmap_decoded_from_store_total": ("counter", ()),
    "wardmap_decoded_cache_evicted_total": ("counter", ()),
    "wardmap_decoded_cache_bytes": ("gauge", ()),
}
"""Every metric of /metrics: its type and label names, in exposition order."""


def _pipeline(**kw: Any) -> PipelineCounters:
    return PipelineCounters(5, 7, 4, 1, 0, 2, {"GeometryError": 1}, 3, **kw)


def _backend() -> BackendCounters:
    return BackendCounters(12, 40, 2, 1, 30, {"few matches": 25, "anchor vote": 2}, {"WireError": 1}, 0, 3,
                           20_000)


def test_lease_metrics_say_who_writes() -> None:
    """The writer: held 1 and itself as holder; a standby: held 0 and the writer's name; nobody
    holding the lease: no holder sample."""
    _, writer = _parse(exposition(lease_metrics(LeaseState(True, "a", "a"))))
    held = "wardmap_mapping_lease_held"
    assert writer == {held: 1, 'wardmap_mapping_writer_info{holder="a",server="a"}': 1}
    _, standby = _parse(exposition(lease_metrics(LeaseState(False, "a", "b"))))
    assert standby == {held: 0, 'wardmap_mapping_writer_info{holder="a",server="b"}': 1}
    _, nobody = _parse(exposition(lease_metrics(LeaseState(False, None, "b"))))
    assert nobody == {held: 0}


def test_backend_counters() -> None:
    """The back-end's counters by name; rejections and failures by reason."""
    _, samples = _parse(exposition(backend_metrics(_backend())))
    assert samples["wardmap_backend_keyframes_total"] == 12 and samples["wardmap_backend_graph_nodes"] == 40
    assert samples["wardmap_backend_loop_closures_total"] == 2
    assert samples["wardmap_backend_sessions_anchored_total"] == 1
    assert samples['wardmap_backend_candidates_rejected_total{reason="few matches"}'] == 25
    assert samples['wardmap_backend_failures_total{reason="WireError"}'] == 1
    assert samples["wardmap_backend_backlog"] == 3 and samples["wardmap_backend_index_bytes"] == 20_000


def _parse(text: str) -> tuple[dict[str, str], dict[str, float]]:
    """(metric name -> TYPE, sample -> value) of Prometheus text."""
    types, samples = {}, {}
    for line in text.splitlines():
        if line.startswith("# TYPE "):
            _, _, name, kind = line.split(" ")
            types[name] = kind
        elif line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            samples[name] = float(value)
    return types, samples


def test_names_types_and_labels_are_the_contract() -> None:
    """Every metric keeps its name, type and labels, in the documented order."""
    families = (ingest_metrics(IngestCounters(1, 2, 3, 4, 5, 6), {"store": 1}, 2) + map_metrics(3, 1)
                + lease_metrics(LeaseState(True, "server-a", "server-a"))
                + pipeline_metrics(_pipeline(skipped={"little_depth": 1}))
                + backend_metrics(_backend()) + decoded_metrics(DecodedCounters(1, 2, 3, 4, 5, 6, 7, 8)))
    text = exposition(families)
    types, samples = _parse(text)
    assert list(types.items()) == [(name, kind) for name, (kind, _) in CONTRACT.items()]
    for sample in samples:
        name, _, labels = sample.partition("{")
        label_names = tuple(part.split("=")[0] for part in labels.rstrip("}").split(",") if part)
        assert label_names == CONTRACT[name][1], sample
    for name in CONTRACT:
        assert text.index(f"# HELP {name} ") < text.index(f"# TYPE {name} ")


def test_values_and_label_escaping() -> None:
    """Counter values are the snapshot's; label values are escaped (quotes, backslashes, newlines)."""
    rejections = {'odd "reason"': 1, "back\\slash\nnewline": 2, "wire: payload": 4}
    _, samples = _parse(exposition(ingest_metrics(IngestCounters(10, 7, 2, 1, 3, 0), rejections, 2)))
    assert samples["wardmap_keyframes_received_total"] == 10
    assert samples["wardmap_keyframes_stored_total"] == 7
    assert samples["wardmap_ingest_queue_depth"] == 3 and samples["wardmap_robots"] == 2
    assert samples['wardmap_rejections_total{reason="odd \\"reason\\""}'] == 1
    assert samples['wardmap_rejections_total{reason="back\\\\slash\\nnewline"}'] == 2
    assert samples['wardmap_rejections_total{reason="wire: payload"}'] == 4


def test_no_ingest_counts_zero() -> None:
    """An API-only server (no Zenoh) still exposes the ingest counters, at 0."""
    _, samples = _parse(exposition(ingest_metrics(None, {}, 0)))
    assert samples["wardmap_keyframes_received_total"] == 0 and samples["wardmap_ack_failures_total"] == 0


def test_mapping_counters() -> None:
    """The mapping stage's counters by name; every skip kind has its line, 0 when none."""
    c = _pipeline(closed_idle=1, floating=6, beyond_range=9, wall_pieces=4, floor_pieces=8,
                  skipped={"little_depth": 2})
    _, samples = _parse(exposition(pipeline_metrics(c)))
    assert samples["wardmap_mapping_floating_left_out_total"] == 6
    assert samples["wardmap_mapping_beyond_range_total"] == 9
    assert samples["wardmap_mapping_wall_pieces_left_out_total"] == 4
    assert samples["wardmap_mapping_floor_pieces_left_out_total"] == 8
    assert samples["wardmap_mapping_keyframes_total"] == 5 and samples["wardmap_mapping_backlog"] == 2
    assert samples['wardmap_mapping_failures_total{reason="GeometryError"}'] == 1
    name = "wardmap_mapping_instances_skipped_total"
    assert {k: v for k, v in samples.items() if k.startswith(name)} == {
        f'{name}{{kind="{k}"}}': (2 if k == "little_depth" else 0) for k in SKIP_KINDS
    }


class _Store:
    def __init__(self) -> None:
        self.rejected = {"wire: payload": 1}

    def rejections(self) -> dict[str, int]:
        return dict(self.rejected)

    def stats(self) -> Any:
        return type("Stats", (), {"robots": 4})()


class _Objects:
    def count(self, unconfirmed: bool) -> int:
        return 2 if unconfirmed else 9


def test_collector_reads_at_scrape_time_on_its_own_registry() -> None:
    """The collector keeps no copy: a count that changes between scrapes shows in the next one.
    Its registry is the app's own; the process-global registry never sees wardmap metrics."""
    store = _Store()
    registry = metrics_registry(ServerCollector(store, _Objects(), None, None))  # type: ignore[arg-type]
    _, first = _parse(exposition(registry))
    store.rejected["wire: payload"] = 5
    _, second = _parse(exposition(registry))
    key = 'wardmap_rejections_total{reason="wire: payload"}'
    assert (first[key], second[key]) == (1, 5)
    assert second["wardmap_robots"] == 4 and second['wardmap_map_objects{confirmed="false"}'] == 2
    assert not any(name.startswith("wardmap_mapping_") for name in second)
    assert not any(m.name.startswith("wardmap_") for m in REGISTRY.collect())


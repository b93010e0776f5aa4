"""Perception workers (``wardmap.server.mapping.workers``): real worker processes with the packaged
segmentation network measure stored keyframes, and the mapping stage builds from their results the
same object map it builds measuring every keyframe itself."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from wardmap.server.mapping import MapPipeline, PipelineConfig
from wardmap.server.mapping.stage import CURSOR_NAME
from wardmap.server.mapping.workers import MappingConfig, PerceptionWorkers, WorkerCounters, worker_threads
from wardmap.server.objectmap import MAX_LIMIT, ObjectMap
from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.store import MapStore, ObjectRecord, SqliteMapStore
from wardmap.shared.errors import ConfigError
from wardmap.shared.wire import KeyframeMsg

from .test_stage import _keyframes

MODEL = Path(__file__).resolve().parents[3] / "server" / "models" / "hospital_seg.onnx"
needs_model = pytest.mark.skipif(not MODEL.is_file(), reason="the packaged segmentation network is not built")

STAGE = PipelineConfig(poll_s=0.05, close_idle_s=0.0, checkpoint_s=0.0)


@pytest.fixture(scope="module")
def keyframes() -> list[tuple[KeyframeMsg, bytes]]:
    return list(_keyframes(anchored=True))


def _objects(store: MapStore) -> list[ObjectRecord]:
    return [h.record for h in ObjectMap(store).query(include_unconfirmed=True, limit=MAX_LIMIT).hits]


def _map(path: Path, keyframes: list[tuple[KeyframeMsg, bytes]], shared: MappingConfig) -> list[ObjectRecord]:
    """Store ``keyframes``, run the stage (no workers of its own) until idle; the object map."""
    with SqliteMapStore.open(path) as store:
        for msg, payload in keyframes:
            store.insert(msg, payload, time.time())
        pipe = MapPipeline(store, ObjectMap(store), config=STAGE, perception=PerceptionConfig(),
                           shared=shared)
        pipe.start()
        try:
            assert pipe.wait_idle(180.0)
            assert pipe.counters().processed + sum(pipe.counters().failures.values()) == len(keyframes)
        finally:
            pipe.stop()
        return _objects(store)


def _settled(workers: PerceptionWorkers, n: int, timeout_s: float = 30.0) -> WorkerCounters:
    """The workers' counters once they report ``n`` keyframes stored (measured or skipped)."""
    deadline = time.monotonic() + timeout_s
    while True:
        c = workers.counters()
        if c.measured + sum(c.failures.values()) >= n or time.monotonic() > deadline:
            return c
        time.sleep(0.1)


def _same_maps(a: list[ObjectRecord], b: list[ObjectRecord]) -> None:
    assert [(r.object_id, r.category, r.n_observations) for r in a] == \
        [(r.object_id, r.category, r.n_observations) for r in b]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x.T_world_object, y.T_world_object)
        np.testing.assert_array_equal(x.size, y.size)
        assert x.confidence == y.confidence and x.color_rgb == y.color_rgb


@needs_model
def test_two_workers_give_the_map_the_stage_makes_alone(tmp_path: Path,
                                                         keyframes: list[tuple[KeyframeMsg, bytes]]) -> None:
    """Eight keyframes of ward_chairs: once mapped by the stage alone (no workers), once with two
    worker processes running beside the stage, which waits for them (``wait_s`` long): the
    workers measure every keyframe, and the object map is the same object for object (ids,
    categories, observations, poses, sizes, colours). The workers run ``nice`` steps nicer than
    this process."""
    alone = _map(tmp_path / "alone.db", keyframes, MappingConfig())
    assert alone, "the scene has objects"
    shared = MappingConfig(perception_workers=2, wait_s=50.0, poll_s=0.02, nice=7)
    path = tmp_path / "shared.db"
    SqliteMapStore.open(path).close()
    workers = PerceptionWorkers(f"sqlite:///{path}", config=shared, perception=PerceptionConfig(), name="t")
    workers.start()
    try:
        with_workers = _map(path, keyframes, shared)
        counters = _settled(workers, len(keyframes))
        if hasattr(os, "getpriority"):
            want = min(19, os.getpriority(os.PRIO_PROCESS, 0) + 7)
            pids = [p.pid for p in workers._procs if p is not None and p.pid is not None]
            assert [os.getpriority(os.PRIO_PROCESS, pid) for pid in pids] == [want] * 2
    finally:
        workers.stop()
    assert counters.workers == 2
    assert counters.measured + sum(counters.failures.values()) == len(keyframes)
    assert counters.claims == len(keyframes) and counters.refused == 0
    assert set(counters.busy_s) <= {"t/p0", "t/p1"}
    _same_maps(alone, with_workers)


@needs_model
def test_a_worker_killed_mid_run_loses_no_keyframe(tmp_path: Path,
                                                     keyframes: list[tuple[KeyframeMsg, bytes]]) -> None:
    """One worker, short claims: it is SIGKILLed right after its first claim; its claim expires,
    the restarted worker claims the keyframe again, and every keyframe gets a result."""
    path = tmp_path / "map.db"
    shared = MappingConfig(perception_workers=1, claim_s=2.0, wait_s=1.0, poll_s=0.02)
    with SqliteMapStore.open(path) as store:
        for msg, payload in keyframes:
            store.insert(msg, payload, time.time())
        workers = PerceptionWorkers(f"sqlite:///{path}", config=shared, perception=PerceptionConfig(),
                                    name="k")
        workers.start()
        try:
            deadline = time.monotonic() + 60.0
            while workers.counters().claims == 0 and time.monotonic() < deadline:
                time.sleep(0.02)
            [proc] = workers._procs  # the one process (white box: kill it as the OOM killer would)
            assert proc is not None and proc.pid is not None
            os.kill(proc.pid, signal.SIGKILL)
            deadline = time.monotonic() + 90.0
            while store.count_unperceived(CURSOR_NAME) > 0 and time.monotonic() < deadline:
                time.sleep(0.1)
            assert store.count_unperceived(CURSOR_NAME) == 0
            assert workers.counters().restarts >= 1
        finally:
            workers.stop()
        slots = store.perception_slots(0, 10**9, 100)
        assert len(slots) == len(keyframes) and all(s.result is not None for s in slots)


def test_worker_threads_share_the_cores() -> None:
    """N workers' onnxruntime threads never exceed the cores (at least one each)."""
    assert worker_threads(4, 2, cores=8) == 4
    assert worker_threads(4, 4, cores=8) == 2
    assert worker_threads(1, 2, cores=2) == 1
    assert worker_threads(8, 3, cores=2) == 1


@pytest.mark.parametrize("kwargs", [{"perception_workers": -1}, {"claim_s": 0.0}, {"wait_s": -1.0},
                                    {"wait_s": 60.0, "claim_s": 60.0}, {"poll_s": float("nan")},
                                    {"nice": -1}, {"nice": 20}, {"nice": True}, {"nice": 2.5}])
def test_bad_mapping_config_is_rejected(kwargs: dict) -> None:
    with pytest.raises(ConfigError):
        MappingConfig(**kwargs)


def test_worker_counters_in_prometheus_text() -> None:
    from wardmap.server.api.prometheus import exposition, worker_metrics

    c = WorkerCounters(2, 1, claims=9, measured=7, measurements=20, refused=1, failures={"WireError": 1},
                       busy_s={"a/p0": 1.5, "a/p1": 2.0}, cpu_s={"a/p0": 1.25}, restarts=1, floating=3)
    text = exposition(worker_metrics(c))
    samples = {k: float(v) for k, v in (line.rsplit(" ", 1) for line in text.splitlines()
                                         if line and not line.startswith("#"))}
    assert samples["wardmap_perception_workers"] == 2 and samples["wardmap_perception_workers_alive"] == 1
    assert samples["wardmap_perception_claims_total"] == 9
    assert samples["wardmap_perception_keyframes_total"] == 7
    assert samples['wardmap_perception_failures_total{reason="WireError"}'] == 1
    assert samples['wardmap_perception_busy_seconds_total{worker="a/p1"}'] == 2.0
    assert samples['wardmap_perception_cpu_seconds_total{worker="a/p0"}'] == 1.25
    assert samples['wardmap_perception_left_out_total{check="floating"}'] == 3

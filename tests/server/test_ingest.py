"""The keyframe ingest (``wardmap.server.ingest.Ingest``) in this process: a zenoh router on a
thread, the ingest storing into a SQLite file, and a zenoh client standing in for the robots
(it publishes keyframes reliable with congestion control BLOCK and queues every ack it hears).

Sessions are clients on 127.0.0.1 with shared memory and multicast scouting off. The tests wait
on zenoh matching events and the ack queue, never on sleeps. ``wardmap server`` as a process:
tests/integration/test_server_cmd.py.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from factories import keyframe, pack, walk
from peers import ALL_ACKS, matched_publisher, open_client
from procs import free_port

pytest.importorskip("zenoh")

from wardmap.server.ingest import (
    DEFAULT_MAX_BYTES,
    Ingest,
    IngestCounters,
    IngestError,
    SampleQueue,
    wire_reason,
)
from wardmap.server.store import InsertResult, SqliteKeyframeStore, StoreError, open_store
from wardmap.server.telemetry import ServerTelemetry
from wardmap.server.zenoh_session import ZenohSessionError, open_session
from wardmap.shared import wire
from wardmap.shared.errors import ConfigError
from wardmap.shared.wire import AckMsg, KeyframeMsg
from wardmap.shared.zenoh_config import keyframe_key, robot_id_from_key

pytestmark = pytest.mark.timeout(60)

EVENT_TIMEOUT_S = 10.0


@pytest.fixture
def store(tmp_path: Path) -> Iterator[SqliteKeyframeStore]:
    with open_store(f"sqlite:///{tmp_path / 'map.db'}") as s:
        yield s


@contextlib.contextmanager
def running(
    router: str, store: Any, capacity: int = 256, max_bytes: int = DEFAULT_MAX_BYTES,
    telemetry: ServerTelemetry | None = None,
) -> Iterator[Ingest]:
    """An ingest started on its own client session to ``router`` (the server's composition root
    shares one session the same way); stopped, then the session closed."""
    session = open_session([router])
    try:
        with Ingest(session, store, capacity=capacity, max_bytes=max_bytes, telemetry=telemetry) as ingest:
            yield ingest
    finally:
        session.close()


class Robots:
    """A zenoh client that publishes on keyframe keys and queues ``(key robot, ack)`` for every
    ack (the subscriber callback only enqueues)."""

    def __init__(self, endpoint: str) -> None:
        self.acks: queue.Queue[tuple[str, AckMsg]] = queue.Queue()
        self._session = open_client(endpoint)
        self._subscriber = self._session.declare_subscriber(ALL_ACKS, self._on_ack)
        self._publishers: dict[str, Any] = {}

    def _on_ack(self, sample: Any) -> None:
        self.acks.put((robot_id_from_key(str(sample.key_expr)), wire.decode_ack(sample.payload.to_bytes())))

    def put(self, key: str, payload: bytes) -> None:
        """Publish ``payload`` on ``key`` once the ingest's subscriber matches it."""
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = matched_publisher(self._session, key, EVENT_TIMEOUT_S)
        pub.put(payload)

    def next_acks(self, n: int) -> list[tuple[str, AckMsg]]:
        """The next ``n`` acks; fails the test when they do not all arrive in time."""
        got = []
        for _ in range(n):
            try:
                got.append(self.acks.get(timeout=EVENT_TIMEOUT_S))
            except queue.Empty:
                pytest.fail(f"only {len(got)} of {n} acks arrived: {got}")
        return got

    def close(self) -> None:
        for pub in self._publishers.values():
            pub.undeclare()
        self._subscriber.undeclare()
        self._session.close()


@pytest.fixture
def robots(router: str) -> Iterator[Robots]:
    r = Robots(router)
    try:
        yield r
    finally:
        r.close()


def _keyframes(robot: str, n: int) -> list[KeyframeMsg]:
    return walk(keyframe(np.random.default_rng(sum(robot.encode())), robot_id=robot), n)


def test_stores_acks_and_counts_duplicates(router: str, store: SqliteKeyframeStore, robots: Robots) -> None:
    """Three keyframes of r1 are stored and acked ``stored`` in order; the first, sent again, is
    acked ``duplicate``. The store holds the three payloads byte for byte; the counters say 4
    received, 3 stored, 1 duplicate, nothing rejected or waiting."""
    msgs = _keyframes("r1", 3)
    payloads = [wire.encode(m) for m in msgs]
    with running(router, store) as ingest:
        for p in payloads:
            robots.put(keyframe_key("r1"), p)
        stored = robots.next_acks(3)
        robots.put(keyframe_key("r1"), payloads[0])
        (dup,) = robots.next_acks(1)
        counters = ingest.counters()
    assert stored == [("r1", AckMsg("r1", "s1", seq, "stored")) for seq in range(3)]
    assert dup == ("r1", AckMsg("r1", "s1", 0, "duplicate"))
    assert counters == IngestCounters(received=4, stored=3, duplicates=1, rejected=0, queue_depth=0,
                                      ack_failures=0)
    assert [store.payload("r1", "s1", seq) for seq in range(3)] == payloads
    assert store.rejections() == {}


def test_telemetry_times_ingest_and_acks_and_follows_each_robot(
    router: str, store: SqliteKeyframeStore, robots: Robots
) -> None:
    """Two keyframes of r1 and one of r2, r1's first sent again: the ingest and ack histograms
    hold one observation per keyframe received, each robot's keyframes are counted by their ack
    status, and its last-seen time is the wall clock of its last keyframe."""
    telemetry = ServerTelemetry()
    msgs = {"r1": _keyframes("r1", 2), "r2": _keyframes("r2", 1)}
    before = time.time()
    with running(router, store, telemetry=telemetry):
        for robot, kfs in msgs.items():
            for m in kfs:
                robots.put(keyframe_key(robot), wire.encode(m))
        robots.next_acks(3)
        robots.put(keyframe_key("r1"), wire.encode(msgs["r1"][0]))
        robots.next_acks(1)
    after = time.time()

    def value(name: str, **labels: str) -> float:
        for metric in (telemetry.ingest_seconds, telemetry.ack_seconds, telemetry.robot_keyframes,
                       telemetry.robot_last_seen):
            for fam in metric.collect():
                for sample in fam.samples:
                    if sample.name == name and sample.labels == labels:
                        return float(sample.value)
        raise AssertionError(f"no sample {name} {labels}")

    assert value("wardmap_ingest_seconds_count") == 4
    assert value("wardmap_ack_seconds_count") == 4
    assert value("wardmap_robot_keyframes_total", robot="r1", result="stored") == 2
    assert value("wardmap_robot_keyframes_total", robot="r1", result="duplicate") == 1
    assert value("wardmap_robot_keyframes_total", robot="r2", result="stored") == 1
    for robot in ("r1", "r2"):
        assert before <= value("wardmap_robot_last_seen_seconds", robot=robot) <= after


def test_bad_samples_are_acked_rejected_and_counted_by_reason(
        router: str, store: SqliteKeyframeStore, robots: Robots) -> None:
    """On r1's key: random bytes, a keyframe whose depth codec is unknown, and r2's valid
    keyframe. Each is acked ``rejected`` to r1 (with the keyframe's session and seq where it
    decoded) and counted under a bounded reason; nothing is stored."""
    (r1,) = _keyframes("r1", 1)
    (r2,) = _keyframes("r2", 1)
    tree = msgpack.unpackb(wire.encode(replace(r1, seq=5)), raw=False)
    tree["depth"]["codec"] = "png"
    with running(router, store) as ingest:
        robots.put(keyframe_key("r1"), bytes(range(200)))
        robots.put(keyframe_key("r1"), pack(tree))
        robots.put(keyframe_key("r1"), wire.encode(replace(r2, session_id="s9", seq=7)))
        acks = robots.next_acks(3)
        counters = ingest.counters()
    assert [(key, a.robot_id, a.session_id, a.seq, a.status) for key, a in acks] == [
        ("r1", "r1", "unknown", 0, "rejected"),
        ("r1", "r1", "unknown", 0, "rejected"),
        ("r1", "r1", "s9", 7, "rejected"),
    ]
    assert all(a.reason for _, a in acks)
    assert store.rejections() == {"wire: payload": 1, "wire: depth": 1, "robot_id mismatch": 1}
    assert (counters.received, counters.rejected, counters.stored) == (3, 3, 0)
    assert store.robots() == []


def test_a_key_without_a_robot_id_is_counted_not_acked(
        router: str, store: SqliteKeyframeStore, robots: Robots) -> None:
    """A keyframe on a key whose robot part is not a robot id has nobody to ack: it is counted
    as a ``robot_id mismatch`` only. r1's keyframe sent after it is stored and acked, the only ack."""
    (msg,) = _keyframes("r1", 1)
    with running(router, store) as ingest:
        robots.put("wardmap/v1/robot/r!1/keyframe", wire.encode(msg))
        robots.put(keyframe_key("r1"), wire.encode(msg))
        (ack,) = robots.next_acks(1)
        counters = ingest.counters()
    assert ack == ("r1", AckMsg("r1", "s1", 0, "stored"))
    assert robots.acks.empty()
    assert store.rejections() == {"robot_id mismatch": 1}
    assert (counters.received, counters.rejected, counters.stored) == (2, 1, 1)


class _FailingInserts:
    """``store``, except that inserting seq 0 raises StoreError and seq 1 a RuntimeError (a bug)."""

    def __init__(self, store: SqliteKeyframeStore) -> None:
        self.store = store

    def insert(self, msg: KeyframeMsg, payload: bytes, received_s: float) -> InsertResult:
        if msg.seq == 0:
            raise StoreError("disk I/O error")
        if msg.seq == 1:
            raise RuntimeError("a bug in the store")
        return self.store.insert(msg, payload, received_s)

    def count_rejection(self, reason: str, n: int = 1) -> None:
        self.store.count_rejection(reason, n)

    def rejections(self) -> dict[str, int]:
        return self.store.rejections()

    def writable(self) -> tuple[bool, str]:
        return self.store.writable()


def test_store_failures_are_retries_and_the_worker_goes_on(
        router: str, store: SqliteKeyframeStore, robots: Robots) -> None:
    """A store error is never a rejection: acked ``retry`` (the robot keeps and resends it) and
    counted as retry-later; an unexpected exception is counted ``internal`` and not acked; the
    next keyframe is stored."""
    msgs = _keyframes("r1", 3)
    with running(router, _FailingInserts(store)) as ingest:
        for m in msgs:
            robots.put(keyframe_key("r1"), wire.encode(m))
        acks = robots.next_acks(2)
        counters = ingest.counters()
    assert [(a.seq, a.status) for _, a in acks] == [(0, "retry"), (2, "stored")]
    assert store.rejections() == {"internal": 1}
    assert (counters.received, counters.rejected, counters.stored, counters.retry_later) == (3, 1, 1, 1)


def test_a_full_channel_holds_the_robots_back_and_drops_nothing(
        router: str, store: SqliteKeyframeStore, robots: Robots) -> None:
    """With a channel of one sample, 40 keyframes published back to back are all stored and
    acked in order (FIFO, block when full: backpressure, never a drop)."""
    msgs = _keyframes("r1", 40)
    with running(router, store, capacity=1) as ingest:
        for m in msgs:
            robots.put(keyframe_key("r1"), wire.encode(m))
        acks = robots.next_acks(40)
        counters = ingest.counters()
    assert [(a.seq, a.status) for _, a in acks] == [(seq, "stored") for seq in range(40)]
    assert (counters.received, counters.stored, counters.queue_depth) == (40, 40, 0)


class _HeldInserts(_FailingInserts):
    """``store``, except that the first insert waits until ``release`` is set."""

    def __init__(self, store: SqliteKeyframeStore) -> None:
        super().__init__(store)
        self.release = threading.Event()
        self.entered = threading.Event()

    def insert(self, msg: KeyframeMsg, payload: bytes, received_s: float) -> InsertResult:
        if not self.entered.is_set():
            self.entered.set()
            if not self.release.wait(60):
                raise RuntimeError("never released")
        return self.store.insert(msg, payload, received_s)


def test_the_queue_is_bounded_in_bytes_and_holds_the_robots_back(
        router: str, store: SqliteKeyframeStore, robots: Robots) -> None:
    """While the store is stuck on the first keyframe, twelve 3 MiB garbage payloads queue up to
    at most the 8 MiB bound (not 36 MiB: the rest waits in zenoh's own bounded buffers); once
    the store moves, all of them are rejected and counted and the 3 keyframes after them stored."""
    held = _HeldInserts(store)
    msgs = _keyframes("r1", 4)
    garbage = [bytes([i]) * (3 * 2**20) for i in range(12)]
    max_bytes = 8 * 2**20
    with running(router, held, max_bytes=max_bytes) as ingest:
        try:
            robots.put(keyframe_key("r1"), wire.encode(msgs[0]))
            assert held.entered.wait(EVENT_TIMEOUT_S)
            sender = threading.Thread(target=lambda: [robots.put(keyframe_key("r1"), g) for g in garbage]
                                      + [robots.put(keyframe_key("r1"), wire.encode(m)) for m in msgs[1:]],
                                      daemon=True)
            sender.start()
            peak, deadline = 0, time.monotonic() + EVENT_TIMEOUT_S
            while time.monotonic() < deadline and peak < max_bytes - 3 * 2**20:  # the queue fills
                peak = max(peak, ingest.counters().queued_bytes)
                time.sleep(0.01)
            for _ in range(50):  # and stays within its bound while the store is stuck
                peak = max(peak, ingest.counters().queued_bytes)
                time.sleep(0.01)
            assert max_bytes - 3 * 2**20 <= peak <= max_bytes, peak
            held.release.set()
            acks = robots.next_acks(16)
            sender.join(EVENT_TIMEOUT_S)
            counters = ingest.counters()
        finally:
            held.release.set()
    stored = [a.seq for _, a in acks if a.status == "stored"]
    assert stored == [0, 1, 2, 3]
    assert sum(a.status == "rejected" for _, a in acks) == 12
    assert store.rejections() == {"wire: payload": 12}
    assert (counters.received, counters.queued_bytes, counters.queue_depth) == (16, 0, 0)


def test_sample_queue_bounds_blocks_and_closes() -> None:
    """SampleQueue: FIFO; a put that would pass the byte bound waits for a get; an item larger
    than the bound goes in alone; close releases a waiting put (refused) and get returns what
    is left, then None."""
    q = SampleQueue(capacity=3, max_bytes=10)
    assert q.put("a", 6) and q.depth() == (1, 6)
    done = threading.Event()
    waiter = threading.Thread(target=lambda: (q.put("b", 6), done.set()), daemon=True)
    waiter.start()
    assert not done.wait(0.2)  # 12 bytes would pass the bound
    assert q.get() == "a" and done.wait(5) and q.get() == "b"
    assert q.put("huge", 100) and q.depth() == (1, 100)  # alone, as it can never fit otherwise
    result: list[bool] = []
    blocked = threading.Thread(target=lambda: result.append(q.put("c", 1)), daemon=True)
    blocked.start()
    q.close()
    blocked.join(5)
    assert result == [False]
    assert q.get() == "huge" and q.get() is None and not q.put("d", 1)


@pytest.mark.parametrize("capacity", [0, -3, True, 2.5, "8"])
def test_bad_capacity_is_refused(store: SqliteKeyframeStore, capacity: Any) -> None:
    with pytest.raises(ConfigError, match="capacity"):
        Ingest(object(), store, capacity=capacity)


def test_bad_endpoint_is_refused_before_zenoh(store: SqliteKeyframeStore) -> None:
    with pytest.raises(ConfigError, match="nohost"):
        open_session(["tcp/nohost"])


def test_start_errors_and_stop_twice(router: str, store: SqliteKeyframeStore) -> None:
    """No router at the endpoint: the server's session cannot open and the error names it. A
    started ingest refuses a second start; stop may be called again."""
    nobody = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(ZenohSessionError, match=nobody):
        open_session([nobody])
    session = open_session([router])
    try:
        ingest = Ingest(session, store)
        ingest.start()
        try:
            with pytest.raises(IngestError, match="already started"):
                ingest.start()
        finally:
            ingest.stop()
        ingest.stop()
        assert ingest.counters().received == 0
    finally:
        session.close()


def test_wire_rejection_reasons_are_bounded() -> None:
    """Rejection reasons come from a fixed set of top-level fields, whatever field name a
    hostile payload carries (each reason becomes a DB row and a Prometheus label)."""
    assert wire_reason("") == "wire: payload"
    assert wire_reason("keypoints.uv") == "wire: keypoints"
    assert wire_reason("T_odom_camera.q_xyzw") == "wire: T_odom_camera"
    reasons = {wire_reason(f"field{i}") for i in range(1000)} | {wire_reason("intrmnsics.fx")}
    assert reasons == {"wire: unknown field"}

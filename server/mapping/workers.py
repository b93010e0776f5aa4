"""Perception workers: processes on every server that claim stored keyframes and measure them.

Perception (segmentation and 3D measurement, ``perceive.py``) is the costly part of mapping and
needs nothing of the map, so it is shared out: each server (the writer and every standby) runs
``[mapping] perception_workers`` worker processes. Each one, in a loop, claims the first stored
keyframe after the mapping stage's cursor that has no result and no live claim
(:meth:`~wardmap.server.store.PerceptionStore.claim_keyframe`; a claim lasts ``claim_s``),
measures it from its stored payload and stores the result. The mapping stage, on the writer
only, takes the results in insertion order (``stage.py``); association and object-map writes
stay with it. A worker killed mid-keyframe leaves its claim to expire, and another worker (or the
stage itself) claims the keyframe again: none is lost, and the first result stored stays.

Processes, not threads: about 60% of a keyframe's perception time holds the GIL (numpy on small
arrays and Python around the network, which runs in onnxruntime without it), so two threads of one
process would reach about 1.6x one, not 2x (docs/decisions/0040-perception-worker-processes.md).
Each process opens its own store connection and its own segmenter, whose onnxruntime intra-op
threads are ``[perception] threads`` capped at the cores per worker, so N workers do not
oversubscribe the host.

Failures: a keyframe perception cannot measure is stored as a result with its reason (the
error type); an unexpected error (a bug) releases the claim, and the keyframe's ``max_attempts``
-th claim that fails so (or finds the earlier claimers died) stores it as ``internal: <type>``.
The worker backs off (``retry_s``) after a store error. A worker process that dies is started
again after ``RESTART_S``; a worker whose server process died (SIGKILL does not reach children)
exits at its next claim.

Ownership: :class:`PerceptionWorkers` (the server's composition root owns it) owns the processes,
one bounded report queue (policy: a full queue drops the snapshot; the next one carries the
totals, as snapshots are cumulative), one bounded log queue (records relayed to this process's
loggers by a ``QueueListener`` thread), and one monitor thread that drains the reports and
restarts dead workers.
"""

from __future__ import annotations

import contextlib
import logging
import logging.handlers
import math
import multiprocessing
import os
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from multiprocessing.process import BaseProcess
from typing import Any, Final

from wardmap.server.mapping.perceive import MAPPING_CURSOR, KeyframeMeasurer
from wardmap.server.perception.config import PerceptionConfig
from wardmap.server.store import ClaimedKeyframe, MappedPose, MapStore, Perceived
from wardmap.shared.errors import ConfigError

log = logging.getLogger(__name__)

__all__ = ["MappingConfig", "PerceptionWorkers", "WorkerCounters", "worker_threads"]

RESTART_S: Final = 5.0
"""Seconds before a worker process that died is started again."""
REPORT_QUEUE: Final = 64
"""Counter snapshots the report queue holds (policy: drop a snapshot when full)."""
LOG_QUEUE: Final = 1000
"""Log records the log queue holds (a full queue drops a record, QueueHandler's policy)."""
STOP_JOIN_S: Final = 10.0
"""How long :meth:`PerceptionWorkers.stop` waits for a worker to finish its keyframe before killing it."""


@dataclass(frozen=True)
class MappingConfig:
    """Perception shared out between servers (``[mapping]`` table).

    Attributes:
        perception_workers: worker processes on this server (writer or standby) that claim stored
            keyframes and measure them; 0: none here (the writer's mapping stage measures what no
            worker measured, as a single server always did).
        claim_s: how long a claim lasts (seconds, server wall clock; the servers' clocks must agree
            well within it): a worker that died holds a keyframe this long at most.
        wait_s: how long the writer's mapping stage waits for a worker to claim the keyframe it
            needs next before measuring it itself (seconds; 0 when this server has no workers).
        poll_s: how long an idle worker sleeps before it looks for keyframes again (seconds).
        retry_s: how long a worker waits after a store error (seconds).
        nice: added to each worker process's niceness (0-19; Unix), and to the threads of the
            mapping stage and the back-end in the server process (Linux; ``server/priority.py``):
            mapping, which can wait, yields the cores to ingest, whose acks robots wait for.
    """

    perception_workers: int = 0
    claim_s: float = 60.0
    wait_s: float = 2.0
    poll_s: float = 0.05
    retry_s: float = 1.0
    nice: int = 10

    def __post_init__(self) -> None:
        if not (isinstance(self.perception_workers, int) and 0 <= self.perception_workers <= 64):
            raise ConfigError("mapping.perception_workers must be an int in [0, 64], "
                              f"got {self.perception_workers!r}")
        if not (isinstance(self.nice, int) and not isinstance(self.nice, bool) and 0 <= self.nice <= 19):
            raise ConfigError(f"mapping.nice must be an int in [0, 19], got {self.nice!r}")
        for name in ("claim_s", "poll_s", "retry_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"mapping.{name} must be > 0, got {value}")
        if not (math.isfinite(self.wait_s) and self.wait_s >= 0):
            raise ConfigError(f"mapping.wait_s must be >= 0, got {self.wait_s}")
        if self.wait_s >= self.claim_s:
            raise ConfigError(f"mapping.wait_s ({self.wait_s}) must be shorter than claim_s ({self.claim_s})")


@dataclass(frozen=True)
class WorkerCounters:
    """A snapshot of this server's perception workers for ``/metrics``.

    Attributes:
        workers: worker processes configured.
        alive: worker processes running now.
        claims: keyframes they claimed.
        measured: keyframes they measured and stored a result for (failures not included).
        measurements: object measurements in those results.
        refused: results not stored because another worker's (or the stage's) came first.
        failures: keyframes stored as skipped, by reason (the error type; ``internal: <type>``).
        busy_s: seconds each worker spent on keyframes (claim to stored result), by worker name.
        cpu_s: CPU seconds each worker's process used on them (all its threads), by worker name.
        restarts: worker processes started again after they died.
        floating, wall_pieces, floor_pieces: instances the floor checks left out (as the mapping
            stage counts them).
        skipped: instances measurement could not measure, by kind.
    """

    workers: int
    alive: int
    claims: int = 0
    measured: int = 0
    measurements: int = 0
    refused: int = 0
    failures: dict[str, int] = field(default_factory=dict)
    busy_s: dict[str, float] = field(default_factory=dict)
    cpu_s: dict[str, float] = field(default_factory=dict)
    restarts: int = 0
    floating: int = 0
    wall_pieces: int = 0
    floor_pieces: int = 0
    skipped: dict[str, int] = field(default_factory=dict)


def worker_threads(perception_threads: int, workers: int, cores: int | None = None) -> int:
    """onnxruntime intra-op threads of each of ``workers`` workers: ``perception_threads`` capped
    at the host's ``cores`` (``os.cpu_count()`` when None) shared between them, at least 1."""
    n = cores if cores is not None else (os.cpu_count() or 1)
    return max(1, min(perception_threads, n // max(1, workers)))


@dataclass(frozen=True)
class _Spec:
    """What a worker process needs (pickled to it at start)."""

    db_url: str
    password: str | None
    perception: PerceptionConfig
    name: str
    threads: int
    claim_s: float
    poll_s: float
    retry_s: float
    max_attempts: int
    nice: int


class PerceptionWorkers:
    """This server's perception worker processes (see the module docstring).

    Args:
        db_url: the store's URL (each worker opens its own connection).
        config: the ``[mapping]`` settings (``perception_workers`` processes).
        perception: segmenter and measurement settings.
        name: this server's name; worker ``i`` is ``"<name>/p<i>"`` in the store and on /metrics.
        max_attempts: claims of one keyframe that may end in an unexpected error before it is
            stored as skipped (``[pipeline] max_attempts``).
        password: the database password (never on a command line).
    """

    def __init__(self, db_url: str, *, config: MappingConfig, perception: PerceptionConfig, name: str,
                 max_attempts: int = 3, password: str | None = None) -> None:
        self.config = config
        n = config.perception_workers
        threads = worker_threads(perception.threads, n)
        self._specs = [_Spec(db_url, password, perception, f"{name}/p{i}", threads, config.claim_s,
                             config.poll_s, config.retry_s, max_attempts, config.nice) for i in range(n)]
        self._ctx = multiprocessing.get_context("spawn")  # the server has zenoh and HTTP threads: never fork
        self._reports: Any = self._ctx.Queue(REPORT_QUEUE)
        self._logs: Any = self._ctx.Queue(LOG_QUEUE)
        self._stop_event: Any = self._ctx.Event()
        self._procs: list[BaseProcess | None] = [None] * n
        self._died_at: list[float | None] = [None] * n
        self._lock = threading.Lock()  # guards _snapshots and _restarts for counters()
        self._snapshots: dict[str, dict[str, Any]] = {}
        self._restarts = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._listener: logging.handlers.QueueListener | None = None

    def start(self) -> None:
        """Start the worker processes (each builds its segmenter and opens the store) and the
        monitor thread; returns without waiting for the workers to be ready."""
        if not self._specs:
            return
        self._listener = logging.handlers.QueueListener(self._logs, _Relay())
        self._listener.start()
        for i in range(len(self._specs)):
            self._spawn(i)
        self._thread = threading.Thread(target=self._monitor, name="perception-workers", daemon=True)
        self._thread.start()
        log.info("perception: %d worker process(es), %d onnxruntime thread(s) each, niceness +%d",
                 len(self._specs), self._specs[0].threads, self.config.nice)

    def stop(self) -> None:
        """Stop the workers after their keyframe in progress (killed after ``STOP_JOIN_S``; their
        claims then expire), the monitor and the log relay (idempotent)."""
        self._stop.set()
        self._stop_event.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join()
        for proc in self._procs:
            if proc is None:
                continue
            proc.join(STOP_JOIN_S)
            if proc.is_alive():
                log.warning("perception worker %s did not stop in %.0f s; killed", proc.name, STOP_JOIN_S)
                proc.kill()
                proc.join()
        self._drain(block=False)
        listener, self._listener = self._listener, None
        if listener is not None:
            listener.stop()

    def running(self) -> bool:
        """Whether every worker process is alive (True with no workers)."""
        return all(p is not None and p.is_alive() for p in self._procs)

    def counters(self) -> WorkerCounters:
        with self._lock:
            snaps = list(self._snapshots.items())
            restarts = self._restarts
        total: Counter[str] = Counter()
        failures: Counter[str] = Counter()
        skipped: Counter[str] = Counter()
        for _, s in snaps:
            total.update({k: s[k] for k in ("claims", "measured", "measurements", "refused", "floating",
                                            "wall_pieces", "floor_pieces")})
            failures.update(s["failures"])
            skipped.update(s["skipped"])
        alive = sum(1 for p in self._procs if p is not None and p.is_alive())
        return WorkerCounters(len(self._specs), alive, total["claims"], total["measured"],
                              total["measurements"], total["refused"], dict(failures),
                              {name: float(s["busy_s"]) for name, s in snaps},
                              {name: float(s["cpu_s"]) for name, s in snaps}, restarts,
                              total["floating"], total["wall_pieces"], total["floor_pieces"],
                              dict(skipped))

    # ------------------------------------------------------------------ monitor thread

    def _spawn(self, i: int) -> None:
        spec = self._specs[i]
        proc = self._ctx.Process(target=_worker_main,
                                 args=(spec, self._stop_event, self._reports, self._logs),
                                 name=f"perception-{spec.name}", daemon=True)
        proc.start()
        self._procs[i] = proc
        self._died_at[i] = None

    def _monitor(self) -> None:
        while not self._stop.is_set():
            self._drain(block=True)
            now = time.monotonic()
            for i, proc in enumerate(self._procs):
                if proc is None or proc.is_alive() or self._stop.is_set():
                    continue
                died = self._died_at[i]
                if died is None:
                    self._died_at[i] = now
                    log.error("perception worker %s exited (code %s); starting it again in %.0f s",
                              self._specs[i].name, proc.exitcode, RESTART_S)
                elif now - died >= RESTART_S:
                    self._spawn(i)
                    with self._lock:
                        self._restarts += 1

    def _drain(self, *, block: bool) -> None:
        """Take every counter snapshot waiting (the first one waiting up to 0.2 s when ``block``)."""
        while True:
            try:
                name, snap = self._reports.get(timeout=0.2) if block else self._reports.get_nowait()
            except (queue.Empty, OSError, ValueError):
                return
            block = False
            with self._lock:
                self._snapshots[name] = snap


class _Relay(logging.Handler):
    """Hands a worker process's log record to the logger of the same name here."""

    def handle(self, record: logging.LogRecord) -> bool:  # a relay: no formatting here
        logger = logging.getLogger(record.name)
        if logger.isEnabledFor(record.levelno):
            logger.handle(record)
        return True

    def emit(self, record: logging.LogRecord) -> None:  # pragma: no cover - handle() does the work
        pass


# ---------------------------------------------------------------------------- in the worker process


def _worker_main(spec: _Spec, stop: Any, reports: Any, logs: Any) -> None:
    """A worker process: relay logs, open the store and the segmenter, then :func:`run_worker`."""
    root = logging.getLogger()
    root.handlers[:] = [logging.handlers.QueueHandler(logs)]
    root.setLevel(logging.INFO)
    if spec.nice and hasattr(os, "nice"):  # before onnxruntime starts its threads: they inherit it
        os.nice(spec.nice)
    from wardmap.server.perception.models import make_segmenter
    from wardmap.server.store import open_store

    try:
        segmenter = make_segmenter(spec.perception.segmenter, spec.perception, threads=spec.threads)
        with open_store(spec.db_url, password=spec.password) as store:
            parent = multiprocessing.parent_process()
            run_worker(store, KeyframeMeasurer(segmenter, spec.perception), spec, stop,
                       lambda snap: _report(reports, spec.name, snap),
                       alive=(lambda: True) if parent is None else parent.is_alive)
    except BaseException:
        log.exception("perception worker %s stopped", spec.name)
        raise


def _report(reports: Any, name: str, snap: dict[str, Any]) -> None:
    with contextlib.suppress(queue.Full):  # the named policy: the next snapshot carries the totals
        reports.put_nowait((name, snap))


def run_worker(store: MapStore, measurer: KeyframeMeasurer, spec: _Spec, stop: Any,
               report: Callable[[dict[str, Any]], None], alive: Callable[[], bool] = lambda: True) -> None:
    """Claim, measure and store keyframes until ``stop`` (an Event) is set or ``alive()`` is False
    (the server process died: a SIGKILLed parent does not stop its children); ``report`` is
    called with the cumulative counters after each keyframe and about once a second when idle."""
    counts: dict[str, Any] = {"claims": 0, "measured": 0, "measurements": 0, "refused": 0, "floating": 0,
                              "wall_pieces": 0, "floor_pieces": 0, "busy_s": 0.0, "cpu_s": 0.0,
                              "failures": Counter(), "skipped": Counter()}
    reported = 0.0
    while not stop.is_set():
        if not alive():
            log.warning("perception worker %s: its server process is gone; exiting", spec.name)
            return
        try:
            claim = store.claim_keyframe(spec.name, cursor=MAPPING_CURSOR, now_s=time.time(),
                                         claim_s=spec.claim_s)
        except Exception:
            log.exception("perception worker %s: claiming failed; retrying in %.1f s", spec.name,
                          spec.retry_s)
            stop.wait(spec.retry_s)
            continue
        if claim is None:
            if time.monotonic() - reported >= 1.0:
                report(_snapshot(counts))
                reported = time.monotonic()
            stop.wait(spec.poll_s)
            continue
        started, cpu = time.perf_counter(), time.process_time()
        counts["claims"] += 1
        try:
            _measure_claimed(store, measurer, spec, claim, counts)
        except Exception:
            log.exception("perception worker %s: storing keyframe %s failed; retrying in %.1f s", spec.name,
                          claim.key, spec.retry_s)
            stop.wait(spec.retry_s)
        counts["busy_s"] += time.perf_counter() - started
        counts["cpu_s"] += time.process_time() - cpu
        report(_snapshot(counts))
        reported = time.monotonic()


def _measure_claimed(store: MapStore, measurer: KeyframeMeasurer, spec: _Spec, claim: ClaimedKeyframe,
                     counts: dict[str, Any]) -> None:
    """Measure one claimed keyframe and store its result (or release the claim after a bug)."""
    if claim.attempts > spec.max_attempts:  # the claimers before died on it
        _store_failure(store, spec, claim, "internal: worker died", counts)
        return
    try:
        measured = measurer.measure(claim.key, claim.payload)
    except Exception as exc:  # a bug: let it be claimed again, up to max_attempts claims
        if claim.attempts >= spec.max_attempts:
            log.exception("perception worker %s: keyframe %s failed %d times; skipped", spec.name, claim.key,
                          claim.attempts)
            _store_failure(store, spec, claim, f"internal: {type(exc).__name__}", counts)
        else:
            log.exception("perception worker %s: keyframe %s failed unexpectedly; released", spec.name,
                          claim.key)
            store.release_claim(spec.name, claim.rowid)
        return
    result = measured.result
    if not store.store_perceived(spec.name, result):
        counts["refused"] += 1
        return
    if result.failure is not None:
        counts["failures"][result.failure] += 1
        return
    counts["measured"] += 1
    counts["measurements"] += len(result.measurements)
    counts["floating"] += measured.left_out.floating
    counts["wall_pieces"] += measured.left_out.walls
    counts["floor_pieces"] += measured.left_out.floors
    counts["skipped"].update(measured.skipped)


def _store_failure(store: MapStore, spec: _Spec, claim: ClaimedKeyframe, reason: str,
                   counts: dict[str, Any]) -> None:
    log.error("perception worker %s: keyframe %s skipped (%s)", spec.name, claim.key, reason)
    failed = Perceived(MappedPose(claim.robot_id, claim.session_id, claim.seq, None, None), False, [], reason)
    if store.store_perceived(spec.name, failed):
        counts["failures"][reason] += 1
    else:
        counts["refused"] += 1


def _snapshot(counts: dict[str, Any]) -> dict[str, Any]:
    return {**counts, "failures": dict(counts["failures"]), "skipped": dict(counts["skipped"])}

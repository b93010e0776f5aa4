"""The mapping stage runner: stored keyframes -> perception -> the map writer, in one thread.

Ingest stores a keyframe and acks it (``server/ingest.py``); this stage runs behind it in its
own thread and never delays an ack. It reads keyframes from the store in insertion order
(their ``rowid``), and for each one:

1. takes its perception result: the one a perception worker of any server stored
   (``workers.py``), or, when no worker has claimed the keyframe (at once when this server runs
   no workers, else after ``[mapping] wait_s``), measures it here (``perceive.py``: the keyframe
   as ingest and the back-end decoded it, ``server/decoded.py``; the segmenter, the trained
   network by default; every non-``moving`` instance measured in 3D, paper 000 Eq. 1). While a
   worker holds a live claim on it, the stage waits: results are taken strictly in order, so
   association (a deterministic function of the ordered measurements) is the same wherever
   they were made;
2. commits the measurements, the keyframe's map pose and camera, and its cursor in one
   transaction (:meth:`~wardmap.server.store.MappingStore.commit_keyframe`), so a crash
   never loses or repeats one;
3. when the keyframe's session is on the map (the robot sent ``T_map_odom``, docs/wire.md),
   hands the measurements, in the map frame, to the :class:`~wardmap.server.mapping.writer.MapWriter`
   (association and object-map writes).

Sessions without ``T_map_odom`` are measured and counted (``unanchored``) but not mapped: their
odom frame is unknown in the map until loop closure aligns it (a later stage). A session that
sent no keyframe for ``close_idle_s`` has its last, incomplete keyframe group associated; the
closure is stored with the cursor, so a replay repeats it at the same point.

Restart: association is a deterministic function of the ordered measurements, so on start the
stage replays every stored measurement of anchored sessions through a fresh writer (no
perception is re-run); then it continues after its cursor. The replay reads map poses and
measurements in chunks of ``REPLAY_CHUNK`` keyframes, never the keyframe payloads (a store
from before map poses were stored has them read once, one at a time, to record them). The
stage checkpoints its association state (``checkpoint.py``) when it stops and every
``checkpoint_s`` at a settled point; a restart starts from a checkpoint of the same
association code and settings and replays only the keyframes after it.

Backlog: ``backlog`` = stored keyframes not yet processed, exported on ``/metrics``.
A keyframe whose perception fails (corrupt image, model error) is counted by reason, logged,
and skipped: the keyframe itself stays stored.

Unexpected errors (a bug, a full disk): the stage logs them, counts a restart on ``/metrics``,
waits (``retry_s``, doubling up to ``max_retry_s``), rebuilds the writer by replay (the
failed round may have left it half-updated) and carries on from its cursor. When the same
keyframe fails ``max_attempts`` times in a row it is skipped as ``internal: <error type>``
(counted with the other failures; the keyframe stays stored), so one bad keyframe cannot stall
the map. Nothing is committed twice: measurements and the cursor move in one transaction.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Final

import numpy as np
from numpy.typing import NDArray

from wardmap.server.association.associator import AssociationConfig, Associator
from wardmap.server.backend.stage import BackendStage
from wardmap.server.decoded import DecodedCache
from wardmap.server.mapping.checkpoint import checkpoint_key, decode_state, encode_state
from wardmap.server.mapping.perceive import MAPPING_CURSOR, KeyframeMeasurer, mapped_pose
from wardmap.server.mapping.workers import MappingConfig
from wardmap.server.mapping.writer import MappedKeyframe, MapWriter, WriterState
from wardmap.server.objectmap import ObjectMap
from wardmap.server.perception.config import PerceptionConfig, measure_config_for
from wardmap.server.perception.models import Segmenter, make_segmenter
from wardmap.server.perception.types import ObjectMeasurement
from wardmap.server.store import Checkpoint, MapStore, Perceived, PerceptionSlot
from wardmap.server.telemetry import ServerTelemetry
from wardmap.shared.errors import ConfigError, WardmapError, WireError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.priority import nice_this_thread
from wardmap.shared.wire import KeyframeMsg, decode_keyframe

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
CURSOR_NAME: Final = MAPPING_CURSOR
WAIT_POLL_S: Final = 0.02
"""How long the stage sleeps while the keyframe it needs next is being measured by a worker."""
MAX_FAILURE_REASON: Final = 120
REPLAY_CHUNK: Final = 500
"""Keyframes read per step of the replay at start (bounds its memory besides the associator's)."""


@dataclass(frozen=True)
class PipelineConfig:
    """The mapping stage (``[pipeline]`` table; perception and association have their own).

    Attributes:
        enabled: run the stage at all (off: the server only stores keyframes).
        poll_s: how long the thread sleeps when no keyframe is waiting.
        batch: keyframes read from the store per round.
        retry_s: first wait after an unexpected error; doubles on each further one.
        max_retry_s: longest wait between attempts.
        max_attempts: attempts at one keyframe before it is skipped as an internal error.
        close_idle_s: a session that sent no keyframe for this long (wall clock, seconds)
            has its last, incomplete keyframe group associated, so what a robot saw before
            it parked or shut down reaches the map; a later keyframe of the session starts a
            new group. 0 = only when the robot starts a new session.
        checkpoint_s: the association state is saved at most this often while keyframes
            come (seconds) and when the stage stops, so a restart replays only what came
            after it; 0 = never (every restart replays every stored measurement).
        rebuild_min_s: least time between two object-map rebuilds after the back-end moved
            keyframes (seconds, stage clock); keyframes mapped meanwhile use the latest poses.
        ready_max_backlog: ``/readyz`` answers 503 while more stored keyframes than this wait
            for the mapping stage (the server stores them but the map falls behind).
    """

    enabled: bool = True
    poll_s: float = 0.2
    batch: int = 8
    retry_s: float = 1.0
    max_retry_s: float = 60.0
    max_attempts: int = 3
    close_idle_s: float = 60.0
    checkpoint_s: float = 600.0
    rebuild_min_s: float = 5.0
    ready_max_backlog: int = 1000

    def __post_init__(self) -> None:
        if not self.poll_s > 0:
            raise ConfigError(f"pipeline.poll_s must be > 0, got {self.poll_s}")
        if self.batch < 1:
            raise ConfigError(f"pipeline.batch must be >= 1, got {self.batch}")
        if not 0 < self.retry_s <= self.max_retry_s:
            raise ConfigError("pipeline: need 0 < retry_s <= max_retry_s")
        if self.max_attempts < 1:
            raise ConfigError(f"pipeline.max_attempts must be >= 1, got {self.max_attempts}")
        if not (math.isfinite(self.close_idle_s) and self.close_idle_s >= 0):
            raise ConfigError(f"pipeline.close_idle_s must be >= 0 (0 = never), got {self.close_idle_s}")
        if not (math.isfinite(self.rebuild_min_s) and self.rebuild_min_s >= 0):
            raise ConfigError(f"pipeline.rebuild_min_s must be >= 0, got {self.rebuild_min_s}")
        if not (math.isfinite(self.checkpoint_s) and self.checkpoint_s >= 0):
            raise ConfigError(f"pipeline.checkpoint_s must be >= 0 (0 = never), got {self.checkpoint_s}")
        if self.ready_max_backlog < 1:
            raise ConfigError(f"pipeline.ready_max_backlog must be >= 1, got {self.ready_max_backlog}")


@dataclass(frozen=True)
class PipelineCounters:
    """A snapshot for ``/metrics``.

    Attributes:
        processed: measured keyframes the stage took in (measured here or by a perception worker).
        measurements: object measurements it stored.
        mapped: keyframes it fed to association (anchored sessions).
        unanchored: keyframes of sessions without ``T_map_odom`` (measured, not mapped).
        replayed: measurements replayed through association at start.
        backlog: stored keyframes not processed yet.
        failures: keyframes skipped, by reason.
        landmarks: landmarks the associator holds.
        restarts: unexpected errors the stage recovered from.
        last_error: the latest of them, ``Type: message`` (empty when none).
        closed_idle: sessions whose last keyframe group this process associated because they
            went quiet (``close_idle_s``).
        floating: instances left out for floating above the floor
            (``PerceptionConfig.floor_gap_m``; keyframes with ``T_odom_base``).
        wall_pieces: instances left out for lying on a surface taller than any object of
            their class (``PerceptionConfig.max_top_m``; keyframes with ``T_odom_base``).
        floor_pieces: instances left out for lying flat on the floor, lower than any object of
            their class (``PerceptionConfig.min_top_m``; keyframes with ``T_odom_base``).
        beyond_range: stored measurements association left out for lying farther than
            ``AssociationConfig.max_range_m`` from their camera.
        skipped: instances perception found but could not measure, by kind
            (:data:`~wardmap.server.perception.measure.SKIP_KINDS`).
        rebuilds: object-map rebuilds after the back-end moved keyframes.
        map_epoch: the map epoch (the back-end's, ``graph_epoch``) whose object map is complete;
            -1 before the stage started.
        settled: the insertion ``rowid`` up to which keyframes are associated and on the object
            map (the cursor moves just before association); -1 before the stage started.
    """

    processed: int
    measurements: int
    mapped: int
    unanchored: int
    replayed: int
    backlog: int
    failures: dict[str, int]
    landmarks: int
    restarts: int = 0
    last_error: str = ""
    closed_idle: int = 0
    floating: int = 0
    beyond_range: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    wall_pieces: int = 0
    floor_pieces: int = 0
    rebuilds: int = 0
    map_epoch: int = -1
    settled: int = -1


@dataclass
class _Counts:
    processed: int = 0
    measurements: int = 0
    mapped: int = 0
    unanchored: int = 0
    replayed: int = 0
    failures: Counter[str] = field(default_factory=Counter)
    restarts: int = 0
    last_error: str = ""
    closed_idle: int = 0
    floating: int = 0
    beyond_range: int = 0
    skipped: Counter[str] = field(default_factory=Counter)
    wall_pieces: int = 0
    floor_pieces: int = 0
    rebuilds: int = 0


class MapPipeline:
    """The mapping stage thread (see the module docstring).

    Args:
        store: the open store (keyframes, measurements, objects).
        objects: the object map on the same store.
        config: stage settings.
        perception: segmenter and measurement settings.
        association: association settings.
        segmenter: a ready segmenter (tests); None builds ``perception.segmenter`` in
            :meth:`start`.
        shared: perception shared out (``[mapping]``): with perception workers on this server
            the stage waits ``wait_s`` for one to claim a keyframe before measuring it itself.
        clock: monotonic seconds, for idle sessions and checkpoint intervals.
        backend: the back-end stage this one follows (started and stopped with it); None
            builds one with default settings.
        telemetry: where the time of each perception, association and rebuild step goes (a
            private one when None).
    """

    def __init__(
        self,
        store: MapStore,
        objects: ObjectMap,
        *,
        config: PipelineConfig | None = None,
        perception: PerceptionConfig | None = None,
        association: AssociationConfig | None = None,
        segmenter: Segmenter | None = None,
        clock: Callable[[], float] = time.monotonic,
        backend: BackendStage | None = None,
        telemetry: ServerTelemetry | None = None,
        shared: MappingConfig | None = None,
    ) -> None:
        self.store = store
        self.shared = shared or MappingConfig()
        self._telemetry = telemetry if telemetry is not None else ServerTelemetry()
        self.backend = backend if backend is not None else BackendStage(store)
        self.decoded: DecodedCache = self.backend.decoded
        """The keyframes ingest decoded (the back-end's; ``server/decoded.py``): hand it to the
        ingest of this process. This stage discards each keyframe once it is processed."""
        self.objects = objects
        self.cfg = config or PipelineConfig()
        self.perception = perception or PerceptionConfig()
        self.association = association or AssociationConfig()
        self._segmenter = segmenter
        self._measurer: KeyframeMeasurer | None = None
        self._clock = clock
        self._unclaimed: tuple[int, float] | None = None  # (rowid, clock) of the keyframe waited for
        self._waiting = False  # the last round stopped at a keyframe a worker is measuring
        self._measure_config = measure_config_for(self.perception, self.perception.segmenter)
        self._kg = KnowledgeGraph.load()
        self._rebuild_after = 0.0
        self._reset()
        self._lock = threading.Lock()  # guards _counts and _backlog for counters()
        self._counts = _Counts()
        self._backlog = 0
        # Rowid up to which keyframes are stored *and* associated and written to the object map
        # (the cursor moves before association): what wait_idle waits for.
        self._settled = -1
        # The map epoch whose rebuild is complete (what wait_idle waits for; -1 before start).
        self._done_epoch = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        """Build the segmenter (fails here on a bad model), replay association, start the thread.

        Raises:
            ConfigError: the segmenter cannot be built (missing or bad model file).
        """
        if self._segmenter is None:
            self._segmenter = make_segmenter(self.perception.segmenter, self.perception)
        self._measurer = KeyframeMeasurer(self._segmenter, self.perception, self._kg)
        self.backend.start()
        self._replay()
        self._settle()
        self._done_epoch = self._epoch
        self._thread = threading.Thread(target=self._main, name="map-pipeline", daemon=True)
        self._thread.start()
        log.info("mapping stage started (segmenter %s)", self.perception.segmenter)

    def stop(self) -> None:
        """Stop after the keyframe in progress (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self.backend.stop()

    def counters(self) -> PipelineCounters:
        with self._lock:
            c = self._counts
            return PipelineCounters(c.processed, c.measurements, c.mapped, c.unanchored, c.replayed,
                                    self._backlog, dict(c.failures), len(self._writer.landmarks()),
                                    c.restarts, c.last_error, c.closed_idle, c.floating, c.beyond_range,
                                    dict(c.skipped), c.wall_pieces, c.floor_pieces, c.rebuilds,
                                    self._done_epoch, self._settled)

    def running(self) -> bool:
        """Whether this stage's thread and the back-end's run (started, not stopped, not died)."""
        thread = self._thread
        return (thread is not None and thread.is_alive() and not self._stop.is_set() and self._error is None
                and self.backend.running())

    def wait_idle(self, timeout_s: float) -> bool:
        """Block until every stored keyframe is measured, associated and on the object map at the
        back-end's latest poses (tests, the demo); True if that happened in time. Idle-session
        closures are not waited for."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._error is not None:
                raise WardmapError(f"mapping stage failed: {self._error}") from self._error
            with self._lock:
                settled, epoch = self._settled, self._done_epoch
            if (settled >= 0 and self.store.count_keyframes_after(settled) == 0
                    and self.store.graph_epoch() == epoch):
                return True
            time.sleep(0.05)
        return False

    @property
    def writer(self) -> MapWriter:
        """The map writer the stage feeds (replaced when the stage recovers from an error)."""
        return self._writer

    # ------------------------------------------------------------------ thread

    def _main(self) -> None:
        nice_this_thread(self.shared.nice)  # ingest, in this process too, comes first
        delay = self.cfg.retry_s
        failing: tuple[int, int] | None = None  # (cursor, consecutive failures there)
        settled = True  # the writer holds exactly the keyframes up to the cursor
        while not self._stop.is_set():
            try:
                if self.store.graph_epoch() != self._epoch and self._clock() >= self._rebuild_after:
                    self._rebuild()
                done = self._round()
                self._settle()
                self.close_idle()  # also while other robots keep the stage busy
                settled = True
                if self._clock() - self._checkpoint_at >= self.cfg.checkpoint_s:
                    self._checkpoint()
                if done == 0:
                    self._stop.wait(WAIT_POLL_S if self._waiting else self.cfg.poll_s)
                delay, failing = self.cfg.retry_s, None
            except Exception as exc:  # any bug: log, back off, recover
                settled = False
                text = f"{type(exc).__name__}: {exc}"[:MAX_FAILURE_REASON]
                with self._lock:
                    self._counts.restarts += 1
                    self._counts.last_error = text
                log.exception("mapping stage: unexpected error; retrying in %.1f s", delay)
                if self._stop.wait(delay):
                    break
                delay = min(2.0 * delay, self.cfg.max_retry_s)
                try:
                    cursor = self._cursor()
                    failing = (cursor, failing[1] + 1 if failing and failing[0] == cursor else 1)
                    if failing[1] >= self.cfg.max_attempts:
                        self._skip_after(cursor, f"internal: {type(exc).__name__}")
                        failing = None
                    self._reset()
                    self._replay()
                    self._settle()
                    with self._lock:
                        self._done_epoch = self._epoch
                    settled = True
                except Exception:  # e.g. the database is still unreadable
                    log.exception("mapping stage: recovery failed; retrying")
            except BaseException as exc:  # reported by wait_idle and logged; ingest keeps running
                self._error = exc
                log.exception("mapping stage stopped")
                return
        if settled:
            self._checkpoint()

    def _skip_after(self, cursor: int, reason: str) -> None:
        """Mark the first keyframe after ``cursor`` processed with no measurements, counted as ``reason``."""
        rows = self.store.next_keyframes(cursor, 1)
        if not rows:
            return
        kf = rows[0]
        log.error("mapping stage: keyframe %s failed %d times; skipped (%s)",
                  kf.key, self.cfg.max_attempts, reason)
        unmeasured = mapped_pose(kf.robot_id, kf.session_id, kf.seq, None)
        self.store.commit_keyframe(CURSOR_NAME, kf.rowid, unmeasured, [], anchored=False)
        with self._lock:
            self._counts.failures[reason] += 1

    def _rebuild(self) -> None:
        """Re-associate every mapped keyframe at the back-end's current poses and replace the
        object map with the result (objects association no longer finds are deleted): after a
        loop closure or an anchoring moved keyframes (the graph epoch changed)."""
        started = time.monotonic()
        before = set(self.objects.ids())
        self._reset()
        self._replay()
        after = {lm.id for lm in self._writer.landmarks()}
        for gone in sorted(before - after):
            self.objects.delete(gone)
        self._settle()
        self._rebuild_after = self._clock() + self.cfg.rebuild_min_s
        self._telemetry.mapping("rebuild", time.monotonic() - started)
        with self._lock:
            self._counts.rebuilds += 1
            self._done_epoch = self._epoch
        log.info("mapping stage: object map rebuilt at map epoch %d in %.1f s (%d objects, %d removed)",
                 self._epoch, time.monotonic() - started, len(after), len(before - after))

    def _round(self) -> int:
        done_by_backend = self.backend.cursor()
        slots = self.store.perception_slots(self._cursor(), done_by_backend, self.cfg.batch)
        done = 0
        self._waiting = False
        for slot in slots:
            if self._stop.is_set():
                break
            result = slot.result if slot.result is not None else self._measure_here(slot)
            if result is None:  # a worker measures it (or may claim it soon): keep the order
                self._waiting = True
                break
            self._process(slot.rowid, slot.key, result)
            done += 1
        with self._lock:
            self._backlog = self.store.count_keyframes_after(self._cursor())
        return done

    def _measure_here(self, slot: PerceptionSlot) -> Perceived | None:
        """The keyframe measured by this stage, or None while a worker holds a live claim on it or,
        with workers on this server, it has waited less than ``wait_s`` unclaimed. The stage takes
        no claim: a worker that claims the keyframe meanwhile measures it again, and whichever
        result comes second is dropped (both are the same measurement)."""
        if slot.claim_expires_s is not None and slot.claim_expires_s > time.time():
            return None
        wait_s = self.shared.wait_s if self.shared.perception_workers > 0 else 0.0
        if wait_s > 0:
            if self._unclaimed is None or self._unclaimed[0] != slot.rowid:
                self._unclaimed = (slot.rowid, self._clock())
            if self._clock() - self._unclaimed[1] < wait_s:
                return None
        if self._measurer is None:
            raise WardmapError("the mapping stage measures keyframes only once started")
        payload = self.store.payload(slot.robot_id, slot.session_id, slot.seq)
        if payload is None:
            raise WardmapError(f"keyframe {slot.key} is not stored")
        started = time.perf_counter()
        measured = self._measurer.measure(slot.key, payload, self.decoded)
        self._telemetry.mapping("perception", time.perf_counter() - started)
        left = measured.left_out
        with self._lock:
            self._counts.floating += left.floating
            self._counts.wall_pieces += left.walls
            self._counts.floor_pieces += left.floors
            self._counts.skipped.update(measured.skipped)
        return measured.result

    def _process(self, rowid: int, key: str, result: Perceived) -> None:
        """Commit a keyframe's perception result with the cursor, then associate it when its
        session is on the map."""
        pose = result.pose
        self.store.commit_keyframe(CURSOR_NAME, rowid, pose, result.measurements, anchored=result.anchored)
        self.decoded.discard(key)  # this stage reads a keyframe last
        if result.failure is not None:
            with self._lock:
                self._counts.failures[result.failure] += 1
            return
        with self._lock:
            self._counts.processed += 1
            self._counts.measurements += len(result.measurements)
        node = (pose.robot_id, pose.session_id, pose.seq)
        T_map_camera = self.store.graph_poses([node])[node]
        if T_map_camera is None or pose.camera is None:
            with self._lock:
                self._counts.unanchored += 1
            return
        moved = on_map(result.measurements, pose.T_map_camera, T_map_camera)
        stream = f"{pose.robot_id}/{pose.session_id}"
        self.associate([MappedKeyframe(stream, T_map_camera, pose.camera, moved)])

    def associate(self, keyframes: Iterable[MappedKeyframe]) -> None:
        """Feed measured keyframes of anchored sessions to the writer in order and write the
        changes to the object map; counts them as mapped. The stage's thread calls it; call it
        yourself only on a stage that is not started."""
        writer = self._writer
        for kf in keyframes:
            self._last_seen[kf.stream] = self._clock()
            started = time.perf_counter()
            far = writer.associate(kf)
            self._telemetry.mapping("association", time.perf_counter() - started)
            with self._lock:
                self._counts.mapped += 1
                self._counts.beyond_range += far
        writer.write()

    def close_idle(self) -> list[str]:
        """Associate the open keyframe group of every session quiet for ``close_idle_s`` (whose
        stored keyframes are all processed); the closure is stored with the cursor first, so
        replay repeats it at the same point. Returns the sessions closed (``"<robot>/<session>"``).
        The stage's thread calls it; call it yourself only on a stage that is not started."""
        if self.cfg.close_idle_s <= 0:
            return []
        now = self._clock()
        quiet = sorted(stream for stream in self._writer.open_streams.values()
                       if now - self._last_seen.get(stream, now) >= self.cfg.close_idle_s)
        if not quiet:
            return []
        cursor = self._cursor()
        # A session whose keyframes wait behind other robots' backlog is not idle.
        quiet = [stream for stream in quiet
                 if not self.store.session_has_keyframes_after(*_split_stream(stream), cursor)]
        if not quiet:
            return []
        self.store.close_sessions([_split_stream(stream) for stream in quiet], cursor)
        self._writer.close(quiet)
        with self._lock:
            self._counts.closed_idle += len(quiet)
        log.info("mapping stage: closed the last keyframe group of idle session(s) %s", ", ".join(quiet))
        return quiet

    def _reset(self) -> None:
        """A fresh writer at the current map epoch, and no checkpoint written by it yet."""
        self._epoch = self.store.graph_epoch()
        self._new_writer()
        self._checkpointed: tuple[int, int] | None = None  # (cursor, closures there) of the last one
        self._checkpoint_at = self._clock()

    def _new_writer(self, state: WriterState | None = None) -> None:
        self._writer = MapWriter(self.objects, self.association, hist_bins=self._measure_config.hist_bins,
                                 knowledge=self._kg, state=state)
        now = self._clock()
        # stream -> clock time of its last keyframe
        self._last_seen: dict[str, float] = {stream: now for stream in self._writer.open_streams.values()}

    # ------------------------------------------------------------------ storage

    def _cursor(self) -> int:
        return self.store.cursor(CURSOR_NAME)

    def _settle(self) -> None:
        cursor = self._cursor()
        with self._lock:
            self._settled = cursor

    def _replay(self) -> None:
        """Rebuild the writer from stored measurements of anchored keyframes, in order.

        Keyframes are read in chunks of ``REPLAY_CHUNK`` (map pose, camera and measurements);
        no keyframe payload is read (except once, to record the map pose of keyframes a
        version before it processed).
        """
        cursor = self._cursor()
        if cursor == 0:
            return
        self._backfill(cursor)
        start, applied = self._restore(cursor)
        closures: dict[int, list[str]] = {}
        for c in self.store.closed_sessions(start, cursor):
            stream = f"{c.robot_id}/{c.session_id}"
            if not (c.at_rowid == start and stream in applied):
                closures.setdefault(c.at_rowid, []).append(stream)
        counts = [0, 0]  # keyframes, measurements
        after = start
        for end in [*sorted(closures), cursor]:
            self._replay_range(after, end, counts)
            if self._stop.is_set():
                break
            self._writer.close(closures.get(end, []))
            after = end
        keyframes, replayed = counts
        with self._lock:
            self._counts.replayed = replayed
            self._counts.mapped = 0
        log.info("mapping stage: replayed %d measurements of %d keyframes", replayed, keyframes)

    def _checkpoint_key(self) -> str:
        return f"{checkpoint_key(self.association, self._measure_config.hist_bins)} epoch={self._epoch}"

    def _checkpoint(self) -> None:
        """Save the association state at the current cursor, which it must match (a settled
        stage). Skipped when nothing changed since the last one or ``checkpoint_s`` is 0; a
        failure (a full disk) is logged, and a later restart replays from an older one."""
        if self.cfg.checkpoint_s <= 0:
            return
        self._checkpoint_at = self._clock()
        try:
            cursor = self._cursor()
            at_cursor = self.store.closed_sessions(cursor, cursor)
            closed = sorted(f"{c.robot_id}/{c.session_id}" for c in at_cursor)
            if (cursor, len(closed)) == self._checkpointed:
                return
            w = self._writer.state()
            state = encode_state({"associator": w.associator, "hist_sum": w.hist_sum,
                                  "open_stream": w.open_stream, "closed_at_cursor": closed})
            self.store.save_checkpoint(Checkpoint(cursor, self._checkpoint_key(), state, time.time()))
            self._checkpointed = (cursor, len(closed))
            log.info("mapping stage: association checkpoint at keyframe %d (%d landmarks, %.1f MB)", cursor,
                     len(w.associator.landmarks()), len(state) / 1e6)
        except Exception:
            log.exception("mapping stage: association checkpoint not written")

    def _restore(self, cursor: int) -> tuple[int, set[str]]:
        """Load the association checkpoint if it is usable: ``(its cursor, the closures at that
        cursor it holds)``; ``(0, set())`` (replay everything) when there is none, it was made
        by other association code or settings, lies beyond ``cursor`` or cannot be read."""
        if self.cfg.checkpoint_s <= 0:
            return 0, set()
        saved = self.store.checkpoint()
        if saved is None:
            return 0, set()
        at = saved.last_rowid
        if saved.config_key != self._checkpoint_key():
            log.info("mapping stage: the association checkpoint is of other code or settings; replaying all")
            return 0, set()
        if at > cursor:
            log.warning("mapping stage: the association checkpoint (keyframe %d) lies beyond the cursor "
                        "(%d); replaying all", at, cursor)
            return 0, set()
        try:
            state = decode_state(saved.state)
            associator, hist_sum, open_stream = state["associator"], state["hist_sum"], state["open_stream"]
            applied = set(state["closed_at_cursor"])
            if not (isinstance(associator, Associator) and isinstance(hist_sum, dict)
                    and isinstance(open_stream, dict)):
                raise TypeError("unexpected contents")
        except Exception as exc:  # any decoding error: the full replay is always correct
            log.warning("mapping stage: the association checkpoint cannot be read (%s: %s); replaying all",
                        type(exc).__name__, exc)
            return 0, set()
        self._new_writer(WriterState(associator, hist_sum, open_stream))
        self._checkpointed = (at, len(applied))
        log.info("mapping stage: association restored from its checkpoint at keyframe %d (%d landmarks)", at,
                 len(associator.landmarks()))
        return at, applied

    def _replay_range(self, after: int, end: int, counts: list[int]) -> None:
        """Replay the keyframes with ``after < rowid <= end`` (see :meth:`_replay`)."""
        while not self._stop.is_set():
            rows = self.store.anchored_keyframes(after, end, REPLAY_CHUNK)
            if not rows:
                break
            self.associate(MappedKeyframe(f"{kf.robot_id}/{kf.session_id}", kf.T_map_camera, kf.camera,
                                          on_map(kf.measurements, kf.T_measured_camera, kf.T_map_camera))
                           for kf in rows)
            counts[0] += len(rows)
            counts[1] += sum(len(kf.measurements) for kf in rows)
            after = rows[-1].rowid

    def _backfill(self, cursor: int) -> None:
        """Record the map pose of processed keyframes that have none (stores written before
        map poses were stored), decoding their payloads one at a time."""
        done = 0
        while True:
            rows = self.store.unmapped_keyframes(cursor, REPLAY_CHUNK)
            if not rows:
                break
            filled = []
            for kf in rows:
                payload = self.store.payload(kf.robot_id, kf.session_id, kf.seq)
                try:
                    msg: KeyframeMsg | None = None if payload is None else decode_keyframe(payload)
                except WireError:
                    msg = None  # it was skipped the first time too (counted then)
                filled.append(mapped_pose(kf.robot_id, kf.session_id, kf.seq, msg))
            self.store.record_mapped(filled)
            done += len(filled)
        if done:
            log.info("mapping stage: recorded the map pose of %d keyframes processed by an older version",
                     done)


# ---------------------------------------------------------------------------- helpers


def _split_stream(stream: str) -> tuple[str, str]:
    robot_id, session_id = stream.split("/", 1)
    return robot_id, session_id


def on_map(measurements: Sequence[ObjectMeasurement], T_measured_camera: F64 | None,
           T_map_camera: F64) -> list[ObjectMeasurement]:
    """``measurements`` computed with the camera at ``T_measured_camera`` moved to the map, where
    the back-end now puts that camera (``T_map_camera``): every world-frame pose is
    premultiplied by ``T_map_camera @ inv(T_measured_camera)``, so measurements follow their
    keyframe (relative poses, sizes and points in the camera frame are unchanged)."""
    if T_measured_camera is None:
        return list(measurements)
    delta = np.asarray(T_map_camera, np.float64) @ np.linalg.inv(np.asarray(T_measured_camera, np.float64))
    if np.allclose(delta, np.eye(4), atol=1e-12):
        return list(measurements)
    return [replace(m, T_world_camera=delta @ m.T_world_camera, T_world_object=delta @ m.T_world_object)
            for m in measurements]


PipelineFactory = Callable[[MapStore, ObjectMap, DecodedCache], MapPipeline]

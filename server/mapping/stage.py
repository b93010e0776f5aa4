"""The map server's mapping stage: stored keyframes -> perception -> association -> object map.

Ingest stores a keyframe and acks it (``server/ingest.py``); this stage runs behind it in its
own thread and never delays an ack. It reads keyframes from the store in insertion order
(SQLite ``rowid``), and for each one:

1. decodes the payload (JPEG colour, depth upsampled to the colour size, intrinsics);
2. runs the segmenter (``server/perception/models.py``: the trained network by default) and
   measures every non-``moving`` instance in 3D (paper 000 Eq. 1, ``measure.py``);
3. commits the measurements, the keyframe's map pose and camera (``mapped_keyframes``), and
   its cursor in one transaction (``measurements``, ``pipeline_cursor``), so a crash never
   loses or repeats one;
4. when the keyframe's session is on the map (the robot sent ``T_map_odom``, docs/wire.md),
   feeds the measurements, in the map frame, to the :class:`Associator` (paper 000:
   keyframe groups per robot session, HDP across groups), and writes the landmarks it
   created or changed into the :class:`ObjectMap` (which publishes them on Zenoh). The
   first keyframe of a robot's new session first closes its previous session's last,
   incomplete group (``Associator.flush``).

Sessions without ``T_map_odom`` are measured and counted (``unanchored``) but not mapped: their
odom frame is unknown in the map until loop closure aligns it (a later stage).

Restart: association is a deterministic function of the ordered measurements, so on start the
stage replays every stored measurement of anchored sessions through a fresh associator (no
perception is re-run) and upserts the landmarks; then it continues after its cursor. The
replay reads ``mapped_keyframes`` and ``measurements`` in chunks of ``REPLAY_CHUNK``
keyframes, never the keyframe payloads (a store from before schema v4 has them read once, one
at a time, to fill ``mapped_keyframes``). The stage checkpoints its association state (the
pickled associator, colour sums and open sessions, with the cursor and the idle closures at
it; table ``association_checkpoint``) when it stops and every ``checkpoint_s`` at a settled
point; a restart starts from a checkpoint of the same association code and settings and
replays only the keyframes after it (association costs 7-19 ms per keyframe,
bench/association_revisits.py, so a full replay grows with the store's history).

Backlog: ``backlog`` = stored keyframes not yet processed, exported on ``/metrics``.
A keyframe whose perception fails (corrupt image, model error) is counted by reason, logged,
and skipped: the keyframe itself stays stored.

Unexpected errors (a bug, a full disk): the stage logs them, counts a restart on ``/metrics``,
waits (``retry_s``, doubling up to ``max_retry_s``), rebuilds the associator by replay (the
failed round may have left it half-updated) and carries on from its cursor. When the same
keyframe fails ``max_attempts`` times in a row it is skipped as ``internal: <error type>``
(counted with the other failures; the keyframe stays stored), so one bad keyframe cannot stall
the map. Nothing is committed twice: measurements and the cursor move in one transaction.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import pickle
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Final

import cv2
import msgpack
import numpy as np
from numpy.typing import NDArray

from wardmap.server.association.associator import AssociationConfig, Associator
from wardmap.server.association.types import Landmark, LandmarkChange
from wardmap.server.codedigest import code_digest
from wardmap.server.objectmap import ObjectMap, from_landmark
from wardmap.server.perception.measure import mean_rgb, measure_instances_report
from wardmap.server.perception.models import (
    PerceptionConfig,
    Segmenter,
    drop_misplaced,
    make_segmenter,
    measure_config_for,
    split_instances,
)
from wardmap.server.perception.types import ObjectMeasurement
from wardmap.server.store import SqliteKeyframeStore, pose_blob, pose_from_blob
from wardmap.shared.camera import PinholeCamera
from wardmap.shared.config import to_mapping
from wardmap.shared.errors import ConfigError, WardmapError, WireError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.wire import KeyframeMsg, decode_depth, decode_keyframe

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
CURSOR_NAME: Final = "mapping"
MAX_FAILURE_REASON: Final = 120
_INSERT_MAPPED: Final = ("INSERT OR REPLACE INTO mapped_keyframes (robot_id, session_id, seq, T_map_camera, "
                         "camera) VALUES (?, ?, ?, ?, ?)")
REPLAY_CHUNK: Final = 500
"""Keyframes read per step of the replay at start (bounds its memory besides the associator's)."""
CHECKPOINT_FORMAT: Final = 1
"""Bumped when the checkpoint's contents change shape (part of its key)."""


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
    """

    enabled: bool = True
    poll_s: float = 0.2
    batch: int = 8
    retry_s: float = 1.0
    max_retry_s: float = 60.0
    max_attempts: int = 3
    close_idle_s: float = 60.0
    checkpoint_s: float = 600.0

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
        if not (math.isfinite(self.checkpoint_s) and self.checkpoint_s >= 0):
            raise ConfigError(f"pipeline.checkpoint_s must be >= 0 (0 = never), got {self.checkpoint_s}")


@dataclass(frozen=True)
class PipelineCounters:
    """A snapshot for ``/metrics``.

    Attributes:
        processed: keyframes this process ran through perception.
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


class MapPipeline:
    """The mapping stage thread (see the module docstring).

    Args:
        store: the open keyframe store (its file also holds measurements and objects).
        objects: the object map on the same store.
        config: stage settings.
        perception: segmenter and measurement settings.
        association: association settings.
        segmenter: a ready segmenter (tests); None builds ``perception.segmenter`` in
            :meth:`start`.
    """

    def __init__(
        self,
        store: SqliteKeyframeStore,
        objects: ObjectMap,
        *,
        config: PipelineConfig | None = None,
        perception: PerceptionConfig | None = None,
        association: AssociationConfig | None = None,
        segmenter: Segmenter | None = None,
    ) -> None:
        self.store = store
        self.objects = objects
        self.cfg = config or PipelineConfig()
        self.perception = perception or PerceptionConfig()
        self.association = association or AssociationConfig()
        self._segmenter = segmenter
        self._measure_config = measure_config_for(self.perception, self.perception.segmenter)
        self._kg = KnowledgeGraph.load()
        self._moving = {c.name for c in self._kg.classes if str(c.mobility) == "moving"}
        self._new_associator()
        self._lock = threading.Lock()  # guards _counts and _backlog for counters()
        self._counts = _Counts()
        self._backlog = 0
        # Rowid up to which keyframes are stored *and* associated and written to the object map
        # (the cursor moves before association): what wait_idle waits for.
        self._settled = -1
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
        self._replay()
        self._settle()
        self._thread = threading.Thread(target=self._main, name="map-pipeline", daemon=True)
        self._thread.start()
        log.info("mapping stage started (segmenter %s)", self.perception.segmenter)

    def stop(self) -> None:
        """Stop after the keyframe in progress (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def counters(self) -> PipelineCounters:
        with self._lock:
            c = self._counts
            return PipelineCounters(c.processed, c.measurements, c.mapped, c.unanchored, c.replayed,
                                    self._backlog, dict(c.failures), len(self._associator.landmarks()),
                                    c.restarts, c.last_error, c.closed_idle, c.floating, c.beyond_range,
                                    dict(c.skipped), c.wall_pieces, c.floor_pieces)

    def wait_idle(self, timeout_s: float) -> bool:
        """Block until every stored keyframe is measured, associated and on the object map (tests,
        the demo); True if that happened in time. Idle-session closures are not waited for."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._error is not None:
                raise WardmapError(f"mapping stage failed: {self._error}") from self._error
            with self._lock:
                settled = self._settled
            if settled >= 0 and self._pending(after=settled) == 0:
                return True
            time.sleep(0.05)
        return False

    # ------------------------------------------------------------------ thread

    def _main(self) -> None:
        delay = self.cfg.retry_s
        failing: tuple[int, int] | None = None  # (cursor, consecutive failures there)
        settled = True  # the associator holds exactly the keyframes up to the cursor
        while not self._stop.is_set():
            try:
                done = self._round()
                self._settle()
                self._close_idle()  # also while other robots keep the stage busy
                settled = True
                if time.monotonic() - self._checkpoint_at >= self.cfg.checkpoint_s:
                    self._checkpoint()
                if done == 0:
                    self._stop.wait(self.cfg.poll_s)
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
                    self._new_associator()
                    self._replay()
                    self._settle()
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
        with self.store.reading("mapping: keyframe to skip") as conn:
            row = conn.execute(
                "SELECT rowid, robot_id, session_id, seq FROM keyframes WHERE rowid > ? "
                "ORDER BY rowid LIMIT 1",
                (cursor,),
            ).fetchone()
        if row is None:
            return
        key = f"{row[1]}/{row[2]}/{int(row[3])}"
        log.error("mapping stage: keyframe %s failed %d times; skipped (%s)",
                  key, self.cfg.max_attempts, reason)
        self._commit(int(row[0]), key, msg=None, measurements=[])
        with self._lock:
            self._counts.failures[reason] += 1

    def _round(self) -> int:
        cursor = self._cursor()
        with self.store.reading("mapping: next keyframes") as conn:
            rows = conn.execute(
                "SELECT rowid, robot_id, session_id, seq, payload FROM keyframes WHERE rowid > ? "
                "ORDER BY rowid LIMIT ?",
                (cursor, self.cfg.batch),
            ).fetchall()
        for rowid, robot_id, session_id, seq, payload in rows:
            if self._stop.is_set():
                break
            self._process(int(rowid), f"{robot_id}/{session_id}/{int(seq)}", bytes(payload))
        with self._lock:
            self._backlog = self._pending()
        return len(rows)

    def _process(self, rowid: int, key: str, payload: bytes) -> None:
        try:
            msg = decode_keyframe(payload)
            measurements = self._measure(msg, key)
        except (WardmapError, WireError, cv2.error, ValueError) as exc:
            reason = f"{type(exc).__name__}: {exc}"[:MAX_FAILURE_REASON]
            log.warning("keyframe %s: perception skipped: %s", key, reason)
            with self._lock:
                self._counts.failures[type(exc).__name__] += 1
            self._commit(rowid, key, msg=None, measurements=[])
            return
        self._commit(rowid, key, msg, measurements)
        with self._lock:
            self._counts.processed += 1
            self._counts.measurements += len(measurements)
        if msg.T_map_odom is None:
            with self._lock:
                self._counts.unanchored += 1
            return
        self._associate([_MappedKeyframe(f"{msg.robot_id}/{msg.session_id}", map_pose(msg), camera_of(msg),
                                         measurements)])

    def _measure(self, msg: KeyframeMsg, key: str) -> list[ObjectMeasurement]:
        bgr, depth, camera = decode_images(msg)
        assert self._segmenter is not None
        instances = split_instances(self._segmenter(bgr, depth), depth, camera, self.perception,
                                    self.perception.segmenter)
        instances = [i for i in instances if i.category not in self._moving]
        T_map_camera, floor = map_pose(msg), floor_height(msg)
        instances, left = drop_misplaced(instances, depth, camera, self.perception, T_map_camera, floor)
        if any(left):
            log.debug("keyframe %s: %d instance(s) float above the floor, %d lie on a taller surface, "
                      "%d lie flat on the floor; left out", key, *left)
            with self._lock:
                self._counts.floating += left.floating
                self._counts.wall_pieces += left.walls
                self._counts.floor_pieces += left.floors
        report = measure_instances_report(
            instances, bgr=bgr, depth_m=depth, camera=camera, T_world_camera=T_map_camera,
            keyframe=key, stamp=msg.stamp, config=self._measure_config,
        )
        if report.skipped:
            with self._lock:
                self._counts.skipped.update(skip.kind for skip in report.skipped)
        return report.measurements

    def _associate(self, keyframes: Iterable[_MappedKeyframe]) -> None:
        touched: dict[int, Landmark] = {}
        new: dict[int, list[ObjectMeasurement]] = {}
        for kf in keyframes:
            # A robot's new session ends its previous one: that session's last, incomplete
            # keyframe group is associated now (it would wait for keyframes that never come).
            # Decided from the keyframe order alone, so replay repeats it exactly.
            robot = kf.stream.split("/", 1)[0]
            previous = self._open_stream.get(robot)
            if previous is not None and previous != kf.stream:
                self._collect(self._associator.flush(previous), touched, new)
            self._open_stream[robot] = kf.stream
            self._last_seen[kf.stream] = time.monotonic()
            far = self._associator.beyond_range
            changes = self._associator.add_keyframe(
                for_association(kf.measurements), kf.T_map_camera, kf.camera, stream=kf.stream
            )
            self._collect(changes, touched, new)
            with self._lock:
                self._counts.mapped += 1
                self._counts.beyond_range += self._associator.beyond_range - far
        self._write_landmarks(touched.values(), new)

    def _close_idle(self) -> None:
        """Associate the open keyframe group of every session quiet for ``close_idle_s``; the
        closure is stored with the cursor first, so replay repeats it at the same point."""
        if self.cfg.close_idle_s <= 0:
            return
        now = time.monotonic()
        quiet = sorted(stream for stream in self._open_stream.values()
                       if now - self._last_seen.get(stream, now) >= self.cfg.close_idle_s)
        if not quiet:
            return
        cursor = self._cursor()
        with self.store.reading("mapping: idle sessions") as conn:
            # A session whose keyframes wait behind other robots' backlog is not idle.
            quiet = [stream for stream in quiet if conn.execute(
                "SELECT 1 FROM keyframes WHERE robot_id = ? AND session_id = ? AND rowid > ? LIMIT 1",
                (*stream.split("/", 1), cursor)).fetchone() is None]
        if not quiet:
            return
        with self.store.writing("mapping: close idle sessions") as conn:
            conn.executemany(
                "INSERT OR IGNORE INTO closed_sessions (robot_id, session_id, at_rowid) VALUES (?, ?, ?)",
                [(*stream.split("/", 1), cursor) for stream in quiet],
            )
        self._close(quiet)
        with self._lock:
            self._counts.closed_idle += len(quiet)
        log.info("mapping stage: closed the last keyframe group of idle session(s) %s", ", ".join(quiet))

    def _close(self, streams: Iterable[str]) -> None:
        """Flush the streams' open groups into the map; each robot then has no open session."""
        touched: dict[int, Landmark] = {}
        new: dict[int, list[ObjectMeasurement]] = {}
        for stream in streams:
            self._collect(self._associator.flush(stream), touched, new)
            robot = stream.split("/", 1)[0]
            if self._open_stream.get(robot) == stream:
                del self._open_stream[robot]
        self._write_landmarks(touched.values(), new)

    def _new_associator(self) -> None:
        # The database holds every measurement; the live associator only each landmark's recent ones.
        self._associator = Associator(replace(self.association, keep_measurements=False), self._kg)
        # Per landmark, the running sum of its measurements' colour histograms.
        self._hist_sum: dict[int, NDArray[np.float64]] = {}
        # Landmarks the associator merged into another, in order, waiting to be written.
        self._merges: list[tuple[int, int]] = []
        self._open_stream: dict[str, str] = {}  # robot -> its session being associated
        self._last_seen: dict[str, float] = {}  # stream -> monotonic time of its last keyframe
        self._checkpointed: tuple[int, int] | None = None  # (cursor, closures there) of the last one
        self._checkpoint_at = time.monotonic()

    def _collect(self, changes: Iterable[LandmarkChange], touched: dict[int, Landmark],
                 new: dict[int, list[ObjectMeasurement]]) -> None:
        """Take the measurements each change added and add their colour histograms to the
        landmark's running sum; note merged landmarks (:meth:`_write_landmarks` deletes them)."""
        bins = self._measure_config.hist_bins
        for change in changes:
            lm = change.landmark
            if change.kind == "merged":
                gone = self._hist_sum.pop(lm.id, None)
                if gone is not None:
                    self._hist_sum[change.into] = self._hist_sum.get(change.into, 0.0) + gone
                self._merges.append((lm.id, change.into))
                continue
            hists = [np.asarray(m.color_hist, np.float64) for m in change.added
                     if np.shape(m.color_hist) == (bins[0] * bins[1] * bins[2],)]
            if hists:
                self._hist_sum[lm.id] = self._hist_sum.get(lm.id, 0.0) + np.sum(hists, axis=0)
            new.setdefault(lm.id, []).extend(change.added)
            touched[lm.id] = lm

    def _write_landmarks(self, landmarks: Iterable[Landmark],
                         new: dict[int, list[ObjectMeasurement]]) -> None:
        """Upsert the landmarks (their latest state) with only the observations ``new`` to them
        (:meth:`_collect`), so an update costs the same however often the object has been seen."""
        states, observations = [], []
        bins = self._measure_config.hist_bins
        for lm in landmarks:
            total = self._hist_sum.get(lm.id)
            colour = None if total is None else mean_rgb([total], bins)
            state, obs = from_landmark(lm.id, lm.category, lm.confidence, lm.T_world_object, lm.size,
                                       new.get(lm.id, []), colour, lm.confirmed)
            states.append(state)
            observations.extend(obs)
        if states:
            self.objects.upsert(states, observations)
        merges, self._merges = self._merges, []
        for gone, into in merges:
            # After the upsert: ``into`` may be new. ``gone`` exists: it was written when created.
            self.objects.delete(gone, merged_into=into)

    # ------------------------------------------------------------------ storage

    def _cursor(self) -> int:
        with self.store.reading("mapping: cursor") as conn:
            row = conn.execute(
                "SELECT last_rowid FROM pipeline_cursor WHERE name = ?", (CURSOR_NAME,)
            ).fetchone()
        return int(row[0]) if row else 0

    def _settle(self) -> None:
        cursor = self._cursor()
        with self._lock:
            self._settled = cursor

    def _pending(self, after: int | None = None) -> int:
        """Stored keyframes after ``after`` (default: the cursor)."""
        cursor = self._cursor() if after is None else after
        with self.store.reading("mapping: backlog") as conn:
            row = conn.execute("SELECT COUNT(*) FROM keyframes WHERE rowid > ?", (cursor,)).fetchone()
        return int(row[0])

    def _commit(self, rowid: int, key: str, msg: KeyframeMsg | None,
                measurements: Sequence[ObjectMeasurement]) -> None:
        robot_id, session_id, seq = key.split("/")
        anchored = msg is not None and msg.T_map_odom is not None
        pose, camera = _mapped_row(msg)
        with self.store.writing("mapping: store measurements") as conn:
            conn.executemany(
                "INSERT INTO measurements (robot_id, session_id, seq, anchored, payload) "
                "VALUES (?, ?, ?, ?, ?)",
                [(robot_id, session_id, int(seq), int(anchored), pack_measurement(m)) for m in measurements],
            )
            conn.execute(_INSERT_MAPPED, (robot_id, session_id, int(seq), pose, camera))
            conn.execute(
                "INSERT INTO pipeline_cursor (name, last_rowid) VALUES (?, ?) "
                "ON CONFLICT(name) DO UPDATE SET last_rowid = excluded.last_rowid",
                (CURSOR_NAME, rowid),
            )

    def _replay(self) -> None:
        """Rebuild the associator from stored measurements of anchored keyframes, in order.

        Keyframes are read in chunks of ``REPLAY_CHUNK`` from ``mapped_keyframes`` (pose and
        camera) and ``measurements``; no keyframe payload is read (except once, to fill
        ``mapped_keyframes`` for keyframes a version before it processed).
        """
        cursor = self._cursor()
        if cursor == 0:
            return
        self._backfill(cursor)
        start, applied = self._restore(cursor)
        with self.store.reading("mapping: closed sessions") as conn:
            closures: dict[int, list[str]] = {}
            for at, robot_id, session_id in conn.execute(
                "SELECT at_rowid, robot_id, session_id FROM closed_sessions WHERE at_rowid >= ? AND "
                "at_rowid <= ? ORDER BY at_rowid, robot_id, session_id", (start, cursor)
            ):
                stream = f"{robot_id}/{session_id}"
                if not (at == start and stream in applied):
                    closures.setdefault(int(at), []).append(stream)
        counts = [0, 0]  # keyframes, measurements
        after = start
        for end in [*sorted(closures), cursor]:
            self._replay_range(after, end, counts)
            if self._stop.is_set():
                break
            self._close(closures.get(end, []))
            after = end
        keyframes, replayed = counts
        with self._lock:
            self._counts.replayed = replayed
            self._counts.mapped = 0
        log.info("mapping stage: replayed %d measurements of %d keyframes", replayed, keyframes)

    def _checkpoint_key(self) -> str:
        """What a checkpoint is valid for: its format, the association code and settings."""
        return json.dumps({"format": CHECKPOINT_FORMAT, "code": _association_code(),
                           "association": to_mapping(self.association),
                           "hist_bins": list(self._measure_config.hist_bins)}, sort_keys=True)

    def _checkpoint(self) -> None:
        """Save the association state at the current cursor, which it must match (a settled
        stage). Skipped when nothing changed since the last one or ``checkpoint_s`` is 0; a
        failure (a full disk) is logged, and a later restart replays from an older one."""
        if self.cfg.checkpoint_s <= 0:
            return
        self._checkpoint_at = time.monotonic()
        try:
            cursor = self._cursor()
            with self.store.reading("mapping: closures at the cursor") as conn:
                closed = sorted(f"{r}/{s}" for r, s in conn.execute(
                    "SELECT robot_id, session_id FROM closed_sessions WHERE at_rowid = ?", (cursor,)))
            if (cursor, len(closed)) == self._checkpointed:
                return
            state = pickle.dumps({"associator": self._associator, "hist_sum": self._hist_sum,
                                  "open_stream": self._open_stream, "closed_at_cursor": closed},
                                 protocol=pickle.HIGHEST_PROTOCOL)
            with self.store.writing("mapping: association checkpoint") as conn:
                conn.execute(
                    "INSERT INTO association_checkpoint (id, last_rowid, config_key, state, written_s) "
                    "VALUES (1, ?, ?, ?, ?) ON CONFLICT(id) DO UPDATE SET "
                    "last_rowid = excluded.last_rowid, config_key = excluded.config_key, "
                    "state = excluded.state, written_s = excluded.written_s",
                    (cursor, self._checkpoint_key(), state, time.time()))
            self._checkpointed = (cursor, len(closed))
            log.info("mapping stage: association checkpoint at keyframe %d (%d landmarks, %.1f MB)", cursor,
                     len(self._associator.landmarks()), len(state) / 1e6)
        except Exception:
            log.exception("mapping stage: association checkpoint not written")

    def _restore(self, cursor: int) -> tuple[int, set[str]]:
        """Load the association checkpoint if it is usable: ``(its cursor, the closures at that
        cursor it holds)``; ``(0, set())`` (replay everything) when there is none, it was made
        by other association code or settings, lies beyond ``cursor`` or cannot be read."""
        if self.cfg.checkpoint_s <= 0:
            return 0, set()
        with self.store.reading("mapping: association checkpoint") as conn:
            row = conn.execute(
                "SELECT last_rowid, config_key, state FROM association_checkpoint WHERE id = 1").fetchone()
        if row is None:
            return 0, set()
        at, key, blob = int(row[0]), str(row[1]), bytes(row[2])
        if key != self._checkpoint_key():
            log.info("mapping stage: the association checkpoint is of other code or settings; replaying all")
            return 0, set()
        if at > cursor:
            log.warning("mapping stage: the association checkpoint (keyframe %d) lies beyond the cursor "
                        "(%d); replaying all", at, cursor)
            return 0, set()
        try:
            state = pickle.loads(blob)  # the server's own file (docs/ARCHITECTURE.md)
            associator, hist_sum, open_stream = state["associator"], state["hist_sum"], state["open_stream"]
            applied = set(state["closed_at_cursor"])
            if not (isinstance(associator, Associator) and isinstance(hist_sum, dict)
                    and isinstance(open_stream, dict)):
                raise TypeError("unexpected contents")
        except Exception as exc:  # any unpickling error: the full replay is always correct
            log.warning("mapping stage: the association checkpoint cannot be read (%s: %s); replaying all",
                        type(exc).__name__, exc)
            return 0, set()
        self._associator, self._hist_sum, self._open_stream = associator, hist_sum, open_stream
        now = time.monotonic()
        self._last_seen = {stream: now for stream in open_stream.values()}
        self._checkpointed = (at, len(applied))
        log.info("mapping stage: association restored from its checkpoint at keyframe %d (%d landmarks)", at,
                 len(associator.landmarks()))
        return at, applied

    def _replay_range(self, after: int, end: int, counts: list[int]) -> None:
        """Replay the keyframes with ``after < rowid <= end`` (see :meth:`_replay`)."""
        while not self._stop.is_set():
            with self.store.reading("mapping: replay") as conn:
                rows = conn.execute(
                    "SELECT k.rowid, k.robot_id, k.session_id, k.seq, mk.T_map_camera, mk.camera "
                    "FROM keyframes k JOIN mapped_keyframes mk USING (robot_id, session_id, seq) "
                    "WHERE k.rowid > ? AND k.rowid <= ? AND mk.T_map_camera IS NOT NULL "
                    "ORDER BY k.rowid LIMIT ?",
                    (after, end, REPLAY_CHUNK),
                ).fetchall()
                if not rows:
                    break
                last = int(rows[-1][0])
                by_key: dict[str, list[ObjectMeasurement]] = {}
                for robot_id, session_id, seq, payload in conn.execute(
                    "SELECT m.robot_id, m.session_id, m.seq, m.payload FROM measurements m "
                    "JOIN keyframes k USING (robot_id, session_id, seq) "
                    "WHERE k.rowid > ? AND k.rowid <= ? AND m.anchored = 1 "
                    "ORDER BY k.rowid, m.measurement_id",
                    (after, last),
                ):
                    by_key.setdefault(f"{robot_id}/{session_id}/{int(seq)}", []).append(
                        unpack_measurement(payload))
            chunk = [
                _MappedKeyframe(f"{robot_id}/{session_id}", pose_from_blob(pose), _camera_from_json(camera),
                                by_key.get(f"{robot_id}/{session_id}/{int(seq)}", []))
                for _, robot_id, session_id, seq, pose, camera in rows
            ]
            self._associate(chunk)
            counts[0] += len(chunk)
            counts[1] += sum(len(v) for v in by_key.values())
            after = last

    def _backfill(self, cursor: int) -> None:
        """Fill ``mapped_keyframes`` for processed keyframes that have no row (stores written
        before schema v4), decoding their payloads one at a time."""
        done = 0
        while True:
            with self.store.reading("mapping: keyframes to backfill") as conn:
                rows = conn.execute(
                    "SELECT k.rowid, k.robot_id, k.session_id, k.seq FROM keyframes k "
                    "LEFT JOIN mapped_keyframes mk USING (robot_id, session_id, seq) "
                    "WHERE k.rowid <= ? AND mk.robot_id IS NULL ORDER BY k.rowid LIMIT ?",
                    (cursor, REPLAY_CHUNK),
                ).fetchall()
            if not rows:
                break
            filled = []
            for rowid, robot_id, session_id, seq in rows:
                with self.store.reading("mapping: keyframe to backfill") as conn:
                    (payload,) = conn.execute("SELECT payload FROM keyframes WHERE rowid = ?",
                                              (rowid,)).fetchone()
                try:
                    msg: KeyframeMsg | None = decode_keyframe(bytes(payload))
                except WireError:
                    msg = None  # it was skipped the first time too (counted then)
                filled.append((robot_id, session_id, int(seq), *_mapped_row(msg)))
            with self.store.writing("mapping: backfill mapped keyframes") as conn:
                conn.executemany(_INSERT_MAPPED, filled)
            done += len(filled)
        if done:
            log.info("mapping stage: recorded the map pose of %d keyframes processed by an older version",
                     done)


# ---------------------------------------------------------------------------- helpers


@dataclass(frozen=True)
class _MappedKeyframe:
    """What association needs of one anchored keyframe."""

    stream: str  # "<robot>/<session>": keyframe groups never span two sessions
    T_map_camera: F64
    camera: PinholeCamera
    measurements: Sequence[ObjectMeasurement]


def _mapped_row(msg: KeyframeMsg | None) -> tuple[bytes | None, str | None]:
    """``(T_map_camera blob, camera JSON)`` of a processed keyframe for ``mapped_keyframes``;
    ``(None, None)`` when it is not on the map (unanchored, undecodable, no intrinsics)."""
    if msg is None or msg.T_map_odom is None or msg.intrinsics is None:
        return None, None
    return pose_blob(map_pose(msg)), json.dumps(to_mapping(camera_of(msg)))


def _camera_from_json(text: str) -> PinholeCamera:
    d = json.loads(text)
    return PinholeCamera(**{**d, "distortion": tuple(d["distortion"])})


def camera_of(msg: KeyframeMsg) -> PinholeCamera:
    """The colour camera of a keyframe (its intrinsics; ``calib_ref`` is not resolvable yet)."""
    i = msg.intrinsics
    if i is None:
        raise WireError("calib_ref", "keyframes with calib_ref are not supported by the mapping stage yet")
    return PinholeCamera(i.width, i.height, i.fx, i.fy, i.cx, i.cy, tuple(i.distortion))  # type: ignore[arg-type]


def decode_images(msg: KeyframeMsg) -> tuple[NDArray[np.uint8], NDArray[np.float32], PinholeCamera]:
    """``(bgr (H, W, 3) uint8, depth (H, W) float32 metres at colour size, camera)``.

    Depth sent at 1/s resolution is upsampled by repetition: colour pixel (y, x) takes depth
    pixel (y // s, x // s) (docs/wire.md, ``depth``).
    """
    camera = camera_of(msg)
    bgr = cv2.imdecode(np.frombuffer(msg.rgb_jpeg, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None or bgr.shape[:2] != (camera.height, camera.width):
        raise WireError("rgb_jpeg", "cannot decode the colour image at the intrinsics' size")
    depth = decode_depth(msg.depth.data, msg.depth.meta)
    s = camera.height // depth.shape[0]
    if s > 1:
        depth = np.repeat(np.repeat(depth, s, axis=0), s, axis=1)
    return np.ascontiguousarray(bgr, np.uint8), np.ascontiguousarray(depth, np.float32), camera


@functools.cache
def _association_code() -> str:
    """Digest of the code whose state a checkpoint holds (the association package, this module)
    and of the packaged knowledge graph: a checkpoint of other code is not used."""
    import wardmap.server.association as association

    return code_digest([*sorted(Path(association.__file__).resolve().parent.glob("*.py")),
                        Path(__file__).resolve()])


def floor_height(msg: KeyframeMsg) -> float | None:
    """Height (m) of the floor in the map frame: that of the robot base, whose frame sits on the
    floor (``T_odom_base``); None for keyframes without a base (a hand-held camera)."""
    if msg.T_odom_base is None:
        return None
    T_map_odom = msg.T_map_odom if msg.T_map_odom is not None else np.eye(4)
    return float((T_map_odom @ msg.T_odom_base)[2, 3])


def map_pose(msg: KeyframeMsg) -> F64:
    """``T_map_camera`` (4, 4) of an anchored keyframe (identity map frame otherwise)."""
    T_map_odom = msg.T_map_odom if msg.T_map_odom is not None else np.eye(4)
    return np.asarray(T_map_odom @ msg.T_odom_camera, np.float64)


# ---------------------------------------------------------------------------- measurement blobs

_ARRAYS: Final = ("box_xyxy", "points_camera", "T_camera_object", "T_world_camera", "T_world_object",
                  "size", "color_hist", "descriptors")


def pack_measurement(m: ObjectMeasurement) -> bytes:
    """msgpack of a measurement without its mask (association does not read masks)."""
    d: dict[str, Any] = {"keyframe": m.keyframe, "stamp": m.stamp, "category": m.category,
                         "confidence": float(m.confidence), "gt_instance": m.gt_instance}
    for name in _ARRAYS:
        a = np.ascontiguousarray(getattr(m, name))
        d[name] = {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}
    return bytes(msgpack.packb(d, use_bin_type=True))


def unpack_measurement(blob: bytes) -> ObjectMeasurement:
    """Inverse of :func:`pack_measurement` (the mask comes back empty, shape (0, 0))."""
    d = msgpack.unpackb(blob, raw=False)
    arrays = {
        name: np.frombuffer(d[name]["data"], np.dtype(d[name]["dtype"])).reshape(d[name]["shape"]).copy()
        for name in _ARRAYS
    }
    return ObjectMeasurement(
        keyframe=d["keyframe"], stamp=float(d["stamp"]), category=d["category"],
        confidence=float(d["confidence"]), mask=np.zeros((0, 0), bool), gt_instance=d["gt_instance"],
        **arrays,
    )


def for_association(measurements: Sequence[ObjectMeasurement]) -> list[ObjectMeasurement]:
    """The measurements without their (H, W) masks and 3D points, for long-lived association
    state: association never reads either, and the points (up to ``MeasureConfig.max_points``,
    36 kB) were most of a measurement's memory. Both stay in the stored measurement."""
    return [replace(m, mask=np.zeros((0, 0), bool), points_camera=np.zeros((0, 3), np.float32))
            for m in measurements]


PipelineFactory = Callable[[SqliteKeyframeStore, ObjectMap], MapPipeline]

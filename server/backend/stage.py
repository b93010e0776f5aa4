"""The back-end stage: stored keyframes -> place recognition -> pose graph, in one thread.

Ingest stores and acks keyframes (``server/ingest.py``); this stage runs behind it in its own
thread, never delaying an ack. It reads keyframes in insertion order from its cursor
(``backend``), runs :class:`~wardmap.server.backend.core.BackendCore` on each, and commits
what changed (the node with its fern code, new factors, moved estimates, sessions anchored
or corrected, an object-map rebuild request) and its cursor in one transaction
(:meth:`~wardmap.server.store.GraphStore.commit_graph`). The mapping stage
(``server/mapping/``) processes only keyframes this stage has passed and reads their map
poses from the store.

After a commit, each session whose ``T_map_odom`` changed is handed to ``publish`` (the
server sends it to the robot on ``wardmap/v1/robots/<id>/correction``) when it is the
robot's running session (that of its latest keyframe); the store keeps the others.

With ``bundle_process`` a bundle adjustment runs in a child process (``bundle_worker.py``);
its result joins the graph with the next keyframe, or, when none waits, is committed alone
(new ``bundle`` edges and the estimates they moved; the cursor stays). Stopping the stage
stops a running adjustment.

Restart: the graph is rebuilt from its stored nodes and factors with the stored estimates as
initial values, and the fern index from the stored codes; no keyframe is verified again.

A keyframe whose payload does not decode is skipped (counted); an unexpected error is
logged and counted, the stage waits (``retry_s`` doubling to ``max_retry_s``), reloads the
graph from the store and carries on; a keyframe failing ``max_attempts`` times is skipped.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Final, cast

import numpy as np
from numpy.typing import NDArray

from wardmap.server.backend.core import BackendConfig, BackendCore, Closure, KeyframeResult, NodeKey
from wardmap.server.backend.graph import EdgeRecord, GraphUpdate, NodeRecord, PoseGraph
from wardmap.server.backend.verify import KeyframeFeatures
from wardmap.server.decoded import DecodedCache, DecodedKeyframe
from wardmap.server.store import GraphChange, GraphEdgeRow, GraphNodeRow, MapStore, SessionAnchor
from wardmap.server.telemetry import ServerTelemetry
from wardmap.shared.errors import WardmapError, WireError
from wardmap.shared.hamming import knn2
from wardmap.shared.priority import nice_this_thread
from wardmap.shared.wire import KeyframeMsg, PoseSource, decode_keyframe

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
CURSOR_NAME: Final = "backend"
FEATURE_CACHE: Final = 64
"""Stored keyframes' features kept decoded (candidates and their neighbours repeat)."""


@dataclass(frozen=True)
class BackendCounters:
    """A snapshot for ``/metrics``.

    Attributes:
        processed: keyframes this process added to the graph.
        nodes: nodes in the graph.
        loops: loop edges accepted (this process).
        anchored: sessions anchored (this process).
        candidates: fern candidates verified.
        rejected: candidates rejected, by reason.
        failures: keyframes skipped, by reason.
        restarts: unexpected errors recovered from.
        backlog: stored keyframes the stage has not processed.
        index_bytes: memory of the fern index.
        last_ms: per-step milliseconds of the latest keyframe.
    """

    processed: int
    nodes: int
    loops: int
    anchored: int
    candidates: int
    rejected: dict[str, int]
    failures: dict[str, int]
    restarts: int
    backlog: int
    index_bytes: int
    last_ms: dict[str, float] = field(default_factory=dict)


Publish = Callable[[SessionAnchor], object]


def warm_up_kernels() -> None:
    """Load (or compile) the numba kernels place recognition runs, now. The first call holds the
    interpreter lock for about 0.15 s (numba's target context, then the cached kernel), which
    under the first keyframes stalled every thread of the server, ingest's acks included."""
    probe = np.zeros((1, 32), np.uint8)
    knn2(probe, probe)


class BackendStage:
    """The back-end thread (see the module docstring).

    Args:
        store: the open store.
        config: back-end settings.
        publish: called with each session whose ``T_map_odom`` changed, after the commit.
        poll_s: sleep when no keyframe waits; batch: keyframes per round.
        retry_s, max_retry_s, max_attempts: recovery from unexpected errors.
        clock: wall-clock seconds (anchoring times).
        telemetry: where each keyframe's time in the back-end goes (stage ``backend``), or None.
        decoded: the keyframes ingest decoded (``server/decoded.py``), shared with the mapping
            stage; None: a private one (every keyframe is then decoded from the store).
        nice: added to this stage's thread's niceness (``[mapping] nice``; ``server/priority.py``).
    """

    def __init__(self, store: MapStore, config: BackendConfig | None = None, *,
                 publish: Publish | None = None, poll_s: float = 0.1, batch: int = 16, retry_s: float = 1.0,
                 max_retry_s: float = 60.0, max_attempts: int = 3,
                 clock: Callable[[], float] = time.time, telemetry: ServerTelemetry | None = None,
                 decoded: DecodedCache | None = None, nice: int = 0) -> None:
        self.store = store
        self.decoded = decoded if decoded is not None else DecodedCache()
        """Decoded keyframes from ingest; this stage reads them, the mapping stage discards them."""
        self._telemetry = telemetry
        self.cfg = config or BackendConfig()
        self._publish = publish
        self._poll_s, self._batch = poll_s, batch
        self._retry_s, self._max_retry_s, self._max_attempts = retry_s, max_retry_s, max_attempts
        self._clock = clock
        self._nice = nice
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter()
        self._rejected: Counter[str] = Counter()
        self._failures: Counter[str] = Counter()
        self._backlog = 0
        self._last_ms: dict[str, float] = {}
        self._cache: OrderedDict[NodeKey, KeyframeFeatures | None] = OrderedDict()
        self._anchors: dict[tuple[str, str], SessionAnchor] = {}
        self._running: dict[str, str] = {}  # robot -> the session of its latest keyframe
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._pending: bytes | None = None
        """The pending votes as last committed (``GraphChange.pending`` is sent only on a change)."""
        self.core = self._load()

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        warm_up_kernels()
        self._thread = threading.Thread(target=self._main, name="backend", daemon=True)
        self._thread.start()
        log.info("back-end started (%d nodes restored)", len(self.core))

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self.core.close()

    def running(self) -> bool:
        """Whether the thread is started and has not stopped or died."""
        thread = self._thread
        return thread is not None and thread.is_alive() and not self._stop.is_set() and self._error is None

    def set_publish(self, publish: Publish | None) -> None:
        """Who receives corrections (call before :meth:`start`)."""
        self._publish = publish

    def counters(self) -> BackendCounters:
        with self._lock:
            c = self._counts
            return BackendCounters(c["processed"], len(self.core), c["loops"], c["anchored"], c["candidates"],
                                   dict(self._rejected), dict(self._failures), c["restarts"], self._backlog,
                                   self.core.index_nbytes(), dict(self._last_ms))

    def cursor(self) -> int:
        return self.store.cursor(CURSOR_NAME)

    def wait_idle(self, timeout_s: float) -> bool:
        """Block until every stored keyframe is in the graph (tests); True if in time."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._error is not None:
                raise WardmapError(f"back-end failed: {self._error}") from self._error
            if self.store.count_keyframes_after(self.cursor()) == 0:
                return True
            time.sleep(0.05)
        return False

    def anchors(self) -> dict[tuple[str, str], SessionAnchor]:
        """Every session's anchoring as last committed (a copy)."""
        with self._lock:
            return dict(self._anchors)

    # ------------------------------------------------------------------ thread

    def _main(self) -> None:
        nice_this_thread(self._nice)
        delay = self._retry_s
        failing: tuple[int, int] | None = None
        while not self._stop.is_set():
            try:
                done = self.step()
                if done == 0 and not self.apply_bundle():
                    self._stop.wait(self._poll_s)
                delay, failing = self._retry_s, None
            except Exception as exc:
                with self._lock:
                    self._counts["restarts"] += 1
                log.exception("back-end: unexpected error; retrying in %.1f s", delay)
                if self._stop.wait(delay):
                    break
                delay = min(2.0 * delay, self._max_retry_s)
                try:
                    cursor = self.cursor()
                    failing = (cursor, failing[1] + 1 if failing and failing[0] == cursor else 1)
                    if failing[1] >= self._max_attempts:
                        self._skip_after(cursor, f"internal: {type(exc).__name__}")
                        failing = None
                    self.core.close()
                    self.core = self._load()
                except Exception:
                    log.exception("back-end: recovery failed; retrying")
            except BaseException as exc:
                self._error = exc
                log.exception("back-end stopped")
                return

    def step(self) -> int:
        """Process the next batch of stored keyframes; how many (the thread calls it; call it
        yourself only on a stage that is not started)."""
        rows = self.store.next_keyframes(self.cursor(), self._batch)
        for kf in rows:
            if self._stop.is_set():
                break
            try:
                decoded = self.decoded.decoded(kf.key, kf.payload)
            except WireError as exc:
                log.warning("keyframe %s: not in the graph: %s", kf.key, exc)
                with self._lock:
                    self._failures["WireError"] += 1
                self.store.commit_graph(CURSOR_NAME, kf.rowid, GraphChange())
                continue
            self._add(kf.rowid, decoded)
        with self._lock:
            self._backlog = self.store.count_keyframes_after(self.cursor())
        return len(rows)

    def _skip_after(self, cursor: int, reason: str) -> None:
        rows = self.store.next_keyframes(cursor, 1)
        if rows:
            log.error("back-end: keyframe %s failed %d times; skipped (%s)", rows[0].key, self._max_attempts,
                      reason)
            self.store.commit_graph(CURSOR_NAME, rows[0].rowid, GraphChange())
            with self._lock:
                self._failures[reason] += 1

    def _add(self, rowid: int, decoded: DecodedKeyframe) -> None:
        started = time.perf_counter()
        msg = decoded.msg
        try:
            images = self.decoded.images(decoded)
        except WireError:
            images = None  # the core finds the same and counts the keyframe as unreadable
        res = self.core.add(msg, images)
        change, changed = self._change(msg, res)
        self.store.commit_graph(CURSOR_NAME, rowid, change)
        self._settled(changed)
        if self._telemetry is not None:
            self._telemetry.mapping("backend", time.perf_counter() - started)
        with self._lock:
            self._counts["processed"] += 1
            self._counts["candidates"] += res.candidates
            self._counts["loops"] += len(res.closures)
            self._counts["anchored"] += len(res.update.anchored)
            self._rejected.update(res.rejected)
            self._last_ms = dict(res.ms)
        for closure in res.closures:
            log.info("back-end: %s %s -> %s (%d inliers)", closure.kind, "/".join(map(str, closure.a)),
                     "/".join(map(str, closure.b)), closure.inliers)
        self._running[msg.robot_id] = msg.session_id
        self._publish_changed(changed)

    def apply_bundle(self, timeout_s: float = 0.0) -> bool:
        """Commit a bundle adjustment the child process finished (waiting up to ``timeout_s``)
        while no keyframe waits: its edges, the estimates they moved, the sessions whose
        ``T_map_odom`` changed (published), a rebuild request; the cursor stays. Whether one was
        committed."""
        got = self.core.collect_bundle(timeout_s)
        if got is None:
            return False
        _, update = got
        _, edges = self.core.graph.new_records()
        keys = self.core.node_keys()
        estimates = [(k, T) for k, T in zip(keys, self.core.graph.estimates(keys), strict=True)
                     if T is not None]
        changed = self._sessions_changed(update, [])
        rebuild = update.moved_m > self.cfg.rebuild_move_m
        self.store.commit_graph(CURSOR_NAME, self.cursor(),
                                GraphChange((), [_edge_row(e) for e in edges], estimates, changed, rebuild))
        self._settled(changed)
        self._publish_changed(changed)
        return True

    def _settled(self, changed: list[SessionAnchor]) -> None:
        """After a commit: the sessions it changed, as the store now has them."""
        with self._lock:
            for anchor in changed:
                self._anchors[(anchor.robot_id, anchor.session_id)] = anchor

    def _publish_changed(self, changed: list[SessionAnchor]) -> None:
        """Send each changed session's correction to its robot, if it is the robot's running one."""
        for anchor in changed:
            # A robot runs one session at a time: older sessions' corrections would only be refused.
            if self._running.get(anchor.robot_id) != anchor.session_id:
                continue
            if anchor.T_map_odom is not None and self._publish is not None:
                try:
                    self._publish(anchor)
                except Exception:
                    log.exception("back-end: correction for %s/%s not published", anchor.robot_id,
                                  anchor.session_id)

    def _change(self, msg: KeyframeMsg, res: KeyframeResult) -> tuple[GraphChange, list[SessionAnchor]]:
        """What to commit for one processed keyframe, and the sessions whose anchoring changed."""
        key = res.key
        estimate = self.core.estimate(key)
        node = GraphNodeRow(key, float(msg.stamp), msg.T_odom_camera, msg.pose_source, estimate,
                            msg.T_map_odom, res.codes)
        _, edges = self.core.graph.new_records()
        edge_rows = [_edge_row(e) for e in edges]
        moved = res.update.moved_m > 1e-3 or bool(res.update.anchored) or bool(res.closures)
        estimates: list[tuple[NodeKey, F64]] = []
        if moved:
            keys = [k for k in self.core.node_keys() if k != key]
            estimates = [(k, T) for k, T in zip(keys, self.core.graph.estimates(keys), strict=True)
                         if T is not None]
        changed = self._sessions_changed(res.update, res.closures)
        session = (msg.robot_id, msg.session_id)
        if session not in self._anchors and session not in res.update.sessions:
            changed.append(SessionAnchor(session[0], session[1], None, None, "", 0))
        pending = self.core.pending_state()
        if pending == self._pending:
            stored_pending = None
        else:
            stored_pending = self._pending = pending
        return GraphChange([node], edge_rows, estimates, changed, res.rebuild, stored_pending), changed

    def _sessions_changed(self, update: GraphUpdate, closures: Sequence[Closure]) -> list[SessionAnchor]:
        """The session rows of a graph update's changed sessions (revision bumped)."""
        now = self._clock()
        changed = []
        for s, T_map_odom in update.sessions.items():
            old = self._anchors.get(s)
            anchored_s = old.anchored_s if old is not None and old.anchored_s is not None else now
            to = old.anchored_to if old is not None and old.anchored_to else self._anchored_to(s, closures)
            changed.append(SessionAnchor(s[0], s[1], T_map_odom, anchored_s, to,
                                         (old.revision if old is not None else 0) + 1))
        return changed

    def _anchored_to(self, session: tuple[str, str], closures: Sequence[Closure]) -> str:
        """Which session a newly anchored one was anchored through (itself: it set the map or
        came with a prior)."""
        for closure in closures:
            sa, sb = closure.a[:2], closure.b[:2]
            if session == sa and sb != sa:
                return f"{sb[0]}/{sb[1]}"
            if session == sb and sa != sb:
                return f"{sa[0]}/{sa[1]}"
        return f"{session[0]}/{session[1]}"

    # ------------------------------------------------------------------ loading

    def _load(self) -> BackendCore:
        """The core over the stored graph (empty for a new store)."""
        nodes, edges = self.store.graph_records()
        self._anchors = {(a.robot_id, a.session_id): a for a in self.store.session_anchors()}
        self._pending = self.store.graph_pending()
        if not nodes:
            return BackendCore(self.cfg, features=self._features)
        graph = PoseGraph.restore(self.cfg.graph, [_node_record(n) for n in nodes],
                                  [_edge_record(e) for e in edges])
        graph.new_records()  # what is stored is not new
        core = BackendCore.restore(self.cfg, [(n.key, n.stamp, n.T_odom_camera, n.codes) for n in nodes],
                                   graph, features=self._features, pending=self._pending)
        log.info("back-end: pose graph restored (%d nodes, %d edges)", len(nodes), len(edges))
        return core

    def _features(self, key: NodeKey) -> KeyframeFeatures | None:
        """A stored keyframe's features (decoded from its payload; a small cache)."""
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        payload = self.store.payload(*key)
        features = None
        if payload is not None:
            try:
                msg = decode_keyframe(payload)
                camera = msg.camera
                if camera is not None:
                    features = KeyframeFeatures.from_keypoints(msg.keypoints, camera)
            except WireError:
                features = None
        self._cache[key] = features
        while len(self._cache) > FEATURE_CACHE:
            self._cache.popitem(last=False)
        return features


def _edge_row(e: EdgeRecord) -> GraphEdgeRow:
    return GraphEdgeRow(e.kind, e.a, e.b, e.T_a_b, e.sigmas, e.robust)


def _edge_record(e: GraphEdgeRow) -> EdgeRecord:
    return EdgeRecord(e.kind, e.a, e.b, e.T_a_b, e.sigmas, e.robust)  # type: ignore[arg-type]


def _node_record(n: GraphNodeRow) -> NodeRecord:
    return NodeRecord(n.key, n.T_odom_camera, cast(PoseSource, n.pose_source), n.T_map_camera,
                      n.prior_T_map_odom)

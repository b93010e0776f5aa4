"""The SLAM back-end's logic: place recognition, verification, anchoring and the pose graph.

:class:`BackendCore` takes keyframes in arrival order (any robots, any sessions) and keeps
one pose graph of all of them (``graph.py``, gtsam iSAM2). For each keyframe:

1. its colour and depth are encoded with random ferns (paper 003 Eq. 10-11, ``places.py``)
   and the fern index is queried for the ``candidates`` most similar stored keyframes (every
   robot and session), leaving out the same session's keyframes within ``recent_path_m`` of
   driving or ``recent_s`` seconds (they always look alike);
2. each candidate above ``min_similarity`` is verified geometrically (``verify.py``: ORB
   matches, EPnP in RANSAC on the candidate's depth, refinement), and then once more
   against the candidate's neighbour in its session: the two relative poses, chained through
   the neighbour's odometry, must agree within ``agree_m`` / ``agree_deg`` (a second
   nearby keyframe, as ORB-SLAM2 asks for consistency before it closes a loop);
3. a verified match between two keyframes already on one map is checked against the graph:
   the measured relative pose may differ from the graph's prediction by at most
   ``gate_m + gate_per_m`` times the distance driven between them in one session (drift
   grows with distance), else it is rejected as perceptual aliasing (identical doors, rows
   of identical chairs); it is closed when a second loop of the same session, within
   ``loop_window_m`` before it, implies the same correction of the map. A session not on
   the map yet closes loops within itself the same way, its odometry predicting them; a match
   between two sessions both off the map is not used (each is anchored through the map);
4. a verified match from a session that is not on the map (it started without a known map
   pose) to a keyframe on the map is a vote for that session's ``T_map_odom``; the session is
   anchored when at least ``anchor_votes`` votes agree (within ``agree_m`` / ``agree_deg``),
   come from keyframes spread over ``anchor_span_m`` of driving or ``anchor_span_deg`` of
   turning, and no rival group of votes (at least half as many, and two) implies another
   ``T_map_odom``: one match could be an identical twin of the place, agreeing ones from
   different places hardly;
5. the keyframe's node (odometry edge from its predecessor) and any accepted loop edge go
   into the graph, and iSAM2 updates it incrementally.

After a loop edge of a session on the map enters the graph, that session's next ``loop_gap``
keyframes are not searched (ORB-SLAM2's loop closing waits 10 keyframes after a loop, likewise): a
session whose place the map has just fixed gains little from more loops there, and in a map
that many sessions revisit every loop edge costs an iSAM2 update over the cliques that tie
those sessions together.

What a keyframe did comes back as a :class:`KeyframeResult`; the stage (``stage.py``)
persists it and publishes corrections. Features of stored keyframes are read through a
callback (the server reads them from the store; without one, the core keeps them in memory).
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Final, Literal, cast

import cv2
import msgpack
import numpy as np
from numpy.typing import NDArray

from wardmap.server.backend.bundle import BundleConfig, BundleFrame, BundleResult, bundle_adjust
from wardmap.server.backend.bundle_worker import BundleWorker
from wardmap.server.backend.graph import EdgeRecord, GraphConfig, GraphUpdate, NodeRecord, PoseGraph
from wardmap.server.backend.places import FernConfig, FernEncoder, FernIndex
from wardmap.server.backend.verify import KeyframeFeatures, Verified, VerifyConfig, verify_pair
from wardmap.server.decoded import KeyframeImages, decode_images
from wardmap.shared.errors import ConfigError, GeometryError, WardmapError
from wardmap.shared.wire import KeyframeMsg

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
NodeKey = tuple[str, str, int]
Session = tuple[str, str]


@dataclass(frozen=True)
class BackendConfig:
    """The back-end (``[backend]`` table; see the module docstring for what each step does).

    Attributes:
        enabled: run place recognition (off: no loop closure, and a session reaches the map
            only when it is the first or came with a ``--map-pose`` prior).
        ferns, verify, graph: the parts' settings.
        candidates: fern-index candidates verified per keyframe.
        min_similarity: fern similarity (fraction of equal block codes) below which a
            candidate is not verified.
        recent_s, recent_path_m: same-session keyframes newer than ``recent_s`` seconds or
            within ``recent_path_m`` metres of driving are not loop candidates.
        agree_m, agree_deg: agreement between two estimates of one relative pose (second
            keyframe check, anchoring votes).
        gate_m, gate_per_m: a loop between keyframes already on one map may differ from the
            graph's prediction by ``gate_m + gate_per_m * d`` metres (``d``: distance driven
            between them when in one session, else ``gate_cross_m`` in total) and
            ``gate_deg`` degrees.
        loop_window_m: a loop inside the map waits for a second one from the same session,
            at most this far back along its path, that implies the same correction.
        anchor_votes: agreeing verified matches that anchor a session.
        anchor_span_m, anchor_span_deg: the agreeing votes must come from keyframes spread
            over at least this distance driven or this camera rotation (different views: an
            aliased stretch, such as two corridors that look alike, rarely lasts).
        check_keyframes, check_m, check_deg: before anchoring, up to this many other
            keyframes of the session are put on the map by the candidate ``T_map_odom``; each
            with a map keyframe within ``check_m`` metres looking the same way (optical axes
            within ``check_deg``) is verified against it; the anchoring is refused when at
            least two fail and fewer agree (the views the map holds there contradict it).
        rebuild_move_m: a graph update that moves any keyframe more than this (metres), or
            anchors a session, asks the mapping stage to rebuild the object map.
        loop_gap: keyframes of a session not searched for loops after one of its loop edges
            entered the graph (0: search every keyframe).
        bundle_enabled: after a loop edge between anchored keyframes, bundle-adjust the
            sessions it joins (``bundle``; ground robots' keyframes with a level prior) and tie
            their consecutive keyframes by ``bundle`` edges (ORB-SLAM2's global bundle
            adjustment after loop closure; tracks from the edge's map point ids and descriptor
            matches, decision 0044) ...
        bundle_process: ... in a child process while the back-end goes on, its result added
            when it is there (``bundle_worker.py``; one at a time: a loop while one runs starts
            none); False: in the back-end thread, which waits for it (deterministic: for
            benchmarks and tests) ...
        bundle_min_pairs: ... when at least this many of their consecutive keyframe pairs have
            no ``bundle`` edge yet ...
        bundle_context: ... over those pairs' keyframes and this many more on each side of
            them and of the loop's two ends ...
        bundle_max_keyframes: ... at most this many (the newest; bounds the adjustment's time).
    """

    enabled: bool = True
    ferns: FernConfig = field(default_factory=FernConfig)
    verify: VerifyConfig = field(default_factory=VerifyConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    candidates: int = 3
    min_similarity: float = 0.55
    recent_s: float = 20.0
    recent_path_m: float = 4.0
    agree_m: float = 0.10
    agree_deg: float = 3.0
    gate_m: float = 0.3
    gate_per_m: float = 0.03
    gate_cross_m: float = 0.6
    gate_deg: float = 10.0
    loop_window_m: float = 3.0
    anchor_votes: int = 3
    anchor_span_m: float = 1.0
    anchor_span_deg: float = 20.0
    check_keyframes: int = 6
    check_m: float = 1.0
    check_deg: float = 30.0
    rebuild_move_m: float = 0.02
    loop_gap: int = 10
    bundle_enabled: bool = True
    bundle_process: bool = True
    bundle: BundleConfig = field(default_factory=BundleConfig)
    bundle_min_pairs: int = 30
    bundle_context: int = 10
    bundle_max_keyframes: int = 400

    def __post_init__(self) -> None:
        if self.candidates < 1:
            raise ConfigError(f"backend.candidates must be >= 1, got {self.candidates}")
        if not 0.0 <= self.min_similarity <= 1.0:
            raise ConfigError(f"backend.min_similarity must be in [0, 1], got {self.min_similarity}")
        for name in ("recent_s", "recent_path_m", "agree_m", "agree_deg", "gate_m", "gate_per_m",
                     "gate_cross_m", "gate_deg", "loop_window_m", "anchor_span_m", "anchor_span_deg",
                     "check_m", "check_deg", "rebuild_move_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"backend.{name} must be >= 0, got {value}")
        if self.anchor_votes < 1:
            raise ConfigError(f"backend.anchor_votes must be >= 1, got {self.anchor_votes}")
        if self.loop_gap < 0:
            raise ConfigError(f"backend.loop_gap must be >= 0, got {self.loop_gap}")
        if self.bundle_context < 0:
            raise ConfigError(f"backend.bundle_context must be >= 0, got {self.bundle_context}")
        if self.bundle_min_pairs < 1 or self.bundle_max_keyframes < 2:
            raise ConfigError(f"backend.bundle_min_pairs must be >= 1 and bundle_max_keyframes >= 2, got "
                              f"{self.bundle_min_pairs} and {self.bundle_max_keyframes}")


@dataclass(frozen=True, eq=False)
class Closure:
    """An accepted place match.

    Attributes:
        a: the new keyframe; b: the stored keyframe it matched.
        T_a_b: (4, 4) float64 ``b``'s camera in ``a``'s camera frame (verified, refined).
        inliers: EPnP inliers.
        kind: ``loop`` (both on one map), ``anchor`` (it anchored ``a``'s or ``b``'s session)
            or ``floating`` (within one session not on the map yet: kept until it is).
        sigmas: (6,) the verification's standard deviations of ``T_a_b`` (rad x3, m x3).
    """

    a: NodeKey
    b: NodeKey
    T_a_b: F64
    inliers: int
    kind: Literal["loop", "anchor", "floating"]
    sigmas: F64 | None = None


@dataclass(eq=False)
class KeyframeResult:
    """What :meth:`BackendCore.add` did with one keyframe.

    Attributes:
        key: the keyframe.
        codes: its fern code (``FernConfig.blocks`` bytes).
        candidates: fern candidates verified.
        searched: whether it was searched for loops (not within ``loop_gap`` keyframes of its
            session's last loop edge, and readable).
        closures: accepted matches.
        rejected: verification and gate rejections by reason.
        update: the graph update (estimates moved, sessions anchored).
        rebuild: the map moved enough to rebuild the object map.
        ms: milliseconds per step: ``encode``, ``query``, ``verify``, ``graph``, and
            ``bundle`` (the adjustment, wherever it ran, and its graph update) when one was added.
        bundle: the bundle adjustment added to the graph with this keyframe (run for its loop
            closure, or finished in the child process since the last keyframe), or None.
    """

    key: NodeKey
    codes: bytes
    candidates: int
    searched: bool
    closures: list[Closure]
    rejected: Counter[str]
    update: GraphUpdate
    rebuild: bool
    ms: dict[str, float]
    bundle: BundleResult | None = None


@dataclass
class _Node:
    key: NodeKey
    stamp: float
    T_odom_camera: F64
    path_m: float  # distance driven in its session up to it (camera centre), metres
    turn_deg: float  # camera rotation accumulated in its session up to it, degrees


@dataclass
class _Vote:
    T_map_odom: F64
    closure: Closure
    path_m: float
    turn_deg: float


FeatureLoader = Callable[[NodeKey], KeyframeFeatures | None]
_UP = np.array([0.0, 0.0, 1.0])
NO_CODE = 0xFF
"""The block code of a keyframe without place recognition (equal to no real code: 0..15)."""
MAX_VOTES = 64
"""Anchoring votes kept per floating session (the most recent)."""
PENDING_FORMAT: Final = "wardmap-backend-pending"
PENDING_VERSION: Final = 1
"""The encoding of :meth:`BackendCore.pending_state` (bump on any change of its layout)."""


class BackendCore:
    """Place recognition, verification, anchoring and the pose graph (see the module docstring).

    Args:
        config: settings.
        features: reads a stored keyframe's features by key (None: the core keeps every
            keyframe's features in memory).
        graph: continue this graph (:meth:`restore`).
    """

    def __init__(self, config: BackendConfig | None = None, *, features: FeatureLoader | None = None,
                 graph: PoseGraph | None = None) -> None:
        self.cfg = config or BackendConfig()
        self.encoder = FernEncoder(self.cfg.ferns)
        self.index = FernIndex(self.cfg.ferns.blocks)
        self.graph = graph if graph is not None else PoseGraph(self.cfg.graph)
        self._load = features
        self._features: dict[NodeKey, KeyframeFeatures] = {}
        self._nodes: list[_Node] = []
        self._row: dict[NodeKey, int] = {}
        self._sessions: dict[Session, int] = {}
        self._session_rows: dict[int, list[int]] = {}
        self._session_of_row: list[int] = []
        self._votes: dict[Session, list[_Vote]] = {}
        # session -> loops waiting for a confirming one: (path_m of a, correction (4, 4), closure)
        self._loop_votes: dict[Session, list[tuple[float, F64, Closure]]] = {}
        self._last_loop: dict[Session, int] = {}
        """Session -> its keyframes counted when its last loop edge entered the graph."""
        self._worker = BundleWorker() if self.cfg.bundle_enabled and self.cfg.bundle_process else None

    # ------------------------------------------------------------------ restore

    @classmethod
    def restore(cls, config: BackendConfig, nodes: Sequence[tuple[NodeKey, float, F64, bytes]],
                graph: PoseGraph, *, features: FeatureLoader | None = None,
                pending: bytes | None = None) -> BackendCore:
        """A core over a stored graph: ``nodes`` = ``(key, stamp, T_odom_camera, codes)`` in
        arrival order; ``graph`` restored from the same records; ``pending``: the
        :meth:`pending_state` stored with them (None: none stored). Codes of another fern
        configuration (wrong length) raise :class:`ConfigError`. A pending state this build
        cannot read (another version, damaged) is logged and dropped: votes start over, which
        only delays anchoring."""
        core = cls(config, features=features, graph=graph)
        for key, stamp, T_odom_camera, codes in nodes:
            arr = np.frombuffer(codes, np.uint8)
            if arr.shape != (config.ferns.blocks,):
                raise ConfigError(f"stored fern codes have {arr.size} blocks, backend.ferns.blocks is "
                                  f"{config.ferns.blocks}")
            core._remember(key, stamp, T_odom_camera, arr, None)
        if pending is not None:
            try:
                core._set_pending(pending)
            except (ValueError, TypeError, KeyError, IndexError, msgpack.UnpackException) as exc:
                log.warning("back-end: stored pending votes not restored (%s); they start over", exc)
                core._votes, core._loop_votes, core._last_loop = {}, {}, {}
        return core

    def pending_state(self) -> bytes:
        """What the core holds between keyframes beyond the graph, as bytes to store with it:
        the anchoring votes of floating sessions, the loops waiting for a confirming one, and
        each session's keyframe count at its last loop (``loop_gap``). Restored with
        :meth:`restore`, a core continues as if it had never stopped.

        Layout (msgpack): ``[PENDING_FORMAT, PENDING_VERSION, votes, loops, last_loop]`` with
        ``votes`` = ``[[robot, session, T_map_odom, closure, path_m, turn_deg], ...]``,
        ``loops`` = ``[[robot, session, path_m, C, closure], ...]``, ``last_loop`` =
        ``[[robot, session, count], ...]``; a pose is 16 little-endian float64 (row-major), a
        closure ``[a, b, T_a_b, inliers, kind, sigmas or None]`` with keys ``[robot, session, seq]``."""
        votes = [[s[0], s[1], _pose_bytes(v.T_map_odom), _closure_list(v.closure), v.path_m, v.turn_deg]
                 for s, vs in self._votes.items() for v in vs]
        loops = [[s[0], s[1], path_m, _pose_bytes(C), _closure_list(c)]
                 for s, ps in self._loop_votes.items() for path_m, C, c in ps]
        last = [[s[0], s[1], n] for s, n in self._last_loop.items()]
        return cast(bytes, msgpack.packb([PENDING_FORMAT, PENDING_VERSION, votes, loops, last]))

    def _set_pending(self, blob: bytes) -> None:
        """Load :meth:`pending_state`'s bytes (raises ValueError on another format or version)."""
        fmt, version, votes, loops, last = msgpack.unpackb(blob)
        if fmt != PENDING_FORMAT or version != PENDING_VERSION:
            raise ValueError(f"{fmt!r} version {version!r}, this build reads {PENDING_FORMAT!r} "
                             f"version {PENDING_VERSION}")
        anchor: dict[Session, list[_Vote]] = {}
        for robot, session, T, closure, path_m, turn_deg in votes:
            anchor.setdefault((str(robot), str(session)), []).append(
                _Vote(_pose_from(T), _closure_from(closure), float(path_m), float(turn_deg)))
        pending: dict[Session, list[tuple[float, F64, Closure]]] = {}
        for robot, session, path_m, C, closure in loops:
            pending.setdefault((str(robot), str(session)), []).append(
                (float(path_m), _pose_from(C), _closure_from(closure)))
        closures = [v.closure for vs in anchor.values() for v in vs]
        closures += [p[2] for ps in pending.values() for p in ps]
        for c in closures:
            for k in (c.a, c.b):
                if k not in self._row:
                    raise ValueError(f"a pending vote names keyframe {k}, which the graph lacks")
        self._votes, self._loop_votes = anchor, pending
        self._last_loop = {(str(r), str(s)): int(n) for r, s, n in last}

    # ------------------------------------------------------------------ adding keyframes

    def add(self, msg: KeyframeMsg, images: KeyframeImages | None = None) -> KeyframeResult:
        """Process one keyframe (see the module docstring), in arrival order; ``images``: its
        rasters already decoded (:func:`~wardmap.server.decoded.decode_images`), or None to
        decode them here."""
        ms: dict[str, float] = {}
        t0 = time.perf_counter()
        key: NodeKey = (msg.robot_id, msg.session_id, msg.seq)
        rejected: Counter[str] = Counter()
        camera = msg.camera
        features: KeyframeFeatures | None = None
        try:
            codes = self.encode(msg, images)
            if camera is not None:
                features = KeyframeFeatures.from_keypoints(msg.keypoints, camera)
        except (WardmapError, ValueError, cv2.error) as exc:
            # A keyframe whose images or keypoints cannot be read still carries its pose: it
            # joins the graph, and only place recognition skips it.
            log.warning("keyframe %s/%s/%d: no place recognition: %s", *key, exc)
            rejected["unreadable keyframe"] += 1
            codes, features = np.full(self.cfg.ferns.blocks, NO_CODE, np.uint8), None
        t1 = time.perf_counter()
        ms["encode"] = (t1 - t0) * 1e3
        self.graph.add_keyframe(key, msg.T_odom_camera, pose_source=msg.pose_source,
                                prior_T_map_odom=msg.T_map_odom)
        row = self._remember(key, msg.stamp, msg.T_odom_camera, codes, features)
        closures: list[Closure] = []
        n_cand = 0
        ms["query"] = ms["verify"] = 0.0
        searched = (self.cfg.enabled and features is not None and len(self._nodes) > 1
                    and not self._resting(key))
        if searched and features is not None:
            allowed = self._allowed(row)
            t2 = time.perf_counter()
            hits = [h for h in self.index.query(codes, self.cfg.candidates, allowed)
                    if h[1] >= self.cfg.min_similarity]
            t3 = time.perf_counter()
            ms["query"] = (t3 - t2) * 1e3
            n_cand = len(hits)
            best = self._best_match(row, features, hits, rejected)
            if best is not None:
                closure = self._accept(row, best, rejected)
                if closure is not None:
                    closures.append(closure)
                    if self.anchored((key[0], key[1])):  # a floating session keeps searching: its votes
                        self._last_loop[(key[0], key[1])] = len(self._session_rows[self._session_of_row[row]])
            ms["verify"] = (time.perf_counter() - t3) * 1e3
        bundle = self._collect_bundle()  # finished in the child: its edges join this update
        t4 = time.perf_counter()
        update = self.graph.update()
        ms["graph"] = (time.perf_counter() - t4) * 1e3
        if bundle is not None:
            ms["bundle"] = bundle.ms
        if self.cfg.bundle_enabled and any(c.kind == "loop" for c in closures):
            t5 = time.perf_counter()
            inline = self._bundle(closures)
            if inline is not None:
                bundle = inline
                update = _merged(update, self.graph.update())
                ms["bundle"] = (time.perf_counter() - t5) * 1e3
        # A session anchored at its first keyframe (the map's first, or a map-pose prior) moved
        # nothing that was mapped; one anchored later brings its waiting keyframes.
        grown = any(len(self._session_rows.get(self._sessions.get(s, -1), [])) > 1
                    for s in update.anchored)
        rebuild = grown or update.moved_m > self.cfg.rebuild_move_m
        return KeyframeResult(key, codes.tobytes(), n_cand, bool(searched), closures, rejected, update,
                              rebuild, ms, bundle)

    def collect_bundle(self, timeout_s: float = 0.0) -> tuple[BundleResult, GraphUpdate] | None:
        """Between keyframes: a bundle adjustment finished in the child process (waiting up to
        ``timeout_s``), added to the graph as ``bundle`` edges and the graph updated; None when
        none finished (or none runs, or it failed: logged)."""
        bundle = self._collect_bundle(timeout_s)
        if bundle is None:
            return None
        return bundle, self.graph.update()

    def bundle_running(self) -> bool:
        """Whether a bundle adjustment runs in the child process."""
        return self._worker is not None and self._worker.busy()

    def close(self) -> None:
        """Stop a bundle adjustment still running in the child process (its pairs stay
        unbundled: a later loop adjusts them)."""
        if self._worker is not None:
            self._worker.close()

    def encode(self, msg: KeyframeMsg, images: KeyframeImages | None = None) -> NDArray[np.uint8]:
        """The keyframe's fern code, from ``images`` (decoded from ``msg`` when None).

        Raises:
            WireError: the colour image or the depth does not decode.
        """
        if images is None:
            images = decode_images(msg)
        return self.encoder.encode(images.bgr, images.depth_m)

    # ------------------------------------------------------------------ reading

    def estimate(self, key: NodeKey) -> F64 | None:
        """``T_map_camera`` of a keyframe, None while its session is not on the map."""
        return self.graph.estimate(key)

    def T_map_odom(self, session: Session) -> F64 | None:
        """The session's odom frame on the map, None while it is not anchored."""
        return self.graph.T_map_odom(session)

    def anchored(self, session: Session) -> bool:
        return bool(self.graph.anchored(session))

    def node_keys(self) -> list[NodeKey]:
        """Every keyframe in the graph, in arrival order."""
        return [n.key for n in self._nodes]

    def index_nbytes(self) -> int:
        """Memory of the fern index, bytes."""
        return int(self.index.nbytes)

    def __len__(self) -> int:
        return len(self._nodes)

    # ------------------------------------------------------------------ internals

    def _collect_bundle(self, timeout_s: float = 0.0) -> BundleResult | None:
        """The child's finished adjustment, its ``bundle`` edges added (no graph update yet)."""
        if self._worker is None:
            return None
        result = self._worker.collect(timeout_s)
        if result is not None:
            added = self.graph.add_bundle_edges(cast(dict[NodeKey, F64], result.poses))
            log.info("bundle adjustment (child process): %d keyframes, %d landmarks, %d observations "
                     "(%d dropped), %d edges, %.0f ms", len(result.poses), result.landmarks,
                     result.observations, result.dropped, added, result.ms)
        return result

    def _bundle(self, closures: Sequence[Closure]) -> BundleResult | None:
        """Bundle-adjust around this keyframe's loop ``closures`` and add the ``bundle`` edges
        (with ``bundle_process``: start the adjustment in the child process and return None;
        its edges come with a later keyframe or :meth:`collect_bundle`).

        The frames: the keyframes of the closures' (anchored) sessions in a pair without a
        ``bundle`` edge, and ``bundle_context`` keyframes on each side of those and of every
        closure's two ends (the views the loop shares), at most the newest
        ``bundle_max_keyframes``; initial poses are the graph's estimates. None when fewer than
        ``bundle_min_pairs`` pairs are new or the adjustment has nothing to work on."""
        cfg = self.cfg
        sessions = sorted({k[:2] for c in closures for k in (c.a, c.b) if self.graph.anchored(k[:2])})
        new_pairs = {s: self.graph.unbundled(s) for s in sessions}
        if sum(len(p) for p in new_pairs.values()) < cfg.bundle_min_pairs:
            return None
        if self._worker is not None and self._worker.busy():
            log.debug("bundle adjustment: one runs already; this loop starts none")
            return None
        chosen: list[tuple[float, Session, int, NodeKey]] = []
        for s in sessions:
            keys = self.graph.session_keys(s)
            wanted = np.zeros(len(keys), bool)
            for i in new_pairs[s]:
                wanted[max(0, i - cfg.bundle_context): i + 2 + cfg.bundle_context] = True
            for c in closures:
                for k in (c.a, c.b):
                    if k[:2] == s and k in self._row:
                        at = keys.index(k)
                        wanted[max(0, at - cfg.bundle_context): at + 1 + cfg.bundle_context] = True
            chosen.extend((self._nodes[self._row[k]].stamp, s, j, k) for j, k in enumerate(keys) if wanted[j])
        chosen = sorted(chosen)[-cfg.bundle_max_keyframes:]
        frames = []
        for _, s, _, k in sorted(chosen, key=lambda c: (c[1], c[2])):
            est = self.graph.estimate(k)
            feats = None if est is None else self._features_of(k)
            if est is not None and feats is not None:
                node = self._nodes[self._row[k]]
                up = est[:3, :3] @ node.T_odom_camera[:3, :3].T @ _UP if self._on_floor(s) else None
                frames.append(BundleFrame(k, est, feats, chain=s, up=up, seq=k[2]))
        if len(frames) < 2:
            return None
        if self._worker is not None:
            self._worker.submit(frames, cfg.bundle)
            log.info("bundle adjustment over %d keyframes started in a child process", len(frames))
            return None
        try:
            result = bundle_adjust(frames, cfg.bundle)
        except (GeometryError, RuntimeError) as exc:  # different cameras; gtsam's own failures
            log.warning("bundle adjustment over %d keyframes skipped: %s", len(frames), exc)
            return None
        added = self.graph.add_bundle_edges(cast(dict[NodeKey, F64], result.poses))
        log.info("bundle adjustment: %d keyframes, %d landmarks, %d observations (%d dropped), %d edges, "
                 "%.0f ms", len(frames), result.landmarks, result.observations, result.dropped, added,
                 result.ms)
        return result

    def _on_floor(self, session: Session) -> bool:
        """Whether ``session``'s odom frame is a ground robot's, z up (REP 103): its first
        keyframe's camera looks within 60 deg of level, down axis down. The tracker's frame is
        the first camera frame when it lacks odometry or the camera's mounting, and there the
        first keyframe's pose is the identity (down axis along y): never taken for a floor."""
        first = self._nodes[self._session_rows[self._sessions[session]][0]]
        return bool(first.T_odom_camera[2, 1] < -0.5)

    def _remember(self, key: NodeKey, stamp: float, T_odom_camera: F64, codes: NDArray[np.uint8],
                  features: KeyframeFeatures | None) -> int:
        session = (key[0], key[1])
        sid = self._sessions.setdefault(session, len(self._sessions))
        rows = self._session_rows.setdefault(sid, [])
        path = turn = 0.0
        if rows:
            prev = self._nodes[rows[-1]]
            path = prev.path_m + float(np.linalg.norm(T_odom_camera[:3, 3] - prev.T_odom_camera[:3, 3]))
            turn = prev.turn_deg + _angle_deg(np.linalg.inv(prev.T_odom_camera) @ T_odom_camera)
        row = len(self._nodes)
        self._nodes.append(_Node(key, float(stamp), np.asarray(T_odom_camera, np.float64), path, turn))
        self._session_of_row.append(sid)
        rows.append(row)
        self._row[key] = row
        self.index.add(row, codes)
        if features is not None and self._load is None:
            self._features[key] = features
        return row

    def _resting(self, key: NodeKey) -> bool:
        """Whether ``key``'s session had a loop edge within its last ``loop_gap`` keyframes."""
        session = (key[0], key[1])
        last = self._last_loop.get(session)
        if last is None:
            return False
        return len(self._session_rows[self._sessions[session]]) - last <= self.cfg.loop_gap

    def _allowed(self, row: int) -> NDArray[np.bool_]:
        """Index rows that may be candidates for ``row``: not itself, not the recent past of
        its own session."""
        node = self._nodes[row]
        n = len(self._nodes)
        allowed = np.ones(n, bool)
        allowed[row] = False
        sid = self._session_of_row[row]
        for r in reversed(self._session_rows[sid]):
            other = self._nodes[r]
            old_enough = node.stamp - other.stamp >= self.cfg.recent_s
            if old_enough and node.path_m - other.path_m >= self.cfg.recent_path_m:
                break
            allowed[r] = False
        return allowed

    def _features_of(self, key: NodeKey) -> KeyframeFeatures | None:
        if self._load is not None:
            return self._load(key)
        return self._features.get(key)

    def _best_match(self, row: int, features: KeyframeFeatures, hits: list[tuple[int, float]],
                    rejected: Counter[str]) -> tuple[int, Verified] | None:
        """The verified candidate with the most inliers whose neighbour agrees."""
        best: tuple[int, Verified] | None = None
        for cand_row, _similarity in hits:
            cand = self._nodes[cand_row]
            cand_features = self._features_of(cand.key)
            if cand_features is None:
                rejected["no features"] += 1
                continue
            found = verify_pair(features, cand_features, self.cfg.verify)
            if isinstance(found, str):
                rejected[found] += 1
                continue
            if best is not None and found.inliers <= best[1].inliers:
                continue  # cannot win: its neighbour need not be verified
            if not self._neighbour_agrees(features, cand_row, found, rejected):
                continue
            best = (cand_row, found)
        return best

    def _neighbour_agrees(self, features: KeyframeFeatures, cand_row: int, found: Verified,
                          rejected: Counter[str]) -> bool:
        """Verify against the candidate's session neighbour (next, else previous) and compare."""
        sid = self._session_of_row[cand_row]
        rows = self._session_rows[sid]
        i = rows.index(cand_row)
        for j in (i + 1, i - 1):
            if not 0 <= j < len(rows):
                continue
            nb = self._nodes[rows[j]]
            nb_features = self._features_of(nb.key)
            if nb_features is None:
                continue
            second = verify_pair(features, nb_features, self.cfg.verify)
            if isinstance(second, str):
                rejected[f"neighbour: {second}"] += 1
                return False
            cand = self._nodes[cand_row]
            T_cand_nb = np.linalg.inv(cand.T_odom_camera) @ nb.T_odom_camera
            chained = np.asarray(T_cand_nb @ second.T_cand_query, np.float64)
            if not _agree(found.T_cand_query, chained, self.cfg.agree_m, self.cfg.agree_deg):
                rejected["neighbour disagrees"] += 1
                return False
            return True
        rejected["no neighbour"] += 1
        return False

    def _accept(self, row: int, match: tuple[int, Verified], rejected: Counter[str]) -> Closure | None:
        """Gate a verified match against the graph, or count it as an anchoring vote."""
        cand_row, found = match
        node, cand = self._nodes[row], self._nodes[cand_row]
        a, b = node.key, cand.key
        T_a_b = np.asarray(np.linalg.inv(found.T_cand_query), np.float64)
        sa, sb = (a[0], a[1]), (b[0], b[1])
        on_a, on_b = self.anchored(sa), self.anchored(sb)
        if (on_a and on_b) or sa == sb:
            # On one map: its estimates predict the match; one floating session: its odometry.
            Ta, Tb = ((self.graph.estimate(a), self.graph.estimate(b)) if on_a
                      else (node.T_odom_camera, cand.T_odom_camera))
            if Ta is not None and Tb is not None:
                predicted = np.asarray(np.linalg.inv(Ta) @ Tb, np.float64)
                d = node.path_m - cand.path_m if sa == sb else None
                slack = self.cfg.gate_per_m * abs(d) if d is not None else self.cfg.gate_cross_m
                limit = self.cfg.gate_m + slack
                if not _agree(predicted, T_a_b, limit, self.cfg.gate_deg):
                    rejected["inconsistent with the map"] += 1
                    return None
                closure = Closure(a, b, T_a_b, found.inliers, "loop" if on_a else "floating", found.sigmas)
                confirmed = self._confirmed_loop(sa, node, closure, Ta, Tb)
                if confirmed is None:
                    rejected["loop vote"] += 1
                    return None
                for c in (confirmed, closure):
                    self.graph.add_loop(c.a, c.b, c.T_a_b, inliers=c.inliers, sigmas=c.sigmas)
                return closure
            self.graph.add_loop(a, b, T_a_b, inliers=found.inliers, sigmas=found.sigmas)
            return Closure(a, b, T_a_b, found.inliers, "loop", found.sigmas)
        if on_a != on_b:
            floating, row_f = (sa, row) if not on_a else (sb, cand_row)
            closure = Closure(a, b, T_a_b, found.inliers, "anchor", found.sigmas)
            T_map_odom = self._implied_T_map_odom(closure, floating)
            if T_map_odom is None:
                return None
            votes = self._votes.setdefault(floating, [])
            node_f = self._nodes[row_f]
            votes.append(_Vote(T_map_odom, closure, node_f.path_m, node_f.turn_deg))
            del votes[:-MAX_VOTES]
            cluster = [v for v in votes
                       if _agree(v.T_map_odom, T_map_odom, self.cfg.agree_m, self.cfg.agree_deg)]
            span_m = max(v.path_m for v in cluster) - min(v.path_m for v in cluster)
            span_deg = max(v.turn_deg for v in cluster) - min(v.turn_deg for v in cluster)
            if len(cluster) < self.cfg.anchor_votes or (span_m < self.cfg.anchor_span_m
                                                         and span_deg < self.cfg.anchor_span_deg):
                rejected["anchor vote"] += 1
                return None
            rivals = [v for v in votes if all(v is not c for c in cluster)]
            rival = max((sum(_agree(w.T_map_odom, v.T_map_odom, self.cfg.agree_m, self.cfg.agree_deg)
                             for w in rivals) for v in rivals), default=0)
            if rival >= max(2, len(cluster) // 2):
                rejected["ambiguous anchor"] += 1
                return None
            if self._contradicted(floating, T_map_odom, cluster):
                rejected["anchor contradicted"] += 1
                del self._votes[floating]
                return None
            for v in cluster[:-1]:
                self.graph.add_loop(v.closure.a, v.closure.b, v.closure.T_a_b, inliers=v.closure.inliers,
                                    sigmas=v.closure.sigmas)
            self.graph.add_loop(a, b, T_a_b, inliers=found.inliers, sigmas=found.sigmas)
            del self._votes[floating]
            return closure
        # Two sessions both off the map: nothing predicts the match and nothing checks it; each
        # is anchored through the map instead.
        rejected["both off the map"] += 1
        return None

    def _confirmed_loop(self, session: Session, node: _Node, closure: Closure, Ta: F64, Tb: F64
                        ) -> Closure | None:
        """The pending loop of ``session`` that confirms ``closure``, or None (it waits).

        Each loop implies a correction of the map, ``C = T_map_b @ inv(T_a_b) @ inv(T_map_a)``
        (where the match puts keyframe ``a``, relative to where the map has it). A loop is
        accepted when a loop from another keyframe of the same session, at most
        ``loop_window_m`` of driving before, implies the same correction (the two put this
        keyframe within ``agree_m`` / ``agree_deg`` of each other), as ORB-SLAM2 asks
        consecutive keyframes to agree before it closes a loop: a twin place rarely fools two
        keyframes the same way."""
        C = np.asarray(Tb @ np.linalg.inv(closure.T_a_b) @ np.linalg.inv(Ta), np.float64)
        pending = [p for p in self._loop_votes.get(session, [])
                   if 0.0 <= node.path_m - p[0] <= self.cfg.loop_window_m]
        here = C @ Ta
        for _, C_other, other in pending:
            if other.a != closure.a and _agree(np.asarray(C_other @ Ta, np.float64), here,
                                               self.cfg.agree_m, self.cfg.agree_deg):
                self._loop_votes[session] = [p for p in pending if p[2] is not other]
                return other
        self._loop_votes[session] = [*pending, (node.path_m, C, closure)][-MAX_VOTES:]
        return None

    def _contradicted(self, floating: Session, T_map_odom: F64, cluster: list[_Vote]) -> bool:
        """Whether the floating session's other keyframes, put on the map by ``T_map_odom``,
        fail to match the map where it has keyframes seeing the same (within ``check_m`` and
        ``check_deg``): up to ``check_keyframes`` of them, spread over the session; a
        contradiction is a failed verification, a support one that agrees. Contradicted when
        at least two fail and fewer agree."""
        sid = self._sessions[floating]
        voters = {v.closure.a if v.closure.a[:2] == floating else v.closure.b for v in cluster}
        rows = [r for r in self._session_rows[sid] if self._nodes[r].key not in voters]
        if not rows:
            return False
        anchored = [n for n in self._nodes if self.anchored((n.key[0], n.key[1]))]
        if not anchored:
            return False
        T_map = self.graph.estimates([n.key for n in anchored])
        keys = [n.key for n, T in zip(anchored, T_map, strict=True) if T is not None]
        poses = np.stack([T for T in T_map if T is not None])
        step = max(1, len(rows) // self.cfg.check_keyframes)
        fails = agrees = 0
        for r in rows[::step][: self.cfg.check_keyframes]:
            node = self._nodes[r]
            T = T_map_odom @ node.T_odom_camera
            near = np.linalg.norm(poses[:, :3, 3] - T[:3, 3], axis=1)
            # the same view: close, and looking the same way (optical axes, camera z)
            cos_max = math.cos(math.radians(self.cfg.check_deg))
            same_way = np.einsum("i,ni->n", T[:3, 2], poses[:, :3, 2]) >= cos_max
            hits = np.flatnonzero((near <= self.cfg.check_m) & same_way)
            if hits.size == 0:
                continue
            j = int(hits[np.argmin(near[hits])])
            mine, theirs = self._features_of(node.key), self._features_of(keys[j])
            if mine is None or theirs is None:
                continue
            found = verify_pair(mine, theirs, self.cfg.verify)
            if isinstance(found, str):
                fails += 1
                continue
            T_expected = np.linalg.inv(poses[j]) @ T
            agrees += int(_agree(found.T_cand_query, np.asarray(T_expected, np.float64), 3 * self.cfg.agree_m,
                                 3 * self.cfg.agree_deg))
        return fails >= 2 and agrees < fails

    def _implied_T_map_odom(self, closure: Closure, floating: Session) -> F64 | None:
        """The floating session's ``T_map_odom`` that this match implies."""
        a, b = closure.a, closure.b
        if (a[0], a[1]) == floating:
            Tb = self.graph.estimate(b)
            if Tb is None:
                return None
            T_map_a = Tb @ np.linalg.inv(closure.T_a_b)
            return np.asarray(T_map_a @ np.linalg.inv(self._nodes[self._row[a]].T_odom_camera), np.float64)
        Ta = self.graph.estimate(a)
        if Ta is None:
            return None
        T_map_b = Ta @ closure.T_a_b
        return np.asarray(T_map_b @ np.linalg.inv(self._nodes[self._row[b]].T_odom_camera), np.float64)


def _pose_bytes(T: F64) -> bytes:
    return np.asarray(T, "<f8").reshape(16).tobytes()


def _pose_from(blob: bytes) -> F64:
    T = np.frombuffer(blob, "<f8").astype(np.float64)
    if T.shape != (16,) or not np.all(np.isfinite(T)):
        raise ValueError("a stored pose is not 16 finite float64")
    return T.reshape(4, 4)


def _closure_list(c: Closure) -> list[object]:
    sigmas = None if c.sigmas is None else np.asarray(c.sigmas, "<f8").tobytes()
    return [list(c.a), list(c.b), _pose_bytes(c.T_a_b), c.inliers, c.kind, sigmas]


def _closure_from(item: Sequence[object]) -> Closure:
    a, b, T, inliers, kind, sigmas = item
    if kind not in ("loop", "anchor", "floating"):
        raise ValueError(f"unknown closure kind {kind!r}")
    key_a, key_b = (cast(Sequence[object], k) for k in (a, b))
    return Closure((str(key_a[0]), str(key_a[1]), int(cast(int, key_a[2]))),
                   (str(key_b[0]), str(key_b[1]), int(cast(int, key_b[2]))), _pose_from(cast(bytes, T)),
                   int(cast(int, inliers)), kind,
                   None if sigmas is None else np.frombuffer(cast(bytes, sigmas), "<f8").astype(np.float64))


def _merged(first: GraphUpdate, second: GraphUpdate) -> GraphUpdate:
    """Two consecutive graph updates as one: the larger move, sessions reported by either
    (the second's newer values), anchored by either."""
    return GraphUpdate(moved_m=max(first.moved_m, second.moved_m),
                       sessions={**first.sessions, **second.sessions},
                       anchored=first.anchored + tuple(s for s in second.anchored if s not in first.anchored))


def _angle_deg(T: F64) -> float:
    """Rotation angle of a pose, degrees."""
    return math.degrees(math.acos(float(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))


def _agree(T1: F64, T2: F64, max_m: float, max_deg: float) -> bool:
    """Whether two poses differ by at most ``max_m`` metres and ``max_deg`` degrees."""
    D = np.linalg.inv(T1) @ T2
    return float(np.linalg.norm(D[:3, 3])) <= max_m and _angle_deg(D) <= max_deg


__all__ = ["BackendConfig", "BackendCore", "Closure", "EdgeRecord", "FeatureLoader", "KeyframeResult",
           "NodeRecord"]

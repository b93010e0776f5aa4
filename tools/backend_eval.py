"""Scores of the SLAM back-end against simulator ground truth (``bench/backend.py``).

Pure functions on poses; keyframes are ``(robot_id, session_id, seq)`` keys and every pose is
(4, 4) float64 ``T_a_b`` (docs/ARCHITECTURE.md "Conventions"). Ground truth is each keyframe's
camera ``T_world_camera``; the estimate of the back-end is ``T_map_camera``.

- **Pose error** of an estimate ``T_est`` against ``T_ref``: the translation (m) and rotation
  angle (deg) of ``inv(T_ref) @ T_est``.
- **Closure truth**: a loop edge ``T_a_b`` (keyframe b's camera in keyframe a's) is *true* when
  its pose error against ``inv(T_world_a) @ T_world_b`` is within ``max_m`` and ``max_deg``
  (default 0.3 m, 5 deg: a verified match to the right place is off by centimetres; one to an
  identical twin door or chair by the twin's spacing, >= 0.5 m).
- **Revisit events and recall at the first revisit**: a keyframe *revisits* when an earlier
  processed keyframe (any robot, any session) had a ground-truth camera within ``radius_m``
  (1 m) and ``max_deg`` (30 deg) of its own, and that earlier keyframe is of another session
  or at least ``min_gap_s`` (30 s) older. A session's revisiting keyframes, in seq order,
  form runs (gaps of up to ``max_gap`` non-revisiting keyframes joined); a run of at least
  ``min_keyframes`` (3) is a *revisit event*. An event is *recalled* when a true loop edge
  from one of its first ``window`` (10) keyframes entered the graph. Recall = recalled
  events / events.
- **Session alignment**: a session's ground-truth ``T_world_odom`` at keyframe k is
  ``T_world_camera_k @ inv(T_odom_camera_k)``; its estimate ``T_map_odom`` at k is
  ``T_map_camera_k @ inv(T_odom_camera_k)``. The alignment error of session s relative to a
  reference session r (the one that anchored the map) is the pose error of
  ``inv(T_map_odom_r) @ T_map_odom_s`` against ``inv(T_world_odom_r) @ T_world_odom_s``.
- **Session alignment, trajectories fitted** (the alignment of two sessions' maps as wholes,
  not of two single keyframes): each session's estimated cameras are fitted to ground truth by
  a rigid motion (rotation: chordal mean of the orientation errors; translation: centroids;
  :func:`fit_to_world`), ``T_world_map_s`` and ``T_world_map_r``; the
  error is the RMS over session s's keyframes of how far the two fits place each of them apart
  (``|T_world_map_s p - T_world_map_r p|``) and the rotation angle between the fits. Zero when
  both sessions' maps are placed alike, whatever their own shape errors (their ATE).
- **Map ATE**: the estimated camera centres of all sessions fitted to ground truth by one rigid
  motion (Umeyama, as ATE), translation RMSE: the error of the shared map as one whole.
- **Same-place agreement** (relative alignment where it matters for a shared map): for each
  keyframe of a session, the keyframe of *another* session nearest in ground truth (camera
  centres within ``radius_m``, optical axes within ``max_deg``); its error is the pose error of
  the estimated relative pose ``inv(T_map_other) @ T_map_this`` against ground truth's. Objects
  that two robots measure from such keyframes land apart by about this much.
- **Pose-graph floor**: the same graph (the frontend's odometry, the same sigmas), but with a
  ground-truth loop edge (tight sigmas) from every revisiting keyframe to its nearest earlier
  one (the revisit definition above): the ATE a pose graph over this odometry reaches with
  perfect and complete loop closures; what is left is the odometry's own shape error, which
  only re-estimating the keyframes from their features (bundle adjustment) can remove.
- **Object maps compared**: the confirmed landmarks of two maps of one world are paired within
  each category, nearest centres first (greedy), up to ``max_m`` apart; offsets are the
  centre distances of the pairs. A ground-truth object is *duplicated* in a map when two or
  more confirmed landmarks have it as their majority object (``gt_instance`` of their
  measurements).
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from evo.core.geometry import umeyama_alignment
from numpy.typing import ArrayLike, NDArray

from wardmap.server.association.types import Landmark
from wardmap.server.backend.graph import GraphConfig, PoseGraph
from wardmap.shared.errors import WardmapError
from wardmap.shared.metrics import ate
from wardmap.shared.se3 import inverse
from wardmap.shared.wire import PoseSource

__all__ = [
    "ClosureCheck",
    "LandmarkPair",
    "RevisitEvent",
    "alignment_error",
    "check_closure",
    "duplicated_objects",
    "fit_pairs",
    "fit_to_world",
    "fitted_alignment_error",
    "frame_rmse",
    "majority_object",
    "map_ate",
    "pair_landmarks",
    "pose_error",
    "pose_graph_floor",
    "recalled",
    "revisit_events",
    "same_place_errors",
    "trajectory_ate",
]

F64 = NDArray[np.float64]
NodeKey = tuple[str, str, int]


def pose_error(T_est: ArrayLike, T_ref: ArrayLike) -> tuple[float, float]:
    """Translation (m) and rotation angle (deg) of ``inv(T_ref) @ T_est``; both (4, 4)."""
    D = inverse(np.asarray(T_ref, np.float64)) @ np.asarray(T_est, np.float64)
    R = D[:3, :3]
    # atan2 of sin and cos stays accurate near 0 (arccos of the trace loses ~1e-6 deg there)
    sin = 0.5 * float(np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]))
    cos = 0.5 * (float(np.trace(R)) - 1.0)
    return float(np.linalg.norm(D[:3, 3])), math.degrees(math.atan2(sin, cos))


@dataclass(frozen=True)
class ClosureCheck:
    """One loop edge scored against ground truth.

    Attributes:
        a, b: its keyframes; error_m, error_deg: pose error of its ``T_a_b``; true: within the limits.
    """

    a: NodeKey
    b: NodeKey
    error_m: float
    error_deg: float
    true: bool


def check_closure(a: NodeKey, b: NodeKey, T_a_b: ArrayLike, T_world_a: ArrayLike, T_world_b: ArrayLike,
                  *, max_m: float = 0.3, max_deg: float = 5.0) -> ClosureCheck:
    """Score loop edge ``T_a_b`` (4, 4) against the ground-truth cameras ``T_world_a``, ``T_world_b``."""
    m, deg = pose_error(T_a_b, inverse(np.asarray(T_world_a, np.float64)) @ np.asarray(T_world_b, np.float64))
    return ClosureCheck(a, b, m, deg, m <= max_m and deg <= max_deg)


@dataclass(frozen=True)
class RevisitEvent:
    """A session's return to a place seen before: its revisiting keyframes in seq order."""

    keys: tuple[NodeKey, ...]

    @property
    def first(self) -> NodeKey:
        return self.keys[0]


def revisit_events(
    order: Sequence[NodeKey],
    stamps: Sequence[float],
    truth: Sequence[ArrayLike],
    *,
    radius_m: float = 1.0,
    max_deg: float = 30.0,
    min_gap_s: float = 30.0,
    max_gap: int = 3,
    min_keyframes: int = 3,
) -> list[RevisitEvent]:
    """Revisit events (module docstring) of keyframes processed in ``order``.

    Args:
        order: keyframes in processing order (N); within a session in seq order.
        stamps: (N,) their stamps, seconds.
        truth: (N) ground-truth ``T_world_camera`` (4, 4) of each.

    Returns:
        Events ordered by their first keyframe's position in ``order``.
    """
    n = len(order)
    if len(stamps) != n or len(truth) != n:
        raise WardmapError(f"revisit_events: {n} keys, {len(stamps)} stamps, {len(truth)} poses")
    T = np.asarray(truth, np.float64).reshape(n, 4, 4)
    t = np.asarray(stamps, np.float64)
    sessions = [(k[0], k[1]) for k in order]
    sid = np.array([sorted(set(sessions)).index(s) for s in sessions]) if n else np.zeros(0, int)
    centres = T[:, :3, 3]
    cos_max = math.cos(math.radians(max_deg))
    revisits = np.zeros(n, bool)
    for q in range(1, n):
        near = np.linalg.norm(centres[:q] - centres[q], axis=1) <= radius_m
        # rotation angle of inv(R_p) @ R_q: trace(R_p^T R_q) = sum of elementwise products
        cos = (np.einsum("pij,ij->p", T[:q, :3, :3], T[q, :3, :3]) - 1.0) / 2.0
        apart = (sid[:q] != sid[q]) | (t[:q] <= t[q] - min_gap_s)
        revisits[q] = bool(np.any(near & (cos >= cos_max - 1e-12) & apart))
    events: list[tuple[int, list[int]]] = []
    for s in sorted(set(sid.tolist())):
        rows = [i for i in range(n) if sid[i] == s]
        run: list[int] = []
        gap = 0
        for i in rows:
            if revisits[i]:
                run.append(i)
                gap = 0
            elif run:
                gap += 1
                if gap > max_gap:
                    events.append((run[0], run))
                    run, gap = [], 0
        if run:
            events.append((run[0], run))
    out = []
    for first, run in sorted(events):
        # the event spans the run's keyframes in seq order, joined gaps included
        rows = [i for i in range(n) if sid[i] == sid[first] and run[0] <= i <= run[-1]]
        if len(run) >= min_keyframes:
            out.append(RevisitEvent(tuple(order[i] for i in rows)))
    return out


def recalled(event: RevisitEvent, true_closure_keys: set[NodeKey], window: int = 10) -> bool:
    """Whether a true loop edge starts at one of the event's first ``window`` keyframes."""
    return any(k in true_closure_keys for k in event.keys[:window])


def alignment_error(T_map_odom: ArrayLike, T_map_odom_ref: ArrayLike, T_world_odom: ArrayLike,
                    T_world_odom_ref: ArrayLike) -> tuple[float, float]:
    """Error (m, deg) of a session's alignment relative to the reference session (module docstring).

    Args:
        T_map_odom, T_map_odom_ref: (4, 4) estimated odom frames of the session and the reference.
        T_world_odom, T_world_odom_ref: (4, 4) their ground truth.
    """
    est = inverse(np.asarray(T_map_odom_ref, np.float64)) @ np.asarray(T_map_odom, np.float64)
    ref = inverse(np.asarray(T_world_odom_ref, np.float64)) @ np.asarray(T_world_odom, np.float64)
    return pose_error(est, ref)


def frame_rmse(T_world_frame: ArrayLike, T_frame_camera: Sequence[ArrayLike],
               T_world_camera: Sequence[ArrayLike]) -> float:
    """Translation RMSE (m) of cameras given in a frame placed in the world by ``T_world_frame``
    (4, 4), against ground truth ``T_world_camera`` (each (N) (4, 4)); no alignment: the error a
    map built in that frame has."""
    W = np.asarray(T_world_frame, np.float64)
    est = np.einsum("ij,njk->nik", W, np.asarray(T_frame_camera, np.float64).reshape(-1, 4, 4))
    ref = np.asarray(T_world_camera, np.float64).reshape(-1, 4, 4)
    if est.shape != ref.shape or not len(est):
        raise WardmapError(f"frame_rmse: {len(est)} estimates for {len(ref)} reference poses")
    return float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - ref[:, :3, 3]) ** 2, axis=1))))


def fit_to_world(T_est: Sequence[ArrayLike], T_ref: Sequence[ArrayLike], *,
                 rotation: Literal["positions", "orientations"] = "positions") -> F64:
    """``T_world_map`` (4, 4): the rigid motion (no scale) that best fits the cameras ``T_est``
    (each (4, 4), in the map) onto ``T_ref`` (ground truth). ``positions``: least squares over
    camera centres (Umeyama, evo; as ATE); ``orientations``: the rotation is the chordal mean
    of ``R_ref @ R_est.T`` (well posed also for a camera that turns on the spot), the
    translation then fits the centroids. Raises WardmapError with fewer than 3 poses or unequal
    counts."""
    est = np.asarray(T_est, np.float64).reshape(-1, 4, 4)
    ref = np.asarray(T_ref, np.float64).reshape(-1, 4, 4)
    if est.shape != ref.shape or len(est) < 3:
        raise WardmapError(f"fit_to_world: {len(est)} estimates for {len(ref)} reference poses (need >= 3)")
    if rotation == "positions":
        R, t, _ = umeyama_alignment(est[:, :3, 3].T, ref[:, :3, 3].T, with_scale=False)
    else:
        U, _, Vt = np.linalg.svd(np.einsum("nij,nkj->ik", ref[:, :3, :3], est[:, :3, :3]))
        R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        t = ref[:, :3, 3].mean(0) - R @ est[:, :3, 3].mean(0)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def fitted_alignment_error(T_world_map: ArrayLike, T_world_map_ref: ArrayLike,
                           T_map_camera: Sequence[ArrayLike]) -> tuple[float, float]:
    """Session alignment, trajectories fitted (module docstring): RMS (m) over the session's
    cameras ``T_map_camera`` (each (4, 4)) of their distance under the session's own fit
    ``T_world_map`` and the reference session's ``T_world_map_ref`` (both (4, 4)), and the
    angle (deg) between the fits."""
    W, Wr = np.asarray(T_world_map, np.float64), np.asarray(T_world_map_ref, np.float64)
    p = np.asarray(T_map_camera, np.float64).reshape(-1, 4, 4)[:, :3, 3]
    if not len(p):
        raise WardmapError("fitted_alignment_error: no cameras")
    d = p @ (W[:3, :3] - Wr[:3, :3]).T + (W[:3, 3] - Wr[:3, 3])
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1)))), pose_error(W, Wr)[1]


def map_ate(T_est: Sequence[ArrayLike], T_ref: Sequence[ArrayLike]) -> float:
    """Map ATE (m, module docstring): translation RMSE of ``T_est`` (all sessions' cameras in
    the map) against ``T_ref`` after one rigid fit (:func:`fit_to_world`)."""
    W = fit_to_world(T_est, T_ref)
    return frame_rmse(W, T_est, T_ref)


def trajectory_ate(stamps: Sequence[float], T_est: Sequence[ArrayLike], T_ref: Sequence[ArrayLike]) -> float:
    """ATE RMSE (m) of ``T_est`` against ``T_ref`` (each (N) (4, 4), one pose per stamp), after an
    SE3 (Umeyama) alignment (evo, :func:`wardmap.shared.metrics.ate`)."""
    s = np.asarray(stamps, np.float64)
    return ate(s, np.asarray(T_est, np.float64), s, np.asarray(T_ref, np.float64), max_diff_s=1e-6).rmse



def _nearest(T: Sequence[F64], i: int, others: Iterable[int], radius_m: float, max_deg: float) -> int | None:
    """The one of ``others`` whose camera ``T[j]`` is nearest ``T[i]``, within ``radius_m`` and
    with optical axes within ``max_deg``; None when none is."""
    cos_max = math.cos(math.radians(max_deg))
    best: tuple[float, int] | None = None
    for j in others:
        d = float(np.linalg.norm(T[i][:3, 3] - T[j][:3, 3]))
        if d <= radius_m and float(T[i][:3, 2] @ T[j][:3, 2]) >= cos_max and (best is None or d < best[0]):
            best = (d, j)
    return None if best is None else best[1]


def same_place_errors(keys: Sequence[NodeKey], truth: Sequence[ArrayLike],
                      estimates: Sequence[ArrayLike | None], session: tuple[str, str], *,
                      radius_m: float = 1.0, max_deg: float = 30.0) -> list[tuple[float, float]]:
    """Same-place agreement (module docstring) of ``session``'s keyframes: one (m, deg) error per
    keyframe that has another session's keyframe near it in ground truth (both estimated)."""
    T = [np.asarray(t, np.float64) for t in truth]
    others = [j for j, o in enumerate(keys) if (o[0], o[1]) != session and estimates[j] is not None]
    out = []
    for i, k in enumerate(keys):
        if (k[0], k[1]) != session or estimates[i] is None:
            continue
        j = _nearest(T, i, others, radius_m, max_deg)
        if j is not None:
            est = inverse(np.asarray(estimates[j], np.float64)) @ np.asarray(estimates[i], np.float64)
            out.append(pose_error(est, inverse(T[j]) @ T[i]))
    return out


def pose_graph_floor(keys: Sequence[NodeKey], stamps: Sequence[float], T_odom_camera: Sequence[ArrayLike],
                     pose_sources: Sequence[PoseSource], truth: Sequence[ArrayLike], config: GraphConfig,
                     *, radius_m: float = 1.0, max_deg: float = 30.0, min_gap_s: float = 30.0,
                     sigma_m: float = 1e-3, sigma_rad: float = 1e-3) -> dict[tuple[str, str], F64]:
    """The pose-graph floor (module docstring): keyframes in processing order; returns each
    anchored session's final ``T_map_camera`` estimates (n, 4, 4) in its keyframes' order."""
    graph = PoseGraph(dataclasses.replace(config, loop_sigma_scale=1.0, loop_trans_floor_m=sigma_m,
                                          loop_rot_floor_deg=math.degrees(sigma_rad)))
    T = [np.asarray(t, np.float64) for t in truth]
    sigmas = np.array([sigma_rad] * 3 + [sigma_m] * 3)
    for i, k in enumerate(keys):
        graph.add_keyframe(k, T_odom_camera[i], pose_source=pose_sources[i])
        earlier = (j for j in range(i) if keys[j][:2] != k[:2] or stamps[i] - stamps[j] >= min_gap_s)
        j = _nearest(T, i, earlier, radius_m, max_deg)
        if j is not None:
            graph.add_loop(keys[j], k, inverse(T[j]) @ T[i], inliers=1000, sigmas=sigmas)
        graph.update()
    out: dict[tuple[str, str], F64] = {}
    for session in dict.fromkeys((k[0], k[1]) for k in keys):
        mine = [k for k in keys if (k[0], k[1]) == session]
        est = graph.estimates(mine)
        if all(e is not None for e in est):
            out[session] = np.stack([np.asarray(e) for e in est])
    return out


@dataclass(frozen=True)
class LandmarkPair:
    """A landmark of map a and its partner in map b (same category), ``offset_m`` apart."""

    a: Landmark
    b: Landmark
    offset_m: float


def pair_landmarks(a: Sequence[Landmark], b: Sequence[Landmark], *, max_m: float = 1.0) -> list[LandmarkPair]:
    """Pair the confirmed landmarks of two maps in one frame: per category, nearest centres
    (``T_world_object`` translations) first, each landmark at most once, pairs up to ``max_m``."""
    a = [lm for lm in a if lm.confirmed]
    b = [lm for lm in b if lm.confirmed]
    candidates = sorted(
        (float(np.linalg.norm(la.T_world_object[:3, 3] - lb.T_world_object[:3, 3])), i, j)
        for i, la in enumerate(a) for j, lb in enumerate(b) if la.category == lb.category
    )
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs = []
    for d, i, j in candidates:
        if d > max_m:
            break
        if i in used_a or j in used_b:
            continue
        used_a.add(i)
        used_b.add(j)
        pairs.append(LandmarkPair(a[i], b[j], d))
    return pairs


def fit_pairs(pairs: Sequence[LandmarkPair]) -> F64:
    """The rigid motion (4, 4, no scale) that best moves the paired landmarks of map b onto
    their partners in map a (least squares over centres, Umeyama); identity with fewer than 3
    pairs."""
    T = np.eye(4)
    if len(pairs) < 3:
        return T
    b = np.stack([p.b.T_world_object[:3, 3] for p in pairs], 1)
    a = np.stack([p.a.T_world_object[:3, 3] for p in pairs], 1)
    R, t, _ = umeyama_alignment(b, a, with_scale=False)
    T[:3, :3], T[:3, 3] = R, t
    return T


def majority_object(landmark: Landmark) -> int | None:
    """The ground-truth object most of a landmark's measurements are on (None: none known)."""
    votes = Counter(i for i in landmark.gt_instances if i is not None)
    return votes.most_common(1)[0][0] if votes else None


def duplicated_objects(landmarks: Sequence[Landmark]) -> dict[int, int]:
    """Ground-truth object id -> number of confirmed landmarks it is the majority object of, for
    every object with two or more."""
    counts = Counter(majority_object(lm) for lm in landmarks if lm.confirmed)
    return {i: n for i, n in counts.items() if i is not None and n > 1}

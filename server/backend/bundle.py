"""Bundle adjustment over stored keyframes: ORB keypoints with depth, RGB-D "stereo" factors.

The pose graph can only spread the frontend's odometry error between a loop's ends
(decision 0034); re-estimating the keyframe poses from their features removes part of it.
:func:`bundle_adjust` takes keyframes with initial map poses (the pose graph's estimates after
loop closure) and joins their keypoints into tracks (a track never holds two keypoints of one
keyframe): within a session by the edge tracker's map point ids where the keyframes carry them
(the tracker's own association) and by matching ORB descriptors between keyframes up to
``window`` apart (:attr:`BundleConfig.tracks`); and by matching descriptors between keyframes
whose initial poses are close (revisits, across sessions). Then it solves
ORB-SLAM2's RGB-D bundle adjustment with gtsam:

- a keypoint with depth ``d`` is a stereo measurement ``(u_L, u_R, v)`` with the virtual right
  coordinate ``u_R = u_L - bf / d`` (ORB-SLAM2's ``mbf``), a ``GenericStereoFactor3D``;
- a keypoint without depth is a monocular ``GenericProjectionFactorCal3_S2``;
- sigma ``pixel_sigma * scale_factor ** octave`` pixels, under a Huber kernel at the 95 %
  chi-square bound (``sqrt(7.815)`` for 3 dof, ``sqrt(5.991)`` for 2), Levenberg-Marquardt;
  then, as ORB-SLAM2's global BA, observations beyond those bounds are dropped and the
  problem is solved once more;
- the first keyframe's pose is held fixed (the gauge).

Keypoints are undistorted before use. Frames: ``T_map_camera`` (4, 4) maps camera
coordinates (x right, y down, z forward, metres) into the map frame.
"""

from __future__ import annotations

import time
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import gtsam
import numpy as np
from numpy.typing import NDArray

from wardmap.server.backend.verify import KeyframeFeatures
from wardmap.shared.errors import GeometryError
from wardmap.shared.hamming import knn2
from wardmap.shared.wire import POINT_ID_SPAN

F64 = NDArray[np.float64]

_CHI2_3DOF = 7.815  # 95 % bound, stereo (u_L, u_R, v)
_CHI2_2DOF = 5.991  # 95 % bound, monocular (u, v)
TrackSource = Literal["ids", "descriptors", "both"]
_WEAK_PRIOR = 1.0  # rad and m: a prior on every pose that only matters where no feature is


@dataclass(frozen=True)
class BundleConfig:
    """Matching and noise model of :func:`bundle_adjust` (chosen on tuning world 1001)."""

    window: int = 10
    """Keyframes up to this many apart in the input order are matched (the covisible span of
    a keyframe stream at 2 Hz), unless both carry map point ids and ``tracks`` is ``ids``."""
    tracks: TrackSource = "both"
    """How keypoints of one chain (session) join into tracks: ``both``: by the edge tracker's
    map point id (``KeyframeFeatures.point_id``: the tracker matched the keypoint against its
    local map at the pose it measured), then descriptor matches within the window join those
    tracks too (the tracker re-makes a point it failed to match, so its own tracks are
    short); ``ids``: by id only where both keyframes carry ids, descriptors
    where they do not; ``descriptors``: ids ignored. Revisits always match descriptors
    (decision 0044)."""
    revisit_radius_m: float = 1.5
    """Keyframes further apart in sequence are matched when their initial camera centres are
    within this distance ..."""
    revisit_angle_deg: float = 35.0
    """... and their viewing directions within this angle (the loop's revisits)."""
    max_hamming: int = 40
    """Largest descriptor distance of a match, bits of 256."""
    ratio: float = 0.8
    """Lowe's ratio test; matches must also be mutual best."""
    gate_px: float = 2.0
    """A match is kept when the matched point, back-projected with its depth and the initial
    poses, lands within this many pixels of the other keypoint (tight: in front of a row of
    identical chairs, looser gates let in matches that pull the solution off by centimetres)."""
    depth_range_m: tuple[float, float] = (0.1, 20.0)
    """Depths outside this range count as no depth (monocular observation); far depth is
    weighted down by ``bf`` rather than cut."""
    bf: float = 500.0
    """Virtual stereo baseline times focal length, pixel-metres (ORB-SLAM2's ``Camera.bf``):
    sets how much depth weighs: a disparity sigma of s pixels is a depth sigma of
    ``s * d**2 / bf`` metres (0.5 px at 2 m: 4 mm)."""
    pixel_sigma: float = 0.5
    """Keypoint position sigma at octave 0, pixels (also sets the chi-square bound beyond
    which the second solve drops an observation: 1.4 px in the image at octave 0)."""
    scale_factor: float = 1.2
    """ORB pyramid scale between octaves (sigma grows by it per octave)."""
    iterations: int = 30
    """Levenberg-Marquardt iterations per solve."""
    level_sigmas: tuple[float, float] | None = (0.5, 0.02)
    """Prior of a frame with ``up`` set (a ground robot's): sigmas of its tilt about the
    horizontal axes (degrees) and of its height along ``up`` (metres) about its initial pose,
    which the edge's floor levelling made good (decision 0026); None: no prior. Without it
    the adjustment drifts in pitch and height like the unlevelled frontend (decision 0036)."""

    def __post_init__(self) -> None:
        if self.window < 1:
            raise GeometryError(f"bundle window must be >= 1, got {self.window}")
        if self.tracks not in get_args(TrackSource):
            raise GeometryError(
                f"bundle tracks: expected one of {', '.join(get_args(TrackSource))}, got {self.tracks!r:.40}")
        if not (self.bf > 0 and self.pixel_sigma > 0 and self.gate_px > 0 and self.scale_factor >= 1):
            raise GeometryError("bundle config: bf, pixel_sigma, gate_px must be > 0, scale_factor >= 1")


@dataclass(frozen=True)
class BundleFrame:
    """One keyframe for :func:`bundle_adjust`.

    Attributes:
        key: any hashable identifier (the back-end uses its node key).
        T_map_camera: (4, 4) initial pose of the colour camera in the map.
        features: keypoints (pixels, depth in metres, ORB descriptors, octaves) and camera.
        chain: the keyframe stream it belongs to (the back-end: its session); the sequence
            window pairs only frames of one chain, revisits pair any.
        up: (3,) unit vector, the map's up direction, for a frame of a robot on a level floor
            (adds the level prior, :attr:`BundleConfig.level_sigmas`), or None.
        seq: the keyframe's number in its chain (the wire's ``seq``): map point ids join
            keypoints only of frames fewer than :data:`~wardmap.shared.wire.POINT_ID_SPAN`
            apart (ids travel modulo 2**31).
    """

    key: Hashable
    T_map_camera: F64
    features: KeyframeFeatures
    chain: Hashable = None
    up: F64 | None = None
    seq: int = 0


@dataclass(frozen=True)
class BundleResult:
    """Refined poses and what the solve used.

    Attributes:
        poses: ``key -> (4, 4) T_map_camera`` for every input frame (the first unchanged).
        landmarks: 3D points solved.
        observations: factors used in the final solve.
        dropped: observations dropped after the first solve (beyond the chi-square bound).
        error_before, error_after: gtsam's total factor error at the start and the end.
        ms: wall time in milliseconds.
    """

    poses: dict[Hashable, F64]
    landmarks: int
    observations: int
    dropped: int
    error_before: float
    error_after: float
    ms: float


class _Tracks:
    """Union-find over ``(frame index, keypoint index)`` that never puts two keypoints of one
    frame into a track."""

    def __init__(self) -> None:
        self.parent: dict[tuple[int, int], tuple[int, int]] = {}
        self.frames: dict[tuple[int, int], set[int]] = {}

    def find(self, a: tuple[int, int]) -> tuple[int, int]:
        root = a
        while self.parent.get(root, root) != root:
            root = self.parent[root]
        while a != root:  # path compression
            nxt = self.parent[a]
            self.parent[a] = root
            a = nxt
        return root

    def join(self, a: tuple[int, int], b: tuple[int, int]) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return
        fa, fb = self.frames.get(ra, {ra[0]}), self.frames.get(rb, {rb[0]})
        if fa & fb:
            return
        self.parent[rb] = ra
        self.parent.setdefault(ra, ra)
        self.frames[ra] = fa | fb
        self.frames.pop(rb, None)

    def tracks(self) -> list[list[tuple[int, int]]]:
        out: dict[tuple[int, int], list[tuple[int, int]]] = {}
        for a in self.parent:
            out.setdefault(self.find(a), []).append(a)
        return [t for t in out.values() if len(t) >= 2]


@dataclass(frozen=True)
class _Prepared:
    uv: F64  # (N, 2) undistorted pixels
    depth: F64  # (N,) metres, 0 = none
    points: F64  # (N, 3) map points from the initial pose (NaN without depth)
    sigma: F64  # (N,) pixel sigma


def _prepare(frame: BundleFrame, cfg: BundleConfig) -> _Prepared:
    f = frame.features
    cam = f.camera
    uv = np.asarray(f.uv, np.float64)
    if cam.has_distortion and len(uv):
        xy = np.stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy], 1)
        xy = cam.undistort_normalized(xy)
        uv = np.stack([xy[:, 0] * cam.fx + cam.cx, xy[:, 1] * cam.fy + cam.cy], 1)
    d = np.asarray(f.depth_m, np.float64)
    lo, hi = cfg.depth_range_m
    d = np.where((d >= lo) & (d <= hi), d, 0.0)
    pc = np.stack([(uv[:, 0] - cam.cx) / cam.fx * d, (uv[:, 1] - cam.cy) / cam.fy * d, d], 1)
    T = np.asarray(frame.T_map_camera, np.float64)
    pts = pc @ T[:3, :3].T + T[:3, 3]
    pts[d <= 0] = np.nan
    octave = np.zeros(len(uv)) if f.octave is None else np.maximum(np.asarray(f.octave, np.float64), 0)
    return _Prepared(uv, d, pts, cfg.pixel_sigma * cfg.scale_factor ** octave)


def _level_noise(frame: BundleFrame, sigmas: tuple[float, float]) -> gtsam.noiseModel.Base:
    """Noise of a prior that holds the camera's tilt and height (along ``frame.up``), free in
    the other three directions; in gtsam's Pose3 tangent order (rotation, translation), camera frame."""
    up_c = np.asarray(frame.T_map_camera, np.float64)[:3, :3].T @ np.asarray(frame.up, np.float64)
    up_c /= np.linalg.norm(up_c)
    a = np.array([1.0, 0.0, 0.0]) if abs(up_c[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(a, up_c)
    x /= np.linalg.norm(x)
    R_lc = np.stack([x, np.cross(up_c, x), up_c])  # rows: the level frame's axes in the camera
    tilt, height = np.radians(sigmas[0]), sigmas[1]
    free = 1e-6
    info_l = np.diag([1 / tilt**2, 1 / tilt**2, free, free, free, 1 / height**2])
    A = np.zeros((6, 6))
    A[:3, :3] = R_lc
    A[3:, 3:] = R_lc
    return gtsam.noiseModel.Gaussian.Information(A.T @ info_l @ A)


def _project(T_map_camera: F64, f: KeyframeFeatures, points: F64) -> tuple[F64, F64]:
    """Ideal (undistorted) pixels (N, 2) and depths (N,) of map points (N, 3) in a camera."""
    Ti = np.linalg.inv(T_map_camera)
    pc = points @ Ti[:3, :3].T + Ti[:3, 3]
    z = pc[:, 2]
    c = f.camera
    with np.errstate(invalid="ignore", divide="ignore"):
        uv = np.stack([c.fx * pc[:, 0] / z + c.cx, c.fy * pc[:, 1] / z + c.cy], 1)
    return uv, z


def _pairs(frames: Sequence[BundleFrame], cfg: BundleConfig) -> list[tuple[int, int]]:
    """Frame pairs ``(j, i)``, j < i, to match: the sequence window within a chain, then
    revisits; nearest in sequence first (tracks grow along the stream before they join
    across a loop). Frames of one chain must be consecutive in ``frames``."""
    n = len(frames)
    chains = [f.chain for f in frames]
    centres = np.stack([np.asarray(f.T_map_camera)[:3, 3] for f in frames])
    axes = np.stack([np.asarray(f.T_map_camera)[:3, 2] for f in frames])
    cos_max = np.cos(np.radians(cfg.revisit_angle_deg))
    window = {(j, i) for i in range(n) for j in range(max(0, i - cfg.window), i) if chains[j] == chains[i]}
    pairs = sorted(window)
    for i in range(n):
        far = np.array([j for j in range(i) if (j, i) not in window], dtype=np.int64)
        if not len(far):
            continue
        near = (np.linalg.norm(centres[far] - centres[i], axis=1) < cfg.revisit_radius_m) & (
            axes[far] @ axes[i] > cos_max)
        pairs.extend((int(j), i) for j in far[near])
    pairs.sort(key=lambda p: (p[1] - p[0], p[1]))
    return pairs


def _id_tracks(frames: Sequence[BundleFrame], tracks: _Tracks) -> None:
    """Join keypoints of one chain with the same map point id, in frames fewer than
    ``POINT_ID_SPAN`` apart (frames of a chain come in ``seq`` order)."""
    first: dict[tuple[Hashable, int], tuple[int, int]] = {}
    for k, f in enumerate(frames):
        pid = f.features.point_id
        if pid is None:
            continue
        for p in np.flatnonzero(pid >= 0).tolist():
            key = (f.chain, int(pid[p]))
            at = first.setdefault(key, (k, p))
            if at[0] == k:
                continue
            if abs(f.seq - frames[at[0]].seq) >= POINT_ID_SPAN:
                first[key] = (k, p)  # the id came round: another point
            else:
                tracks.join(at, (k, p))


def _has_ids(frame: BundleFrame) -> bool:
    return frame.features.point_id is not None


def _match(frames: Sequence[BundleFrame], prep: Sequence[_Prepared], cfg: BundleConfig) -> _Tracks:
    tracks = _Tracks()
    if cfg.tracks != "descriptors":
        _id_tracks(frames, tracks)
    for j, i in _pairs(frames, cfg):
        exact = cfg.tracks == "ids" and _has_ids(frames[i]) and _has_ids(frames[j])
        if exact and frames[i].chain == frames[j].chain and i - j <= cfg.window:
            continue  # joined by id
        fa, fb = frames[i].features, frames[j].features
        if not len(fa.descriptors) or not len(fb.descriptors):
            continue
        best, d1, d2, col_best = knn2(np.asarray(fa.descriptors), np.asarray(fb.descriptors))
        ok = (best >= 0) & (d1 <= cfg.max_hamming) & (d1 < cfg.ratio * d2)
        ia = np.nonzero(ok)[0]
        jb = best[ia]
        mutual = col_best[jb] == ia
        ia, jb = ia[mutual], jb[mutual]
        if not len(ia):
            continue
        Ti, Tj = np.asarray(frames[i].T_map_camera), np.asarray(frames[j].T_map_camera)
        # gate: j's point into i where j has depth, else i's point into j
        uv_i, z_i = _project(Ti, fa, prep[j].points[jb])
        err_i = np.linalg.norm(uv_i - prep[i].uv[ia], axis=1)
        uv_j, z_j = _project(Tj, fb, prep[i].points[ia])
        err_j = np.linalg.norm(uv_j - prep[j].uv[jb], axis=1)
        has_j = prep[j].depth[jb] > 0
        has_i = prep[i].depth[ia] > 0
        with np.errstate(invalid="ignore"):
            good = ((has_j & (z_i > 0) & (err_i < cfg.gate_px))
                    | (~has_j & has_i & (z_j > 0) & (err_j < cfg.gate_px)))
        for p, q in zip(ia[good].tolist(), jb[good].tolist(), strict=True):
            tracks.join((i, p), (j, q))
    return tracks


def bundle_adjust(frames: Sequence[BundleFrame], config: BundleConfig | None = None) -> BundleResult:
    """Refine the poses of ``frames`` (at least two) from their shared features.

    Returns the refined poses; a frame that shares no track keeps its pose moving only
    with its neighbours' gauge (it has no factor, so it keeps its initial value).

    Raises:
        GeometryError: fewer than two frames, or keyframes with different cameras.
    """
    cfg = config or BundleConfig()
    if len(frames) < 2:
        raise GeometryError(f"bundle adjustment needs at least two keyframes, got {len(frames)}")
    cam = frames[0].features.camera
    if any((f.features.camera.fx, f.features.camera.fy, f.features.camera.cx, f.features.camera.cy)
           != (cam.fx, cam.fy, cam.cx, cam.cy) for f in frames):
        raise GeometryError("bundle adjustment: keyframes with different cameras are not supported")
    t0 = time.perf_counter()
    prep = [_prepare(f, cfg) for f in frames]
    tracks = _match(frames, prep, cfg)

    values = gtsam.Values()
    for k, f in enumerate(frames):
        values.insert(k, gtsam.Pose3(np.asarray(f.T_map_camera, np.float64)))
    gauge: list[gtsam.NonlinearFactor] = [
        gtsam.NonlinearEqualityPose3(0, gtsam.Pose3(np.asarray(frames[0].T_map_camera, np.float64)))]
    weak = gtsam.noiseModel.Isotropic.Sigma(6, _WEAK_PRIOR)
    for k in range(1, len(frames)):  # keeps a frame without tracks solvable; negligible otherwise
        initial = gtsam.Pose3(np.asarray(frames[k].T_map_camera, np.float64))
        gauge.append(gtsam.PriorFactorPose3(k, initial, weak))
        if frames[k].up is not None and cfg.level_sigmas is not None:
            gauge.append(gtsam.PriorFactorPose3(k, initial, _level_noise(frames[k], cfg.level_sigmas)))
    k_stereo = gtsam.Cal3_S2Stereo(cam.fx, cam.fy, 0.0, cam.cx, cam.cy, cfg.bf / cam.fx)
    k_mono = gtsam.Cal3_S2(cam.fx, cam.fy, 0.0, cam.cx, cam.cy)
    huber3 = gtsam.noiseModel.mEstimator.Huber.Create(float(np.sqrt(_CHI2_3DOF)))
    huber2 = gtsam.noiseModel.mEstimator.Huber.Create(float(np.sqrt(_CHI2_2DOF)))
    observations: list[tuple[gtsam.NoiseModelFactor, float]] = []  # (factor, pixel sigma)
    n_landmarks = 0
    base = len(frames)  # landmark keys follow the pose keys
    for track in tracks.tracks():
        pts = np.array([prep[k].points[p] for k, p in track if prep[k].depth[p] > 0])
        if not len(pts):
            continue  # monocular only: no depth to place it
        lkey = base + n_landmarks
        values.insert(lkey, gtsam.Point3(np.median(pts, axis=0)))
        n_landmarks += 1
        for k, p in track:
            u, v = prep[k].uv[p]
            sigma = float(prep[k].sigma[p])
            d = float(prep[k].depth[p])
            factor: gtsam.NoiseModelFactor
            if d > 0:
                noise = gtsam.noiseModel.Robust.Create(huber3, gtsam.noiseModel.Isotropic.Sigma(3, sigma))
                stereo = gtsam.StereoPoint2(u, u - cfg.bf / d, v)
                factor = gtsam.GenericStereoFactor3D(stereo, noise, k, lkey, k_stereo)
            else:
                noise = gtsam.noiseModel.Robust.Create(huber2, gtsam.noiseModel.Isotropic.Sigma(2, sigma))
                factor = gtsam.GenericProjectionFactorCal3_S2(gtsam.Point2(u, v), noise, k, lkey, k_mono)
            observations.append((factor, sigma))

    def factor_graph(keep: Sequence[tuple[gtsam.NoiseModelFactor, float]]) -> gtsam.NonlinearFactorGraph:
        graph = gtsam.NonlinearFactorGraph()
        for g in gauge:
            graph.add(g)
        for obs, _ in keep:
            graph.add(obs)
        return graph

    graph = factor_graph(observations)
    error_before = graph.error(values)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.iterations)
    first = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    # drop observations beyond the chi-square bound, solve again (ORB-SLAM2's global BA)
    kept = []
    for obs, sigma in observations:
        r = np.asarray(obs.unwhitenedError(first))
        if float(np.sum((r / sigma) ** 2)) <= (_CHI2_3DOF if len(r) == 3 else _CHI2_2DOF):
            kept.append((obs, sigma))
    dropped = len(observations) - len(kept)
    final = factor_graph(kept) if dropped else graph
    result = gtsam.LevenbergMarquardtOptimizer(final, first, params).optimize() if dropped else first
    poses = {f.key: result.atPose3(k).matrix() for k, f in enumerate(frames)}
    return BundleResult(poses=poses, landmarks=n_landmarks, observations=len(kept), dropped=dropped,
                        error_before=float(error_before), error_after=float(final.error(result)),
                        ms=(time.perf_counter() - t0) * 1e3)

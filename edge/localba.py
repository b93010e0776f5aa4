"""Local bundle adjustment of the tracker's recent keyframes (ORB-SLAM2's LocalBundleAdjustment).

Three parts, each with one owner:

- :class:`CovisibilityGraph` (the tracking thread's): each recent keyframe's pose and its
  observations of map points (stable point ids, undistorted pixels, depth, pixel sigma).
  When a keyframe is made, :meth:`CovisibilityGraph.problem` copies a window out of it: the
  new keyframe and the ``window`` keyframes sharing most points with it are *local* (their
  poses are estimated), the other keyframes that see those points are *fixed* (the gauge).
- :func:`solve_local_ba`: a pure function of that copy (:class:`BaProblem`), solved with gtsam.
  A keypoint with depth ``z`` up to ``max_stereo_depth_m`` is a stereo measurement
  ``(u, u - bf / z, v)`` (``GenericStereoFactor3D``), one without depth a monocular
  ``GenericProjectionFactorCal3_S2``; sigma ``scale_factor ** octave`` pixels under a Huber
  kernel at the 95 % chi-square bound (``sqrt(7.815)``, 3 dof; ``sqrt(5.991)``, 2 dof);
  Levenberg-Marquardt, then observations beyond those bounds (or behind the camera) are
  dropped and the problem is solved again, as ORB-SLAM2 does.
- :class:`LocalBundleAdjuster`: runs the problems, either when submitted (``inline``: the
  offline ``wardmap track``, reproducible) or in a worker process (``process``: live
  robots). gtsam holds Python's global interpreter lock while it optimises, so a worker
  *thread* would stall the tracking thread; a process runs on another core. At most one
  problem waits while one is solved: a newer keyframe's problem replaces a waiting one
  (policy "latest wins", counted as ``superseded``), so the backlog is bounded.

The tracker applies a :class:`BaSolution` at a frame boundary on its own thread
(``Tracker._apply_local_ba``). Frames: ``T_world_cam`` (4, 4) maps camera coordinates (x
right, y down, z forward, metres) into the tracker's world frame.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import multiprocessing
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import ConfigError
from wardmap.shared.se3 import inverse, rotation_angle

log = logging.getLogger(__name__)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

CHI2_STEREO = 7.815  # 95 % chi-square bound, 3 dof (u, u_right, v)
CHI2_MONO = 5.991  # 2 dof (u, v)


@dataclass(frozen=True)
class LocalBaConfig:
    """Local bundle adjustment (``[tracker.local_ba]``).

    Attributes:
        enabled: adjust the recent keyframes and their points at every keyframe.
        worker: ``inline`` (solved when the keyframe is made, outside the frame's timing;
            reproducible, for ``wardmap track``) or ``process`` (a worker process; the
            edge daemon).
        window: keyframes optimised with the new one: those sharing most map points with
            it (covisibility), at least ``min_shared_points`` each.
        min_shared_points: shared points that make two keyframes covisible.
        max_fixed: keyframes held fixed (those outside the window seeing most of its points).
        iterations: Levenberg-Marquardt iterations before and after dropping outliers.
        graph_keyframes: keyframes the covisibility graph remembers.
        cull_after_keyframes: a map point seen by no keyframe but the one that made it is
            dropped this many keyframes later (ORB-SLAM2's MapPointCulling; 0 = never).
        stereo_bf: virtual stereo baseline x fx (pixels x metres) of the adjustment's depth
            residual ``u - stereo_bf / z``: a pixel of its error is ``z^2 / stereo_bf`` metres
            of depth, so ``1 / stereo_bf`` plays the part of a depth sensor's axial noise
            coefficient (std = b z^2). The tracker's ``rgbd_bf`` is ORB-SLAM2's 40.
        max_correction_m, max_correction_deg: a solution that moves a keyframe farther is
            refused (counted), as a failed optimisation.
    """

    enabled: bool = False
    worker: str = "process"
    window: int = 6
    min_shared_points: int = 15
    max_fixed: int = 10
    iterations: tuple[int, int] = (5, 10)
    graph_keyframes: int = 40
    cull_after_keyframes: int = 2
    stereo_bf: float = 40.0
    max_correction_m: float = 0.1
    max_correction_deg: float = 5.0

    def __post_init__(self) -> None:
        if self.worker not in ("inline", "process"):
            raise ConfigError(f"tracker.local_ba.worker must be 'inline' or 'process', got {self.worker!r}")
        if self.window < 1 or self.min_shared_points < 1 or self.max_fixed < 0:
            raise ConfigError("tracker.local_ba: need window >= 1, min_shared_points >= 1, max_fixed >= 0")
        if len(self.iterations) != 2 or min(self.iterations) < 1:
            raise ConfigError(f"tracker.local_ba.iterations must be two counts >= 1, got {self.iterations}")
        if self.graph_keyframes <= self.window:
            raise ConfigError("tracker.local_ba.graph_keyframes must exceed window")
        if self.cull_after_keyframes < 0:
            raise ConfigError("tracker.local_ba.cull_after_keyframes must be >= 0")
        if not (np.isfinite(self.stereo_bf) and self.stereo_bf >= 0):
            raise ConfigError(f"tracker.local_ba.stereo_bf must be >= 0, got {self.stereo_bf}")
        if not (self.max_correction_m > 0 and self.max_correction_deg > 0):
            raise ConfigError("tracker.local_ba: max_correction_m and max_correction_deg must be > 0")


@dataclass(frozen=True)
class Intrinsics:
    """What the solver needs of the camera: an undistorted pinhole (pixels) and the virtual
    stereo baseline ``bf`` (pixels x metres; ``u_right = u - bf / z``)."""

    fx: float
    fy: float
    cx: float
    cy: float
    bf: float
    max_stereo_depth_m: float


@dataclass(frozen=True)
class BaProblem:
    """A copy of the local window (K keyframes, P points, O observations).

    Attributes:
        epoch: the tracker's map epoch (a restarted map makes older problems stale).
        trigger: index of the keyframe whose arrival made this problem.
        kf_index: (K,) keyframe indexes.
        T_world_cam: (K, 4, 4) initial poses.
        fixed: (K,) True for poses held fixed.
        pid: (P,) map point ids.
        points_world: (P, 3) initial positions, metres.
        obs_kf: (O,) row of ``kf_index`` of each observation.
        obs_point: (O,) row of ``pid``.
        uv: (O, 2) undistorted pixel coordinates.
        depth_m: (O,) measured depth along z (0: none, or beyond the stereo range).
        sigma_px: (O,) pixel standard deviation (``scale_factor ** octave``).
    """

    epoch: int
    trigger: int
    kf_index: I64
    T_world_cam: F64
    fixed: NDArray[np.bool_]
    pid: I64
    points_world: F64
    obs_kf: I64
    obs_point: I64
    uv: F64
    depth_m: F64
    sigma_px: F64


@dataclass(frozen=True)
class BaSolution:
    """The adjusted window (rows as in ``problem``).

    Attributes:
        problem: what was solved.
        T_world_cam: (K, 4, 4) adjusted poses (fixed ones unchanged).
        points_world: (P, 3) adjusted positions.
        inlier: (O,) observations kept by the second pass.
        rms_before_px, rms_after_px: RMS whitened reprojection error of the kept observations
            (units of sigma), at the start and the end.
        accepted: False when the result must not be used (``reason`` says why).
        cpu_ms: CPU time of the solve (in the process that solved it).
    """

    problem: BaProblem
    T_world_cam: F64
    points_world: F64
    inlier: NDArray[np.bool_]
    rms_before_px: float
    rms_after_px: float
    accepted: bool
    reason: str
    cpu_ms: float


def reprojection_chi2(problem: BaProblem, intr: Intrinsics, T_world_cam: F64, points_world: F64) -> F64:
    """Squared whitened reprojection error (O,) of each observation.

    ``e = (u - fx x/z - cx, v - fy y/z - cy[, u_r - (fx x - bf) / z]) / sigma`` with ``(x, y, z)``
    the point in the observing camera; the third row only for a stereo observation (``0 < depth
    <= max_stereo_depth_m``). A point behind the camera (z <= 1 cm) gets ``inf``.
    """
    T_cw = inverse(T_world_cam)[problem.obs_kf]
    P = points_world[problem.obs_point]
    Pc = np.einsum("nij,nj->ni", T_cw[:, :3, :3], P) + T_cw[:, :3, 3]
    z = Pc[:, 2]
    front = z > 0.01
    zs = np.where(front, z, 1.0)
    u = intr.fx * Pc[:, 0] / zs + intr.cx
    v = intr.fy * Pc[:, 1] / zs + intr.cy
    e2 = (problem.uv[:, 0] - u) ** 2 + (problem.uv[:, 1] - v) ** 2
    stereo = _is_stereo(problem.depth_m, intr)
    ur_meas = problem.uv[:, 0] - intr.bf / np.where(stereo, problem.depth_m, 1.0)
    e2 = e2 + np.where(stereo, (ur_meas - (u - intr.bf / zs)) ** 2, 0.0)
    return np.where(front, e2 / problem.sigma_px**2, np.inf)


def _is_stereo(depth_m: F64, intr: Intrinsics) -> NDArray[np.bool_]:
    return (depth_m > 0) & (depth_m <= intr.max_stereo_depth_m) & (intr.bf > 0)


def solve_local_ba(problem: BaProblem, intr: Intrinsics, cfg: LocalBaConfig) -> BaSolution:
    """Adjust the local keyframes and points of ``problem`` (see the module docstring).

    Minimises ``sum_o rho(e_o^T e_o)`` over the non-fixed poses and all points, ``e_o`` the
    whitened residual of :func:`reprojection_chi2` and ``rho`` Huber's loss (ORB-SLAM2,
    Optimizer::LocalBundleAdjustment). Pure: new arrays out, nothing of ``problem`` changed.
    """
    import gtsam  # heavy; imported where it is used (a worker process imports it once)

    c0 = time.process_time()
    K, P = len(problem.kf_index), len(problem.pid)
    X = [gtsam.symbol("x", k) for k in range(K)]
    L = [gtsam.symbol("l", p) for p in range(P)]
    values = gtsam.Values()
    for k in range(K):
        values.insert(X[k], gtsam.Pose3(problem.T_world_cam[k]))
    for p in range(P):
        values.insert(L[p], problem.points_world[p])
    k_stereo = gtsam.Cal3_S2Stereo(intr.fx, intr.fy, 0.0, intr.cx, intr.cy, intr.bf / intr.fx)
    k_mono = gtsam.Cal3_S2(intr.fx, intr.fy, 0.0, intr.cx, intr.cy)
    huber3 = gtsam.noiseModel.mEstimator.Huber.Create(float(np.sqrt(CHI2_STEREO)))
    huber2 = gtsam.noiseModel.mEstimator.Huber.Create(float(np.sqrt(CHI2_MONO)))
    stereo = _is_stereo(problem.depth_m, intr)
    factors: list[gtsam.NoiseModelFactor] = []
    for o in range(len(problem.obs_kf)):
        k, p = int(problem.obs_kf[o]), int(problem.obs_point[o])
        u, v = float(problem.uv[o, 0]), float(problem.uv[o, 1])
        s = float(problem.sigma_px[o])
        if stereo[o]:
            noise = gtsam.noiseModel.Robust.Create(huber3, gtsam.noiseModel.Isotropic.Sigma(3, s))
            meas = gtsam.StereoPoint2(u, u - intr.bf / float(problem.depth_m[o]), v)
            factors.append(gtsam.GenericStereoFactor3D(meas, noise, X[k], L[p], k_stereo, False, False))
        else:
            noise = gtsam.noiseModel.Robust.Create(huber2, gtsam.noiseModel.Isotropic.Sigma(2, s))
            factors.append(gtsam.GenericProjectionFactorCal3_S2(
                gtsam.Point2(u, v), noise, X[k], L[p], k_mono, False, False))

    def graph_of(keep: NDArray[np.bool_]) -> gtsam.NonlinearFactorGraph:
        g = gtsam.NonlinearFactorGraph()
        for k in np.flatnonzero(problem.fixed):
            g.add(gtsam.NonlinearEqualityPose3(X[k], gtsam.Pose3(problem.T_world_cam[k])))
        for o in np.flatnonzero(keep):
            g.add(factors[o])
        return g

    def read(vals: gtsam.Values) -> tuple[F64, F64]:
        T = np.stack([vals.atPose3(X[k]).matrix() for k in range(K)])
        pts = np.stack([vals.atPoint3(L[p]) for p in range(P)]) if P else np.zeros((0, 3))
        return T, pts

    thresh = np.where(stereo, CHI2_STEREO, CHI2_MONO)
    chi2_0 = reprojection_chi2(problem, intr, problem.T_world_cam, problem.points_world)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.iterations[0])
    everything = np.ones(len(factors), bool)
    first = gtsam.LevenbergMarquardtOptimizer(graph_of(everything), values, params).optimize()
    T1, pts1 = read(first)
    inlier = reprojection_chi2(problem, intr, T1, pts1) <= thresh
    params.setMaxIterations(cfg.iterations[1])
    final = gtsam.LevenbergMarquardtOptimizer(graph_of(inlier), first, params).optimize()
    T2, pts2 = read(final)
    chi2_2 = reprojection_chi2(problem, intr, T2, pts2)
    inlier &= chi2_2 <= thresh
    rms0 = float(np.sqrt(np.mean(chi2_0[inlier]))) if inlier.any() else 0.0
    rms2 = float(np.sqrt(np.mean(chi2_2[inlier]))) if inlier.any() else 0.0
    accepted, reason = True, ""
    for k in range(K):
        rel = inverse(problem.T_world_cam[k]) @ T2[k]
        if (np.linalg.norm(rel[:3, 3]) > cfg.max_correction_m
                or np.degrees(rotation_angle(rel[:3, :3])) > cfg.max_correction_deg):
            accepted, reason = False, f"keyframe {problem.kf_index[k]} would move too far"
            break
    if accepted and not inlier.any():
        accepted, reason = False, "no inlier observation"
    return BaSolution(problem, T2, pts2, inlier, rms0, rms2, accepted, reason,
                      (time.process_time() - c0) * 1e3)


@dataclass
class _KeyframeObs:
    T_world_cam: F64
    pid: I64
    uv: F64
    depth_m: F64
    sigma_px: F64


class CovisibilityGraph:
    """Recent keyframes and their map-point observations. One owner: the tracking thread."""

    def __init__(self, cam: PinholeCamera, cfg: LocalBaConfig) -> None:
        self.cam = cam
        self.cfg = cfg
        self.kf: dict[int, _KeyframeObs] = {}

    def reset(self) -> None:
        self.kf.clear()

    def add(self, kf_index: int, T_world_cam: F64, pid: I64, uv: NDArray[np.float32],
            depth_m: F64, sigma_px: F64) -> None:
        """Record keyframe ``kf_index``: its pose (4, 4), its point ids (N,), their raw pixels
        (N, 2; undistorted here), depth (N,) metres (0 = none) and pixel sigma (N,)."""
        xy = self.cam.unproject(np.asarray(uv, np.float64), np.ones(len(pid)))
        uv_ideal = np.column_stack([self.cam.fx * xy[:, 0] + self.cam.cx,
                                    self.cam.fy * xy[:, 1] + self.cam.cy])
        self.kf[kf_index] = _KeyframeObs(T_world_cam.copy(), np.asarray(pid, np.int64), uv_ideal,
                                         np.asarray(depth_m, np.float64), np.asarray(sigma_px, np.float64))
        for old in sorted(self.kf)[: max(0, len(self.kf) - self.cfg.graph_keyframes)]:
            del self.kf[old]

    def problem(self, trigger: int, epoch: int, map_pid: I64, map_pos: F64) -> BaProblem | None:
        """The window around keyframe ``trigger``, with the current map (ids ``map_pid`` (M,),
        sorted, positions ``map_pos`` (M, 3)); None when there is nothing to adjust."""
        new = self.kf.get(trigger)
        if new is None:
            return None
        shared = {k: int(np.isin(o.pid, new.pid, assume_unique=True).sum())
                  for k, o in self.kf.items() if k != trigger}
        covis = sorted((k for k, n in shared.items() if n >= self.cfg.min_shared_points),
                       key=lambda k: (-shared[k], -k))[: self.cfg.window]
        local = sorted([trigger, *covis])
        pts = np.unique(np.concatenate([self.kf[k].pid for k in local]))
        pts = pts[np.isin(pts, map_pid, assume_unique=True)]
        seeing = {k: int(np.isin(o.pid, pts, assume_unique=True).sum()) for k, o in self.kf.items()
                  if k not in local}
        fixed = sorted((k for k, n in seeing.items() if n > 0), key=lambda k: (-seeing[k], -k))
        fixed = sorted(fixed[: self.cfg.max_fixed])
        kfs = fixed + local
        is_fixed = np.array([k in fixed for k in kfs])
        if not is_fixed.any():
            is_fixed[int(np.argmin(kfs))] = True  # the gauge: the oldest local keyframe
        obs_kf, obs_pt, uv, z, s = [], [], [], [], []
        for row, k in enumerate(kfs):
            o = self.kf[k]
            hit = np.isin(o.pid, pts, assume_unique=True)
            obs_kf.append(np.full(int(hit.sum()), row, np.int64))
            obs_pt.append(np.searchsorted(pts, o.pid[hit]))
            uv.append(o.uv[hit])
            z.append(o.depth_m[hit])
            s.append(o.sigma_px[hit])
        obs_point = np.concatenate(obs_pt)
        # Points seen once in the window constrain no pose: left out.
        counts = np.bincount(obs_point, minlength=len(pts))
        keep_pt = counts >= 2
        if keep_pt.sum() < 10 or (len(local) < 2 and is_fixed.all()):
            return None
        remap = np.cumsum(keep_pt) - 1
        keep_obs = keep_pt[obs_point]
        pos = map_pos[np.searchsorted(map_pid, pts[keep_pt])]
        return BaProblem(
            epoch=epoch, trigger=trigger, kf_index=np.asarray(kfs, np.int64),
            T_world_cam=np.stack([self.kf[k].T_world_cam for k in kfs]), fixed=is_fixed,
            pid=pts[keep_pt], points_world=pos.copy(),
            obs_kf=np.concatenate(obs_kf)[keep_obs], obs_point=remap[obs_point[keep_obs]],
            uv=np.concatenate(uv)[keep_obs], depth_m=np.concatenate(z)[keep_obs],
            sigma_px=np.concatenate(s)[keep_obs],
        )

    def apply(self, sol: BaSolution) -> None:
        """Take the adjusted poses and drop the outlier observations of ``sol``."""
        pr = sol.problem
        for row, k in enumerate(pr.kf_index.tolist()):
            o = self.kf.get(k)
            if o is None:
                continue
            if not pr.fixed[row]:
                o.T_world_cam = sol.T_world_cam[row].copy()
            bad = pr.pid[pr.obs_point[(pr.obs_kf == row) & ~sol.inlier]]
            if len(bad):
                keep = ~np.isin(o.pid, bad)
                o.pid, o.uv = o.pid[keep], o.uv[keep]
                o.depth_m, o.sigma_px = o.depth_m[keep], o.sigma_px[keep]

    def move_after(self, kf_index: int, delta: F64) -> None:
        """Keyframes made after ``kf_index`` (not in its solution) moved by ``delta`` (4, 4, world frame)."""
        for k, o in self.kf.items():
            if k > kf_index:
                o.T_world_cam = delta @ o.T_world_cam


@dataclass
class BaStats:
    """Counters of a :class:`LocalBundleAdjuster` (reported in the ``track`` summary)."""

    submitted: int = 0
    solved: int = 0
    refused: int = 0
    superseded: int = 0
    unfinished: int = 0  # solving or waiting when the adjuster was closed
    max_backlog: int = 0
    cpu_ms: list[float] = field(default_factory=list)
    rms_before: list[float] = field(default_factory=list)
    rms_after: list[float] = field(default_factory=list)

    def summary(self) -> dict[str, float | int]:
        def med(v: list[float]) -> float:
            return round(float(np.median(v)), 3) if v else 0.0
        return {
            "submitted": self.submitted, "solved": self.solved, "refused": self.refused,
            "superseded": self.superseded, "unfinished": self.unfinished,
            "max_backlog": self.max_backlog,
            "cpu_ms_median": med(self.cpu_ms),
            "cpu_ms_p95": round(float(np.percentile(self.cpu_ms, 95)), 3) if self.cpu_ms else 0.0,
            "rms_before_median": med(self.rms_before), "rms_after_median": med(self.rms_after),
        }


class LocalBundleAdjuster:
    """Solves :class:`BaProblem` s inline or in one worker process (``cfg.worker``).

    Called from one thread only (the tracker's). The worker process is started at the first
    problem and stopped by :meth:`close`. Backlog: the problem being solved plus at most one
    waiting; a newer problem replaces the waiting one (``superseded``).
    """

    def __init__(self, intr: Intrinsics, cfg: LocalBaConfig) -> None:
        self.intr = intr
        self.cfg = cfg
        self.stats = BaStats()
        self._ready: list[BaSolution] = []
        self._pool: cf.ProcessPoolExecutor | None = None
        self._running: cf.Future[BaSolution] | None = None
        self._waiting: BaProblem | None = None

    def submit(self, problem: BaProblem) -> None:
        self.stats.submitted += 1
        if self.cfg.worker == "inline":
            self._done(solve_local_ba(problem, self.intr, self.cfg))
            return
        if self._waiting is not None:
            self.stats.superseded += 1
        self._waiting = problem
        self._pump()

    def poll(self) -> list[BaSolution]:
        """Solutions finished since the last call, oldest first."""
        self._pump()
        out, self._ready = self._ready, []
        return out

    def backlog(self) -> int:
        return int(self._running is not None) + int(self._waiting is not None)

    def wait(self, timeout_s: float | None = None) -> None:
        """Block until nothing is being solved or waits (tests, end of a recording)."""
        t_end = None if timeout_s is None else time.monotonic() + timeout_s
        while self._running is not None or self._waiting is not None:
            if self._running is not None:
                left = None if t_end is None else max(0.0, t_end - time.monotonic())
                cf.wait([self._running], timeout=left)
            self._pump()
            if t_end is not None and time.monotonic() >= t_end:
                return

    def close(self) -> None:
        """Stop the worker; what was solving or waiting is counted ``unfinished``."""
        self.stats.unfinished += self.backlog()
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._running = self._waiting = None

    def _pump(self) -> None:
        if self._running is not None and self._running.done():
            try:
                self._done(self._running.result())
            except Exception as exc:  # a failed solve must not stop tracking
                log.warning("local bundle adjustment failed: %s", exc)
                self.stats.refused += 1
            self._running = None
        if self._running is None and self._waiting is not None:
            if self._pool is None:
                ctx = multiprocessing.get_context("spawn")  # no fork of a threaded parent
                self._pool = cf.ProcessPoolExecutor(max_workers=1, mp_context=ctx)
            self._running = self._pool.submit(solve_local_ba, self._waiting, self.intr, self.cfg)
            self._waiting = None
        self.stats.max_backlog = max(self.stats.max_backlog, self.backlog())

    def _done(self, sol: BaSolution) -> None:
        self.stats.cpu_ms.append(sol.cpu_ms)
        if sol.accepted:
            self.stats.solved += 1
            self.stats.rms_before.append(sol.rms_before_px)
            self.stats.rms_after.append(sol.rms_after_px)
        else:
            self.stats.refused += 1
        self._ready.append(sol)

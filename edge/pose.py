"""Camera pose from 3D-2D correspondences: EPnP in RANSAC, then motion-only bundle adjustment.

Frames and units (docs/ARCHITECTURE.md): ``T_cam_world`` (4, 4) maps world points to the
camera frame (``p_cam = T_cam_world @ p_world``; camera x right, y down, z forward),
metres. Observations ``uv`` are pixel coordinates in the image as captured (distorted).

Both steps work on undistorted, normalised coordinates: every observation is undistorted
once with the camera's model (``PinholeCamera.undistort_normalized``), so distortion is
handled exactly and the projection inside the loops is the plain pinhole ``(X/Z, Y/Z)``.
Reprojection errors are measured in that normalised plane scaled by the focal lengths,
i.e. in pixels of the ideal (undistorted) camera.

- :func:`solve_pnp_ransac`: EPnP (paper 003 Sec. IV-C, Eq. 6-9) as the minimal solver of
  OpenCV's RANSAC, seeded so a run is reproducible.
- :func:`refine_pose_huber`: Gauss-Newton with Levenberg damping on se(3) with Huber
  weights, in rounds that re-classify outliers by a chi-square test, as ORB-SLAM2's
  ``Optimizer::PoseOptimization``.

Pure functions: arrays in, new arrays out; bad shapes raise :class:`GeometryError`,
degenerate data gives ``ok=False`` (PnP) or the initial pose back (refinement).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import GeometryError
from wardmap.shared.se3 import check_transform, make_transform, se3_exp

F64 = NDArray[np.float64]
Mask = NDArray[np.bool_]

CHI2_2DOF_95 = 5.991
"""95 % quantile of chi-square with 2 degrees of freedom: inlier gate on a squared
reprojection error in (whitened) pixels, as in ORB-SLAM2."""

CHI2_3DOF_95 = 7.815
"""The same gate for an RGB-D observation with its virtual right coordinate (3 dof)."""

HUBER_PX_DEFAULT = math.sqrt(CHI2_2DOF_95)
"""Huber threshold (about 2.45 px, ORB-SLAM2's choice): the kernel turns linear exactly
where the chi-square gate starts, so every accepted inlier keeps its full quadratic
weight and only would-be outliers are down-weighted."""

MIN_PNP_POINTS = 6
_MIN_DEPTH = 1e-6


class PnpResult(NamedTuple):
    """Outcome of :func:`solve_pnp_ransac`.

    Attributes:
        T_cam_world: (4, 4) pose; when ``ok`` is False it is the guess (if one was
            given) or the identity, and must not be used.
        inliers: (N,) bool, correspondences within ``reprojection_px`` of the pose
            (all False when not ok).
        ok: whether a pose was found.
        reason: ``"ok"`` or why not, for logs.
    """

    T_cam_world: F64
    inliers: Mask
    ok: bool
    reason: str


class RefineResult(NamedTuple):
    """Outcome of :func:`refine_pose_huber` (unpacks as ``T, inliers, cost``).

    Attributes:
        T_cam_world: (4, 4) refined pose.
        inliers: (N,) bool, whitened squared reprojection error <= the chi-square gate
            at the refined pose (points behind the camera or non-finite are outliers).
        cost: robust (Huber) cost at the refined pose, summed over all finite
            correspondences in front of the camera, in whitened pixels squared;
            ``inf`` when there were too few points to refine.
    """

    T_cam_world: F64
    inliers: Mask
    cost: float


# --------------------------------------------------------------------------- helpers


def _check_correspondences(points_world: ArrayLike, uv: ArrayLike, fn: str) -> tuple[F64, F64]:
    P = np.asarray(points_world, dtype=np.float64)
    p = np.asarray(uv, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise GeometryError(f"{fn}: expected points_world (N, 3), got {P.shape}")
    if p.ndim != 2 or p.shape[1] != 2:
        raise GeometryError(f"{fn}: expected uv (N, 2), got {p.shape}")
    if P.shape[0] != p.shape[0]:
        raise GeometryError(f"{fn}: {P.shape[0]} points but {p.shape[0]} observations")
    return P, p


def _normalized(camera: PinholeCamera, uv: F64) -> F64:
    """Undistorted normalised coordinates (N, 2) of distorted pixels (N, 2)."""
    xy_d = np.column_stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy])
    if not camera.has_distortion:
        return xy_d
    with np.errstate(all="ignore"):
        return camera.undistort_normalized(xy_d)


def _degenerate(P: F64, xy: F64) -> str:
    """Why the correspondences cannot fix a pose, or "" if they may."""
    s = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    if s[0] < 1e-9 or s[1] < 1e-6 * s[0]:
        return "degenerate: world points are coincident or collinear"
    if float(np.ptp(xy[:, 0])) + float(np.ptp(xy[:, 1])) < 1e-9:
        return "degenerate: all observations at one pixel"
    return ""


def _from_rvec_tvec(rvec: ArrayLike, tvec: ArrayLike) -> F64:
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    return make_transform(R, np.asarray(tvec, dtype=np.float64).reshape(3))


# --------------------------------------------------------------------------- EPnP + RANSAC


def solve_pnp_ransac(
    points_world: ArrayLike,
    uv: ArrayLike,
    camera: PinholeCamera,
    *,
    reprojection_px: float = 3.0,
    iterations: int = 100,
    confidence: float = 0.99,
    T_cam_world_guess: ArrayLike | None = None,
    rng_seed: int = 0,
    min_inliers: int = MIN_PNP_POINTS,
) -> PnpResult:
    """Camera pose from 3D-2D correspondences by EPnP inside RANSAC (paper 003 Eq. 6-9).

    The observations are undistorted once (exact for the camera's model) and handed to
    ``cv2.solvePnPRansac(flags=SOLVEPNP_EPNP)`` as pixels of an ideal camera with zero
    distortion; OpenCV re-fits EPnP on the best consensus set. Inliers are then the
    correspondences in front of the camera within ``reprojection_px`` (ideal-camera
    pixels) of the final pose. cv2's global RNG is seeded with ``rng_seed`` first, so
    the same input gives the same output.

    A ``T_cam_world_guess`` (e.g. from a motion model) competes as one more hypothesis:
    if it has more inliers than the RANSAC pose it is returned, which also rescues a
    failed RANSAC.

    Args:
        points_world: (N, 3) points in the world frame, metres.
        uv: (N, 2) observed pixels (distorted image). Rows with NaN/inf in either array
            are ignored (never inliers).
        camera: intrinsics and distortion of the image.
        reprojection_px: RANSAC inlier threshold in pixels.
        iterations: RANSAC iterations.
        confidence: RANSAC confidence for its early stop.
        T_cam_world_guess: optional (4, 4) prior pose.
        rng_seed: seed of cv2's RNG for the RANSAC sampling.
        min_inliers: fewer inliers than this is a failure.

    Returns:
        :class:`PnpResult`; degenerate input gives ``ok=False`` with a reason, never an
        exception.

    Raises:
        GeometryError: arrays of the wrong shape, or a guess that is not a rigid transform.
    """
    P_all, uv_all = _check_correspondences(points_world, uv, "solve_pnp_ransac")
    n = P_all.shape[0]
    guess = None if T_cam_world_guess is None else check_transform(T_cam_world_guess, "T_cam_world_guess")
    fallback = guess.copy() if guess is not None else np.eye(4)
    none = np.zeros(n, np.bool_)
    need = max(MIN_PNP_POINTS, min_inliers)

    xy_all = np.full((n, 2), np.nan)
    finite = np.all(np.isfinite(P_all), axis=1) & np.all(np.isfinite(uv_all), axis=1)
    xy_all[finite] = _normalized(camera, uv_all[finite])
    finite &= np.all(np.isfinite(xy_all), axis=1)
    idx = np.nonzero(finite)[0]
    if idx.size < need:
        return PnpResult(fallback, none, False, f"too few points: {idx.size} usable, need {need}")
    P, xy = P_all[idx], xy_all[idx]
    why = _degenerate(P, xy)
    if why:
        return PnpResult(fallback, none, False, why)

    K = camera.K
    uv_ideal = np.ascontiguousarray(xy * (camera.fx, camera.fy) + (camera.cx, camera.cy))
    T_ransac: F64 | None = None
    failure = ""
    cv2.setRNGSeed(int(rng_seed))
    try:
        found, rvec, tvec, _ = cv2.solvePnPRansac(
            np.ascontiguousarray(P),
            uv_ideal,
            K,
            np.zeros(5),
            useExtrinsicGuess=False,
            iterationsCount=int(iterations),
            reprojectionError=float(reprojection_px),
            confidence=float(confidence),
            flags=cv2.SOLVEPNP_EPNP,
        )
        if found and np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec)):
            T_ransac = _from_rvec_tvec(rvec, tvec)
        else:
            failure = "ransac failed: no consensus"
    except cv2.error as exc:  # OpenCV rejects some degenerate sets deep inside EPnP
        failure = f"ransac failed: {str(exc).strip().splitlines()[-1]}"

    thr2 = float(reprojection_px) ** 2
    best: tuple[F64, Mask] | None = None
    for T in (T_ransac, guess):
        if T is None:
            continue
        inl = _pixel_error2(np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]), P, xy,
                            np.ones(len(P)), np.zeros(len(P)), 0.0, camera.fx, camera.fy) <= thr2
        if best is None or int(inl.sum()) > int(best[1].sum()):
            best = (T, inl)
    if best is None:
        return PnpResult(fallback, none, False, failure or "ransac failed")
    T_best, inl_best = best
    inliers = none.copy()
    inliers[idx] = inl_best
    n_in = int(inl_best.sum())
    if n_in < need:
        return PnpResult(fallback, none, False, f"too few inliers: {n_in} of {idx.size}, need {need}")
    reason = "ok" if T_best is T_ransac else "ok: guess pose kept (more inliers than RANSAC)"
    return PnpResult(T_best, inliers, True, reason)


# --------------------------------------------------------------------------- motion-only BA


def _huber_cost(e2: F64, delta: float) -> float:
    """Sum of Huber rho(e^2): e^2 inside ``delta``, 2 delta e - delta^2 outside."""
    if math.isinf(delta):
        return float(e2.sum())
    e = np.sqrt(e2)
    return float(np.where(e <= delta, e2, 2.0 * delta * e - delta * delta).sum())


@njit(cache=True, nogil=True)
def _robust_system(
    R: F64, t: F64, P: F64, xy: F64, info: F64, izm: F64, bf: float, fx: float, fy: float, delta: float,
    build: bool,
) -> tuple[F64, F64, float, int]:
    """Gauss-Newton system (H (6, 6), g (6,)) and Huber cost of the pose (R, t).

    Residual (ideal pixels) r = (fx (X/Z - x), fy (Y/Z - y)) with (X, Y, Z) = R p + t;
    Jacobian rows for the left perturbation xi = (rho, omega), x = X/Z, y = Y/Z:
    d r_u / d xi = fx [1/Z, 0, -x/Z, -x y, 1 + x^2, -y],
    d r_v / d xi = fy [0, 1/Z, -y/Z, -(1 + y^2), x y, x].
    Where the observation has a measured inverse depth ``izm > 0`` (RGB-D), a third
    residual on ORB-SLAM2's virtual right coordinate u_r = u - bf / Z:
    r_r = r_u - bf (1/Z - izm), d r_r / d xi = d r_u / d xi + bf / Z^2 [0, 0, 1, Y, -X, 0].
    IRLS weight: information (1/sigma^2) times Huber's min(1, delta / e). Points behind
    the camera are left out and counted (last return value).
    """
    H = np.zeros((6, 6))
    g = np.zeros(6)
    ju = np.zeros(6)
    jv = np.zeros(6)
    jr = np.zeros(6)
    cost = 0.0
    behind = 0
    for i in range(P.shape[0]):
        X = R[0, 0] * P[i, 0] + R[0, 1] * P[i, 1] + R[0, 2] * P[i, 2] + t[0]
        Y = R[1, 0] * P[i, 0] + R[1, 1] * P[i, 1] + R[1, 2] * P[i, 2] + t[1]
        Z = R[2, 0] * P[i, 0] + R[2, 1] * P[i, 1] + R[2, 2] * P[i, 2] + t[2]
        if Z <= 1e-6:
            behind += 1
            continue
        iz = 1.0 / Z
        x = X * iz
        y = Y * iz
        ru = fx * (x - xy[i, 0])
        rv = fy * (y - xy[i, 1])
        stereo = bf > 0.0 and izm[i] > 0.0
        rr = ru - bf * (iz - izm[i]) if stereo else 0.0
        e2 = info[i] * (ru * ru + rv * rv + rr * rr)
        e = math.sqrt(e2)
        if e <= delta:
            cost += e2
            w = info[i]
        else:
            cost += 2.0 * delta * e - delta * delta
            w = info[i] * delta / e
        if not build:
            continue
        ju[0] = fx * iz
        ju[1] = 0.0
        ju[2] = -fx * x * iz
        ju[3] = -fx * x * y
        ju[4] = fx * (1.0 + x * x)
        ju[5] = -fx * y
        jv[0] = 0.0
        jv[1] = fy * iz
        jv[2] = -fy * y * iz
        jv[3] = -fy * (1.0 + y * y)
        jv[4] = fy * x * y
        jv[5] = fy * x
        if stereo:
            k = bf * iz * iz
            for a in range(6):
                jr[a] = ju[a]
            jr[2] += k
            jr[3] += k * Y
            jr[4] -= k * X
        else:
            for a in range(6):
                jr[a] = 0.0
        for a in range(6):
            g[a] += w * (ju[a] * ru + jv[a] * rv + jr[a] * rr)
            for b in range(a, 6):
                H[a, b] += w * (ju[a] * ju[b] + jv[a] * jv[b] + jr[a] * jr[b])
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g, cost, behind


@njit(cache=True, nogil=True)
def _exp_left(xi: NDArray[np.floating], R: F64, t: F64) -> tuple[F64, F64]:
    """(R', t') of exp(xi) T for xi = (rho, omega) (same convention as ``se3.se3_exp``)."""
    w0, w1, w2 = xi[3], xi[4], xi[5]
    th = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    K = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    K2 = K @ K
    if th < 1e-9:
        dR = np.eye(3) + K + 0.5 * K2
        V = np.eye(3) + 0.5 * K
    else:
        dR = np.eye(3) + math.sin(th) / th * K + (1.0 - math.cos(th)) / (th * th) * K2
        V = np.eye(3) + (1.0 - math.cos(th)) / (th * th) * K + (th - math.sin(th)) / (th * th * th) * K2
    return dR @ R, dR @ t + V @ xi[:3]


@njit(cache=True, nogil=True)
def _levenberg(
    R: F64, t: F64, P: F64, xy: F64, info: F64, izm: F64, bf: float, fx: float, fy: float, delta: float,
    iterations: int,
) -> tuple[F64, F64]:
    """Levenberg-Marquardt on se(3) with left perturbation ``T <- exp(xi) T`` and Huber IRLS.

    A step is accepted only if the robust cost drops and no point moves behind the
    camera; otherwise the damping grows (up to 8 tries). Stops on convergence.
    """
    lam = 1e-4
    for _ in range(iterations):
        H, g, cost, behind = _robust_system(R, t, P, xy, info, izm, bf, fx, fy, delta, True)
        improved = False
        converged = False
        for _try in range(8):
            A = H.copy()
            for a in range(6):
                A[a, a] += lam * (H[a, a] + 1e-9)
            step = -np.linalg.solve(A, g)
            if not np.all(np.isfinite(step)):
                lam *= 10.0
                continue
            R_new, t_new = _exp_left(step, R, t)
            _, _, cost_new, behind_new = _robust_system(
                R_new, t_new, P, xy, info, izm, bf, fx, fy, delta, False
            )
            if cost_new <= cost and behind_new <= behind:
                improved = True
                converged = cost - cost_new <= 1e-12 * max(cost, 1.0) or np.max(np.abs(step)) < 1e-10
                R, t = R_new, t_new
                lam = max(lam * 0.1, 1e-9)
                break
            lam *= 10.0
        if not improved or converged:
            break
    return R, t


@njit(cache=True, nogil=True)
def _pixel_error2(R: F64, t: F64, P: F64, xy: F64, info: F64, izm: F64, bf: float, fx: float,
                  fy: float) -> F64:
    """Whitened squared reprojection error (N,) in ideal-camera pixels of ``p`` seen at ``xy``
    (normalised) from ``(R, t)``: ``info (du^2 + dv^2)``, plus ORB-SLAM2's virtual right
    coordinate's ``(du - bf (1/Z - izm))^2`` where ``izm > 0`` and ``bf > 0``; inf behind the
    camera."""
    e2 = np.empty(P.shape[0])
    for i in range(P.shape[0]):
        X = R[0, 0] * P[i, 0] + R[0, 1] * P[i, 1] + R[0, 2] * P[i, 2] + t[0]
        Y = R[1, 0] * P[i, 0] + R[1, 1] * P[i, 1] + R[1, 2] * P[i, 2] + t[1]
        Z = R[2, 0] * P[i, 0] + R[2, 1] * P[i, 1] + R[2, 2] * P[i, 2] + t[2]
        if not Z > _MIN_DEPTH:
            e2[i] = np.inf
            continue
        du = fx * (X / Z - xy[i, 0])
        dv = fy * (Y / Z - xy[i, 1])
        v = du * du + dv * dv
        if bf > 0.0 and izm[i] > 0.0:
            dr = du - bf * (1.0 / Z - izm[i])
            v += dr * dr
        e2[i] = info[i] * v
    return e2


@njit(cache=True, nogil=True)
def _refine_rounds(
    R: F64, t: F64, P: F64, xy: F64, info: F64, izm: F64, gate: F64, bf: float, fx: float, fy: float,
    huber: float, iterations: int, rounds: int,
) -> tuple[F64, F64, F64]:
    """:func:`refine_pose_huber`'s rounds: Levenberg-Marquardt (:func:`_levenberg`) on the
    current inliers, the rotation projected back onto SO(3) (SVD), every correspondence
    re-classified by its whitened squared error against ``gate`` (N,). The last of several
    rounds drops the Huber kernel. Returns (R, t) and the final whitened errors (N,)."""
    active = np.ones(P.shape[0], np.bool_)
    e2 = np.empty(0)  # the errors at the current pose, once a round has run
    for rnd in range(rounds):
        idx = np.nonzero(active)[0]
        if idx.shape[0] < 3:
            break
        delta = huber if (rnd < rounds - 1 or rounds == 1) else np.inf
        R, t = _levenberg(R, t, P[idx], xy[idx], info[idx], izm[idx], bf, fx, fy, delta, iterations)
        U, _, Vt = np.linalg.svd(R)
        R_ortho = U @ Vt
        if np.linalg.det(R_ortho) < 0:
            U[:, 2] = -U[:, 2]
            R_ortho = U @ Vt
        R = R_ortho
        e2 = _pixel_error2(R, t, P, xy, info, izm, bf, fx, fy)
        active = e2 <= gate  # inf is never an inlier
    if e2.shape[0] != P.shape[0]:  # no round ran: the start pose's errors
        e2 = _pixel_error2(R, t, P, xy, info, izm, bf, fx, fy)
    return R, t, e2


def refine_pose_huber(
    points_world: ArrayLike,
    uv: ArrayLike,
    camera: PinholeCamera,
    T_cam_world_init: ArrayLike,
    *,
    huber_px: float = HUBER_PX_DEFAULT,
    iterations: int = 10,
    sigma_px: ArrayLike | None = None,
    rounds: int = 4,
    chi2_threshold: float = CHI2_2DOF_95,
    depth_m: ArrayLike | None = None,
    bf: float = 0.0,
    max_stereo_depth_m: float = 3.0,
) -> RefineResult:
    """Motion-only bundle adjustment of a camera pose (ORB-SLAM2's PoseOptimization).

    Minimises the Huber-robust sum of whitened reprojection errors
    ``|| (fx (X/Z - x), fy (Y/Z - y)) / sigma ||^2`` over the pose, where (x, y) are the
    undistorted normalised observations (distortion handled exactly, once) and
    (X, Y, Z) = T_cam_world p_world. ``rounds`` rounds of ``iterations``
    Levenberg-Marquardt steps on se(3) (analytic Jacobians, left perturbation); after each
    round every correspondence is re-classified (whitened squared error <= ``chi2_threshold``
    and in front of the camera), and the next round optimises the inliers only. The
    first ``rounds - 1`` rounds use the Huber kernel; the last is plain least squares on
    the inliers (ORB-SLAM2 drops the kernel for its last rounds too).

    ``huber_px=inf`` with ``chi2_threshold=inf`` is plain least squares on everything.

    Args:
        points_world: (N, 3) world points, metres.
        uv: (N, 2) observed pixels (distorted image); non-finite rows are ignored.
        camera: intrinsics and distortion.
        T_cam_world_init: (4, 4) initial pose (e.g. from :func:`solve_pnp_ransac`).
        huber_px: Huber threshold on the whitened error, pixels (default
            sqrt(5.991) ~ 2.45 px, see :data:`HUBER_PX_DEFAULT`).
        iterations: LM iterations per round (stops early on convergence).
        sigma_px: per-point (N,) or scalar standard deviation of the observation in
            pixels, e.g. ``1.2 ** octave`` for pyramid level ``octave``; default 1.
        rounds: optimise / re-classify rounds (ORB-SLAM2: 4).
        chi2_threshold: inlier gate on the whitened squared error (5.991: 95 %, 2 dof); an
            RGB-D observation's gate is this times 7.815 / 5.991 (3 dof).
        depth_m: (N,) measured depth of each observation in metres (RGB-D keypoints), or
            None. With ``bf > 0``, observations with 0 < depth <= ``max_stereo_depth_m``
            add ORB-SLAM2's virtual right coordinate ``u - bf / depth``, which pins the
            distance to the points (forward motion toward a far wall is otherwise weakly
            observed by reprojection alone).
        bf: virtual stereo baseline times fx, pixels metres (ORB-SLAM2's ``Camera.bf``; 40
            for a Kinect-class sensor); 0 disables the depth term.
        max_stereo_depth_m: depth beyond which a keypoint is a monocular observation
            (ORB-SLAM2's ``ThDepth`` times the baseline).

    Returns:
        :class:`RefineResult` ``(T_cam_world, inliers (N,), cost)``. With fewer than 3
        usable points the initial pose comes back with no inliers and ``cost = inf``.

    Raises:
        GeometryError: wrong shapes, a non-rigid initial pose, or non-positive sigma.
    """
    P_all, uv_all = _check_correspondences(points_world, uv, "refine_pose_huber")
    T = check_transform(T_cam_world_init, "T_cam_world_init").copy()
    n = P_all.shape[0]
    if sigma_px is None:
        sigma = np.ones(n)
    else:
        sigma = np.broadcast_to(np.asarray(sigma_px, dtype=np.float64), (n,)).copy()
        if not np.all(sigma[np.isfinite(sigma)] > 0):
            raise GeometryError("refine_pose_huber: sigma_px must be positive")
    info_all = 1.0 / (sigma * sigma)
    if rounds < 1 or iterations < 0:
        raise GeometryError(
            f"refine_pose_huber: need rounds >= 1 and iterations >= 0, got {rounds}, {iterations}"
        )

    izm_all = np.zeros(n)
    if depth_m is not None and bf > 0:
        z = np.broadcast_to(np.asarray(depth_m, dtype=np.float64), (n,))
        close = np.isfinite(z) & (z > _MIN_DEPTH) & (z <= max_stereo_depth_m)
        izm_all[close] = 1.0 / z[close]
    gate_all = np.where(izm_all > 0, chi2_threshold * CHI2_3DOF_95 / CHI2_2DOF_95, chi2_threshold)
    xy_all = np.full((n, 2), np.nan)
    valid = np.all(np.isfinite(P_all), axis=1) & np.all(np.isfinite(uv_all), axis=1) & np.isfinite(info_all)
    xy_all[valid] = _normalized(camera, uv_all[valid])
    valid &= np.all(np.isfinite(xy_all), axis=1)
    idx = np.nonzero(valid)[0]
    inliers = np.zeros(n, np.bool_)
    if idx.size < 3:
        return RefineResult(T, inliers, math.inf)
    P, xy, info, izm, gate = P_all[idx], xy_all[idx], info_all[idx], izm_all[idx], gate_all[idx]
    fx, fy = camera.fx, camera.fy

    R, t, e2 = _refine_rounds(
        np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]), np.ascontiguousarray(P),
        np.ascontiguousarray(xy), np.ascontiguousarray(info), np.ascontiguousarray(izm),
        np.ascontiguousarray(gate), float(bf), float(fx), float(fy), float(huber_px), int(iterations),
        int(rounds),
    )
    T = make_transform(R, t)
    inliers[idx] = e2 <= gate
    cost = _huber_cost(e2[np.isfinite(e2)], float(huber_px))
    return RefineResult(T, inliers, cost)


class RollingShutterResult(NamedTuple):
    """Result of :func:`refine_pose_rolling_shutter`.

    Attributes:
        T_cam_world: (4, 4) the camera pose at the middle row's instant.
        shear_rad: (3,) the camera's turn over one full readout (first row to last), radians,
            camera frame: angular velocity times readout time.
        ok: the fit converged with enough points (else the inputs come back).
    """

    T_cam_world: F64
    shear_rad: F64
    ok: bool


def refine_pose_rolling_shutter(
    points_world: ArrayLike,
    uv: ArrayLike,
    camera: PinholeCamera,
    T_cam_world_init: ArrayLike,
    shear_init_rad: ArrayLike,
    *,
    sigma_px: ArrayLike | None = None,
    shear_sigma_rad: float = 0.02,
    huber_px: float = HUBER_PX_DEFAULT,
    depth_m: ArrayLike | None = None,
    bf: float = 0.0,
    max_stereo_depth_m: float = 3.0,
    iterations: int = 6,
) -> RollingShutterResult:
    """Pose and rolling-shutter spin of one frame, fitted together (inlier correspondences).

    Row v is read ``tau = (v - cy) / height`` readouts after the middle row; over that time
    the camera turned by ``tau s`` (``s``: the turn over one readout, camera frame), so a
    point at ``X = T_cam_world p`` in the middle row's camera frame is seen at
    ``X - tau s x X`` (first order in rotation, translation during the readout ignored; the
    inverse of :func:`wardmap.edge.tracker.unroll_keypoints`). The spin comes from the
    image's own shear, not from the previous poses, so it does not lag the motion.
    Minimises the Huber-robust whitened reprojection error (plus ORB-SLAM2's virtual right
    coordinate for keypoints with depth, as :func:`refine_pose_huber`) over the pose (6, a left se(3) update)
    and ``s`` (3) by Gauss-Newton with Huber weights; a Gaussian prior
    ``N(shear_init_rad, shear_sigma_rad^2)`` keeps ``s`` defined with few points.

    Args:
        points_world: (N, 3) world points, metres (inliers of a first pose estimate).
        uv: (N, 2) observed pixels as read (not unrolled; distorted image).
        camera: intrinsics and distortion.
        T_cam_world_init: (4, 4) initial pose.
        shear_init_rad: (3,) prior mean and start of ``s``, radians.
        sigma_px: per-point (N,) or scalar observation sigma, pixels (default 1).
        shear_sigma_rad: prior standard deviation of each component of ``s``, radians.
        huber_px: Huber threshold on the whitened error, pixels.
        depth_m, bf, max_stereo_depth_m: the RGB-D term, as in :func:`refine_pose_huber`.
        iterations: most Gauss-Newton steps (stops early once a step is below 1e-7).

    Returns:
        :class:`RollingShutterResult`; ``ok`` False (inputs returned) with fewer than 6
        usable points or a singular or diverging step.

    Raises:
        GeometryError: wrong shapes, a non-rigid initial pose, or non-positive sigma.
    """
    P_all, uv_all = _check_correspondences(points_world, uv, "refine_pose_rolling_shutter")
    T0 = check_transform(T_cam_world_init, "T_cam_world_init").copy()
    s0 = np.asarray(shear_init_rad, np.float64).reshape(3)
    n = P_all.shape[0]
    sigma = np.broadcast_to(np.asarray(1.0 if sigma_px is None else sigma_px, np.float64), (n,))
    if not np.all(sigma[np.isfinite(sigma)] > 0) or not shear_sigma_rad > 0:
        raise GeometryError("refine_pose_rolling_shutter: sigmas must be positive")
    izm = np.zeros(n)
    if depth_m is not None and bf > 0:
        z = np.broadcast_to(np.asarray(depth_m, np.float64), (n,))
        close = np.isfinite(z) & (z > _MIN_DEPTH) & (z <= max_stereo_depth_m)
        izm[close] = 1.0 / z[close]
    xy = np.full((n, 2), np.nan)
    valid = np.all(np.isfinite(P_all), axis=1) & np.all(np.isfinite(uv_all), axis=1) & np.isfinite(sigma)
    xy[valid] = _normalized(camera, uv_all[valid])
    valid &= np.all(np.isfinite(xy), axis=1)
    if int(valid.sum()) < 6:
        return RollingShutterResult(T0, s0, False)
    P, xy, w, izm = P_all[valid], xy[valid], 1.0 / sigma[valid], izm[valid]
    tau = (uv_all[valid, 1] - camera.cy) / camera.height
    fx, fy = camera.fx, camera.fy

    # Gauss-Newton with Huber weights (iteratively reweighted): 9 unknowns, a 9 x 9 solve per
    # step; the pose is re-linearised at each step.
    T, shear = T0, s0.copy()
    for _ in range(iterations):
        H, g = _rolling_shutter_system(np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]),
                                       shear, s0, P, xy, w, izm, tau, float(bf), fx, fy,
                                       float(huber_px), float(shear_sigma_rad))
        try:
            step = np.linalg.solve(H, -g)
        except np.linalg.LinAlgError:
            return RollingShutterResult(T0, s0, False)
        if not np.all(np.isfinite(step)):
            return RollingShutterResult(T0, s0, False)
        T = se3_exp(step[:6]) @ T
        shear = shear + step[6:]
        if float(np.abs(step).max()) < 1e-7:
            break
    return RollingShutterResult(T, shear, True)


@njit(cache=True, nogil=True)
def _rolling_shutter_system(
    R: F64, t: F64, shear: F64, s0: F64, P: F64, xy: F64, w: F64, izm: F64, tau: F64, bf: float,
    fx: float, fy: float, huber: float, shear_sigma: float,
) -> tuple[F64, F64]:
    """Normal equations ``H = J^T W J`` (9, 9) and ``g = J^T W r`` (9,) of
    :func:`refine_pose_rolling_shutter`'s whitened residuals, ``W`` their Huber weights (each
    residual its own; the shear prior Gaussian), unknowns ``(rho, omega, shear)`` with the pose
    perturbed on the left.

    Per point: ``X = R p + t``, ``Y = X - tau s x X`` (the row's camera frame), ``a, b = Y_x / Y_z,
    Y_y / Y_z``; residuals ``w fx (a - x)``, ``w fy (b - y)`` and, with depth, ``w (fx (a - x) -
    bf (1 / Y_z - 1 / z))``. ``dY/dX = I - tau [s]x``, ``dX/d(rho, omega) = [I | -[X]x]``,
    ``dY/ds = tau [X]x``.
    """
    H = np.zeros((9, 9))
    g = np.zeros(9)
    dY = np.zeros((3, 9))
    M = np.zeros((3, 3))  # dY/dX
    jr = np.zeros(9)
    s_x, s_y, s_z = shear[0], shear[1], shear[2]
    for i in range(P.shape[0]):
        X0 = R[0, 0] * P[i, 0] + R[0, 1] * P[i, 1] + R[0, 2] * P[i, 2] + t[0]
        X1 = R[1, 0] * P[i, 0] + R[1, 1] * P[i, 1] + R[1, 2] * P[i, 2] + t[1]
        X2 = R[2, 0] * P[i, 0] + R[2, 1] * P[i, 1] + R[2, 2] * P[i, 2] + t[2]
        ti = tau[i]
        # s x X
        c0 = s_y * X2 - s_z * X1
        c1 = s_z * X0 - s_x * X2
        c2 = s_x * X1 - s_y * X0
        Y0, Y1, Y2 = X0 - ti * c0, X1 - ti * c1, X2 - ti * c2
        iz = 1.0 / max(Y2, _MIN_DEPTH)
        a, b = Y0 * iz, Y1 * iz
        # M = I - tau [s]x
        M[0, 0], M[0, 1], M[0, 2] = 1.0, ti * s_z, -ti * s_y
        M[1, 0], M[1, 1], M[1, 2] = -ti * s_z, 1.0, ti * s_x
        M[2, 0], M[2, 1], M[2, 2] = ti * s_y, -ti * s_x, 1.0
        for r in range(3):
            # M @ [I | -[X]x]: columns 0-2 are M; column 3+k is -M @ hat(X)[:, k]
            m0, m1, m2 = M[r, 0], M[r, 1], M[r, 2]
            dY[r, 0], dY[r, 1], dY[r, 2] = m0, m1, m2
            dY[r, 3] = -(m1 * X2 - m2 * X1)
            dY[r, 4] = -(-m0 * X2 + m2 * X0)
            dY[r, 5] = -(m0 * X1 - m1 * X0)
        # tau [X]x
        dY[0, 6], dY[0, 7], dY[0, 8] = 0.0, -ti * X2, ti * X1
        dY[1, 6], dY[1, 7], dY[1, 8] = ti * X2, 0.0, -ti * X0
        dY[2, 6], dY[2, 7], dY[2, 8] = -ti * X1, ti * X0, 0.0
        wi = w[i]
        stereo = izm[i] > 0.0
        n_res = 3 if stereo else 2
        for k in range(n_res):
            if k == 0:
                res = wi * fx * (a - xy[i, 0])
                for c in range(9):
                    jr[c] = wi * fx * (dY[0, c] - a * dY[2, c]) * iz
            elif k == 1:
                res = wi * fy * (b - xy[i, 1])
                for c in range(9):
                    jr[c] = wi * fy * (dY[1, c] - b * dY[2, c]) * iz
            else:
                res = wi * (fx * (a - xy[i, 0]) - bf * (iz - izm[i]))
                for c in range(9):
                    jr[c] = wi * (fx * (dY[0, c] - a * dY[2, c]) * iz + bf * iz * iz * dY[2, c])
            ar = abs(res)
            wt = 1.0 if ar <= huber else huber / max(ar, 1e-12)
            for c in range(9):
                g[c] += wt * jr[c] * res
                for d in range(c, 9):
                    H[c, d] += wt * jr[c] * jr[d]
    for c in range(9):
        for d in range(c):
            H[c, d] = H[d, c]
    inv_var = 1.0 / (shear_sigma * shear_sigma)
    for k in range(3):  # the Gaussian prior N(s0, shear_sigma^2) on the shear
        H[6 + k, 6 + k] += inv_var
        g[6 + k] += (shear[k] - s0[k]) * inv_var
    return H, g


__all__ = [
    "CHI2_2DOF_95",
    "CHI2_3DOF_95",
    "HUBER_PX_DEFAULT",
    "MIN_PNP_POINTS",
    "PnpResult",
    "RefineResult",
    "RollingShutterResult",
    "refine_pose_huber",
    "refine_pose_rolling_shutter",
    "solve_pnp_ransac",
]

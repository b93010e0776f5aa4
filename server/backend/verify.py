"""Geometric verification of a loop-closure candidate (ORB-SLAM2's loop check, RGB-D).

A place-recognition candidate is accepted only when the two keyframes' ORB features
support one rigid pose:

1. match the query's descriptors against the candidate's keypoints that have depth
   (brute-force Hamming, Lowe's ratio test, a distance cap, mutual best match);
2. back-project the matched candidate keypoints with their depth into the candidate camera
   frame and find the query camera pose from these 3D points and the query pixels by EPnP
   in RANSAC (paper 003 Eq. 6-9; ``cv2.solvePnPRansac(flags=SOLVEPNP_EPNP)``);
3. refine on the inliers with Levenberg-Marquardt (``cv2.solvePnPRefineLM``), re-select the
   inliers, refine again;
4. accept only with enough inliers, a high enough inlier share, inliers spread over both
   images (a single chair or door frame seen twice is not a place), and, where the query
   keypoints have depth, 3D points that agree with the candidate's.

Lens distortion is removed once: query pixels become pixels of an ideal camera with the
query's ``K`` and no distortion; candidate pixels are back-projected with their own camera.
The two keyframes may come from different cameras (robots).

:func:`verify_pair` never raises on scene content; it returns :class:`Verified` or a short
rejection reason from :data:`REASONS`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Final

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import ConfigError, GeometryError
from wardmap.shared.hamming import knn2
from wardmap.shared.se3 import inverse, make_transform
from wardmap.shared.wire import Keypoints

__all__ = ["REASONS", "KeyframeFeatures", "Verified", "VerifyConfig", "verify_pair"]

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]
I64 = NDArray[np.int64]

REASONS: Final = (
    "few points",
    "few matches",
    "pnp failed",
    "few inliers",
    "low inlier ratio",
    "clustered inliers",
    "depth mismatch",
)
"""Every rejection reason :func:`verify_pair` returns."""

_MIN_Z_M = 1e-3
"""Points closer than this to a camera's image plane count as behind it."""


def _readonly(a: NDArray[np.generic]) -> NDArray[np.generic]:
    a = np.ascontiguousarray(a)
    if a.flags.writeable:
        a = a.copy()
        a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class KeyframeFeatures:
    """The keypoints of one keyframe as verification needs them (arrays read-only).

    Attributes:
        uv: float32 (N, 2) pixel coordinates in the (distorted) colour image.
        depth_m: float32 (N,) depth along the camera's z axis, metres; 0 = none.
        descriptors: uint8 (N, 32) ORB descriptors (256 bits).
        camera: the colour camera's intrinsics and distortion.
        octave: int (N,) ORB pyramid level of each keypoint (0 = full resolution), or None
            (unknown; bundle adjustment then weighs all as level 0).
        point_id: int (N,) the edge tracker's map point each keypoint observed, -1 = none
            (the wire's ``keypoints.point_id``), or None when the robot sent none; bundle
            adjustment joins a session's keypoints into tracks by it.
    """

    uv: F32
    depth_m: F32
    descriptors: U8
    camera: PinholeCamera
    octave: NDArray[np.integer] | None = None
    point_id: NDArray[np.integer] | None = None

    def __post_init__(self) -> None:
        uv = np.asarray(self.uv)
        if uv.ndim != 2 or uv.shape[1] != 2 or not np.issubdtype(uv.dtype, np.floating):
            raise GeometryError(f"keyframe features: expected uv float (N, 2), got {uv.dtype} {uv.shape}")
        n = uv.shape[0]
        depth = np.asarray(self.depth_m)
        if depth.shape != (n,) or not np.issubdtype(depth.dtype, np.floating):
            raise GeometryError(
                f"keyframe features: expected depth_m float ({n},), got {depth.dtype} {depth.shape}"
            )
        desc = np.asarray(self.descriptors)
        if desc.dtype != np.uint8 or desc.shape != (n, 32):
            raise GeometryError(
                f"keyframe features: expected descriptors uint8 ({n}, 32), got {desc.dtype} {desc.shape}"
            )
        if not np.all(np.isfinite(uv)):
            raise GeometryError("keyframe features: uv must be finite")
        if not np.all(np.isfinite(depth)) or (n and float(depth.min()) < 0):
            raise GeometryError("keyframe features: depth_m must be finite and >= 0 (0 = none)")
        if not isinstance(self.camera, PinholeCamera):
            raise GeometryError(
                f"keyframe features: expected a PinholeCamera, got {type(self.camera).__name__}"
            )
        object.__setattr__(self, "uv", _readonly(uv.astype(np.float32, copy=False)))
        object.__setattr__(self, "depth_m", _readonly(depth.astype(np.float32, copy=False)))
        object.__setattr__(self, "descriptors", _readonly(desc))
        if self.octave is not None:
            octave = np.asarray(self.octave)
            if octave.shape != (n,) or not np.issubdtype(octave.dtype, np.integer):
                raise GeometryError(
                    f"keyframe features: expected octave int ({n},), got {octave.dtype} {octave.shape}")
            object.__setattr__(self, "octave", _readonly(octave))
        if self.point_id is not None:
            pid = np.asarray(self.point_id)
            if pid.shape != (n,) or not np.issubdtype(pid.dtype, np.integer):
                raise GeometryError(
                    f"keyframe features: expected point_id int ({n},), got {pid.dtype} {pid.shape}")
            object.__setattr__(self, "point_id", _readonly(pid.astype(np.int64, copy=False)))

    def __len__(self) -> int:
        return int(self.uv.shape[0])

    @staticmethod
    def from_keypoints(keypoints: Keypoints, camera: PinholeCamera) -> KeyframeFeatures:
        """The features of a wire :class:`~wardmap.shared.wire.Keypoints` seen by ``camera``."""
        return KeyframeFeatures(keypoints.uv, keypoints.depth_m, keypoints.descriptors, camera,
                                keypoints.octave, keypoints.point_id)


@dataclass(frozen=True)
class VerifyConfig:
    """Thresholds of :func:`verify_pair`. Defaults favour precision: in a hospital ward
    identical doors and rows of identical chairs make false loops the costly error."""

    ratio: float = 0.75
    """Lowe's ratio test: best distance < ratio * second best (ORB-SLAM2's loop search uses 0.75)."""
    max_hamming: int = 50
    """Largest descriptor distance of a match, bits of 256 (ORB-SLAM2's TH_LOW; unrelated
    descriptors are ~128 apart)."""
    mutual: bool = True
    """Keep a match only if it is also the candidate keypoint's best match in the query."""
    min_matches: int = 20
    """Fewer descriptor matches rejects before PnP (ORB-SLAM2 drops loop candidates under 20)."""
    depth_range_m: tuple[float, float] = (0.3, 6.0)
    """Candidate keypoints with depth in this range become 3D points, metres (the edge
    tracker's map-point range; far depth is noisy)."""
    reprojection_px: float = 3.0
    """Inlier threshold on the reprojection error in the query image, pixels (about the 95 %
    chi-square bound for 1 px noise, as ORB-SLAM2's 5.991)."""
    ransac_iterations: int = 300
    """RANSAC hypotheses at most (300 reach 99.9 % confidence at 30 % inliers with 5-point samples)."""
    ransac_confidence: float = 0.999
    """RANSAC stops early once this confident of having drawn an all-inlier sample."""
    min_inliers: int = 30
    """Fewer inliers after refinement rejects (ORB-SLAM2 asks 40 projected matches for a loop;
    30 with the spread and depth checks below)."""
    min_inlier_ratio: float = 0.3
    """Inliers / matches below this rejects: a true revisit explains most matches."""
    spread_grid: tuple[int, int] = (4, 4)
    """Columns x rows of the grid over each image for the spread check."""
    min_spread_cells: int = 5
    """Inliers must fall in at least this many grid cells in both images (5 of 16 cells is
    more than one object at arm's length covers)."""
    depth_tolerance: float = 0.1
    """A query keypoint with depth agrees with its candidate 3D point when they are closer
    than this share of the candidate point's depth (plus 2 cm)."""
    min_depth_agreement: float = 0.5
    """Share of inliers with query depth that must agree (when at least 6 have depth); 0 = off."""
    min_sigma_px: float = 1.0
    """Least reprojection noise (px) assumed for the pose's standard deviations."""

    def __post_init__(self) -> None:
        if not 0 < self.ratio <= 1:
            raise ConfigError(f"verify.ratio must be in (0, 1], got {self.ratio!r}")
        if not (np.isfinite(self.min_sigma_px) and self.min_sigma_px > 0):
            raise ConfigError(f"verify.min_sigma_px must be > 0, got {self.min_sigma_px!r}")
        if not 0 <= self.max_hamming <= 256:
            raise ConfigError(f"verify.max_hamming must be in 0..256, got {self.max_hamming!r}")
        if self.min_matches < 6:
            raise ConfigError(f"verify.min_matches must be >= 6 (EPnP in RANSAC), got {self.min_matches!r}")
        if len(self.depth_range_m) != 2 or not 0 < self.depth_range_m[0] < self.depth_range_m[1]:
            raise ConfigError(f"verify.depth_range_m needs 0 < min < max, got {self.depth_range_m!r}")
        if not self.reprojection_px > 0:
            raise ConfigError(f"verify.reprojection_px must be > 0, got {self.reprojection_px!r}")
        if self.ransac_iterations < 1:
            raise ConfigError(f"verify.ransac_iterations must be >= 1, got {self.ransac_iterations!r}")
        if not 0 < self.ransac_confidence < 1:
            raise ConfigError(f"verify.ransac_confidence must be in (0, 1), got {self.ransac_confidence!r}")
        if self.min_inliers < 6:
            raise ConfigError(f"verify.min_inliers must be >= 6, got {self.min_inliers!r}")
        if not 0 <= self.min_inlier_ratio <= 1:
            raise ConfigError(f"verify.min_inlier_ratio must be in [0, 1], got {self.min_inlier_ratio!r}")
        if len(self.spread_grid) != 2 or min(self.spread_grid) < 1:
            raise ConfigError(f"verify.spread_grid needs two sizes >= 1, got {self.spread_grid!r}")
        if not 0 <= self.min_spread_cells <= self.spread_grid[0] * self.spread_grid[1]:
            raise ConfigError(
                f"verify.min_spread_cells must be in 0..{self.spread_grid[0] * self.spread_grid[1]}, "
                f"got {self.min_spread_cells!r}"
            )
        if not self.depth_tolerance > 0:
            raise ConfigError(f"verify.depth_tolerance must be > 0, got {self.depth_tolerance!r}")
        if not 0 <= self.min_depth_agreement <= 1:
            raise ConfigError(
                f"verify.min_depth_agreement must be in [0, 1], got {self.min_depth_agreement!r}"
            )


_NO_SIGMAS: Final = np.full(6, np.inf)


@dataclass(frozen=True, eq=False)
class Verified:
    """An accepted candidate.

    Attributes:
        T_cand_query: (4, 4) float64 pose of the query camera in the candidate camera frame
            (maps query-camera points to candidate-camera points), metres.
        inliers: matches consistent with the pose after refinement.
        matches: descriptor matches that entered PnP.
        rms_px: root-mean-square reprojection error of the inliers in the query image, pixels
            (of the ideal, undistorted camera).
        sigmas: (6,) float64 standard deviations of ``inv(T_cand_query)`` (the query->candidate
            edge ``T_query_cand``) over a right perturbation: rotation rad x3, translation m x3
            (:func:`_pose_sigmas`; reprojection noise ``max(rms_px, min_sigma_px)``).
    """

    T_cand_query: F64
    inliers: int
    matches: int
    rms_px: float
    sigmas: F64 = field(default_factory=lambda: _NO_SIGMAS)


def _match(query: U8, cand: U8, config: VerifyConfig) -> tuple[I64, I64]:
    """Indices (q, c) of matches query -> cand: ratio test, distance cap, optional mutual check
    (:func:`wardmap.shared.hamming.knn2`: one pass over all pairs gives both directions)."""
    if query.shape[0] == 0 or cand.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    best, d1, d2, back = knn2(query, cand)
    ok = (best >= 0) & (d1 <= config.max_hamming)
    if cand.shape[0] >= 2:
        ok &= d1 < config.ratio * d2
    q_idx = np.flatnonzero(ok).astype(np.int64)
    c_idx = best[q_idx]
    if config.mutual:
        keep = back[c_idx] == q_idx
    else:  # a candidate keypoint claimed by several query keypoints is ambiguous: drop it
        counts = np.bincount(c_idx, minlength=cand.shape[0])
        keep = counts[c_idx] == 1
    return q_idx[keep], c_idx[keep]


def _ideal_pixels(camera: PinholeCamera, uv: F64) -> F64:
    """Pixels (N, 2) of the undistorted camera with the same K."""
    if not camera.has_distortion:
        return uv
    xy_d = np.column_stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy])
    xy = camera.undistort_normalized(xy_d)
    return np.column_stack([xy[:, 0] * camera.fx + camera.cx, xy[:, 1] * camera.fy + camera.cy])


def _errors_px(T_query_cand: F64, points_cand: F64, uv_ideal: F64, camera: PinholeCamera) -> F64:
    """Reprojection errors (N,) in query-image pixels; inf for points behind the query camera."""
    pc = points_cand @ T_query_cand[:3, :3].T + T_query_cand[:3, 3]
    z = pc[:, 2]
    front = z > _MIN_Z_M
    zs = np.where(front, z, 1.0)
    du = camera.fx * pc[:, 0] / zs + camera.cx - uv_ideal[:, 0]
    dv = camera.fy * pc[:, 1] / zs + camera.cy - uv_ideal[:, 1]
    return np.where(front, np.hypot(du, dv), np.inf)


def _pose_sigmas(T_query_cand: F64, points_cand: F64, camera: PinholeCamera, sigma_px: float) -> F64:
    """Standard deviations (6,) of the refined pose ``T_query_cand`` from its inliers: the
    Gauss-Newton covariance ``sigma_px^2 (J^T J)^-1`` of the reprojection errors over a right
    perturbation ``T_query_cand @ exp(xi)``, ``xi`` = (rotation rad x3, translation m x3) in the
    candidate camera frame (the tangent space of a gtsam ``BetweenFactorPose3(query, cand)``);
    correlations are dropped. Errors of the candidate's depth are not modelled here (the back-end
    inflates these)."""
    eps = 1e-6
    n = len(points_cand)
    base = _project(T_query_cand, points_cand, camera)
    J = np.empty((2 * n, 6))
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = eps
        J[:, k] = ((_project(T_query_cand @ _exp(xi), points_cand, camera) - base) / eps).ravel()
    info = J.T @ J
    try:
        cov = np.linalg.inv(info) * sigma_px**2
    except np.linalg.LinAlgError:
        return np.full(6, np.inf)
    out = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    out.flags.writeable = False
    return out


def _project(T: F64, points: F64, camera: PinholeCamera) -> F64:
    pc = points @ T[:3, :3].T + T[:3, 3]
    z = np.maximum(pc[:, 2], _MIN_Z_M)
    return np.column_stack([camera.fx * pc[:, 0] / z + camera.cx, camera.fy * pc[:, 1] / z + camera.cy])


def _exp(xi: F64) -> F64:
    """SE3 exponential, first order in translation: ``[R(xi[:3]) | xi[3:]]`` (for tiny ``xi``)."""
    R, _ = cv2.Rodrigues(np.asarray(xi[:3], np.float64))
    return make_transform(R, xi[3:])


def _pose(rvec: ArrayLike, tvec: ArrayLike) -> F64:
    R, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
    return make_transform(R, np.asarray(tvec, np.float64).reshape(3))


def _cells(uv: NDArray[np.floating], camera: PinholeCamera, grid: tuple[int, int]) -> int:
    """Number of occupied cells of a ``grid`` (columns, rows) over the image."""
    gx, gy = grid
    cx = np.clip((uv[:, 0] + 0.5) * gx / camera.width, 0, gx - 1).astype(np.int64)
    cy = np.clip((uv[:, 1] + 0.5) * gy / camera.height, 0, gy - 1).astype(np.int64)
    return int(np.unique(cy * gx + cx).size)


def verify_pair(
    query: KeyframeFeatures, cand: KeyframeFeatures, config: VerifyConfig | None = None
) -> Verified | str:
    """Check that ``query`` sees the place of ``cand`` and find the relative pose.

    Args:
        query: the new keyframe's features (2D side of PnP; its depth is only checked).
        cand: the candidate's features; keypoints with depth in ``depth_range_m`` give the
            3D points, in the candidate camera frame.
        config: thresholds; defaults if None.

    Returns:
        :class:`Verified` with ``T_cand_query`` (query camera pose in the candidate camera
        frame), or the rejection reason, one of :data:`REASONS`: ``"few points"`` (fewer
        than ``min_matches`` query keypoints or candidate keypoints with depth),
        ``"few matches"``, ``"pnp failed"`` (no RANSAC consensus), ``"few inliers"``,
        ``"low inlier ratio"``, ``"clustered inliers"``, ``"depth mismatch"``.

    Deterministic: OpenCV's RANSAC draws from its own fixed-seed generator.
    """
    cfg = config if config is not None else VerifyConfig()
    lo, hi = cfg.depth_range_m
    c_ok = np.flatnonzero((cand.depth_m >= lo) & (cand.depth_m <= hi))
    if len(query) < cfg.min_matches or c_ok.size < cfg.min_matches:
        return "few points"
    q_idx, c_sub = _match(np.asarray(query.descriptors), np.asarray(cand.descriptors)[c_ok], cfg)
    n_matches = int(q_idx.size)
    if n_matches < cfg.min_matches:
        return "few matches"
    c_idx = c_ok[c_sub]

    # 3D points of the candidate (its camera frame) and ideal query pixels, one row per match.
    P = cand.camera.unproject(cand.uv[c_idx].astype(np.float64), cand.depth_m[c_idx])
    uv_q = _ideal_pixels(query.camera, query.uv[q_idx].astype(np.float64))
    K = query.camera.K
    no_dist = np.zeros(5)
    try:
        found, rvec, tvec, _ = cv2.solvePnPRansac(
            np.ascontiguousarray(P),
            np.ascontiguousarray(uv_q),
            K,
            no_dist,
            iterationsCount=int(cfg.ransac_iterations),
            reprojectionError=float(cfg.reprojection_px),
            confidence=float(cfg.ransac_confidence),
            flags=cv2.SOLVEPNP_EPNP,
        )
    except cv2.error:  # OpenCV rejects some degenerate point sets inside EPnP
        return "pnp failed"
    if not found or not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return "pnp failed"

    T_query_cand = _pose(rvec, tvec)
    inl = _errors_px(T_query_cand, P, uv_q, query.camera) <= cfg.reprojection_px
    for _ in range(2):  # refine on the inliers, then re-select them
        if int(inl.sum()) < 6:
            break
        rvec, tvec = cv2.solvePnPRefineLM(
            np.ascontiguousarray(P[inl]), np.ascontiguousarray(uv_q[inl]), K, no_dist, rvec, tvec
        )
        T_query_cand = _pose(rvec, tvec)
        inl = _errors_px(T_query_cand, P, uv_q, query.camera) <= cfg.reprojection_px
    n_in = int(inl.sum())
    if n_in < cfg.min_inliers:
        return "few inliers"
    if n_in < cfg.min_inlier_ratio * n_matches:
        return "low inlier ratio"
    if (
        _cells(query.uv[q_idx[inl]], query.camera, cfg.spread_grid) < cfg.min_spread_cells
        or _cells(cand.uv[c_idx[inl]], cand.camera, cfg.spread_grid) < cfg.min_spread_cells
    ):
        return "clustered inliers"

    T_cand_query = inverse(T_query_cand)
    if cfg.min_depth_agreement > 0:
        dq = query.depth_m[q_idx[inl]].astype(np.float64)
        has = dq > 0
        if int(has.sum()) >= 6:
            pq = query.camera.unproject(query.uv[q_idx[inl]][has].astype(np.float64), dq[has])
            pc = pq @ T_cand_query[:3, :3].T + T_cand_query[:3, 3]
            Pin = P[inl][has]
            agree = np.linalg.norm(pc - Pin, axis=1) <= cfg.depth_tolerance * Pin[:, 2] + 0.02
            if float(agree.mean()) < cfg.min_depth_agreement:
                return "depth mismatch"

    err = _errors_px(T_query_cand, P[inl], uv_q[inl], query.camera)
    rms = float(np.sqrt(np.mean(err * err)))
    T = np.ascontiguousarray(T_cand_query, dtype=np.float64)
    T.flags.writeable = False
    sigmas = _pose_sigmas(T_query_cand, P[inl], query.camera, max(rms, cfg.min_sigma_px))
    return Verified(T_cand_query=T, inliers=n_in, matches=n_matches, rms_px=rms, sigmas=sigmas)

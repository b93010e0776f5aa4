"""Depth-only relative pose: projective point-to-plane ICP (KinectFusion, Newcombe et al. 2011).

The tracker's fallback for frames whose RGB image is unusable (motion blur, glare) while
the depth image is fine: structured-light and time-of-flight depth cameras expose far
shorter than a colour camera indoors, so a fast turn that smears the RGB image leaves the
depth image sharp. The current frame's depth points are moved into a reference frame
(the last frame with a measured pose) with the pose guess, associated with the reference
vertex by projection, and the point-to-plane error ``n_ref . (T p_cur - q_ref)`` is
minimised by Gauss-Newton with a Huber kernel, coarse to fine over a depth pyramid.

The result is refused (``ok`` False, with a reason) when too few points fit, the fit is
loose, or the geometry leaves a direction unconstrained (a flat wall, a long corridor):
the smallest eigenvalue of the normalised Gauss-Newton matrix is checked.

Frames: both depth images are registered to the same camera (``PinholeCamera``, distortion
handled exactly), depth in metres along z, 0 = no data. ``T_ref_cur`` maps points of the
current camera frame into the reference camera frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wardmap.shared.camera import PinholeCamera
from wardmap.shared.errors import ConfigError, GeometryError
from wardmap.shared.se3 import check_transform, se3_exp

__all__ = ["DepthPyramid", "IcpConfig", "IcpResult", "icp"]

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class IcpConfig:
    """Depth ICP parameters (``[tracker.icp]``).

    Attributes:
        enabled: use the depth fallback at all.
        strides: pixel strides of the pyramid levels, coarse first.
        iterations: Gauss-Newton steps per level.
        max_distance_m: association gate per level, coarse first: the point-to-plane distance
            (and four times it for the distance to the associated vertex).
        max_normal_deg: largest angle between associated normals.
        huber_m: Huber kernel width on the point-to-plane residual.
        max_depth_discontinuity: neighbours whose depths differ by more than this fraction
            per full-resolution pixel of distance give no normal (an occluding edge).
        min_depth_m, max_depth_m: depth range used.
        min_inlier_fraction: smallest share of the current frame's valid points that fit.
        max_rmse_m: largest RMS point-to-plane residual of the fitting points.
        min_eigen: smallest eigenvalue of ``J^T J / n`` (rotation columns scaled by 1 m);
            below it a direction is unconstrained and the pose is refused.
    """

    enabled: bool = True
    strides: tuple[int, ...] = (8, 4)
    iterations: int = 12
    max_distance_m: tuple[float, ...] = (0.15, 0.05)
    max_normal_deg: float = 30.0
    huber_m: float = 0.01
    max_depth_discontinuity: float = 0.05
    min_depth_m: float = 0.3
    max_depth_m: float = 5.0
    min_inlier_fraction: float = 0.4
    max_rmse_m: float = 0.012
    min_eigen: float = 0.002

    def __post_init__(self) -> None:
        if not self.strides or min(self.strides) < 1:
            raise ConfigError("tracker.icp.strides must be a non-empty list of integers >= 1")
        if len(self.max_distance_m) != len(self.strides) or min(self.max_distance_m) <= 0:
            raise ConfigError("tracker.icp.max_distance_m needs one positive value per stride")
        if self.iterations < 1 or self.huber_m <= 0 or not 0 < self.max_normal_deg <= 90:
            raise ConfigError("tracker.icp: need iterations >= 1, huber_m > 0, 0 < max_normal_deg <= 90")
        if not 0 < self.min_depth_m < self.max_depth_m:
            raise ConfigError("tracker.icp: need 0 < min_depth_m < max_depth_m")
        if not 0 < self.min_inlier_fraction <= 1 or self.max_rmse_m <= 0 or self.min_eigen < 0:
            raise ConfigError(
                "tracker.icp: need 0 < min_inlier_fraction <= 1, max_rmse_m > 0, min_eigen >= 0"
            )


@dataclass(frozen=True)
class IcpResult:
    """``T_ref_cur`` (4, 4) when ``ok``; the fit statistics either way; ``reason`` when refused."""

    ok: bool
    T_ref_cur: F64
    inlier_fraction: float
    rmse_m: float
    min_eigen: float
    reason: str = ""


class DepthPyramid:
    """Vertex and normal maps of one depth image at the configured strides (camera frame, metres)."""

    def __init__(self, depth_m: NDArray[np.floating], camera: PinholeCamera, config: IcpConfig,
                 rays: F64 | None = None) -> None:
        """Build the levels.

        Args:
            depth_m: (H, W) depth in metres along z; 0, NaN or inf = no data.
            camera: the camera the depth image is registered to (H, W must match).
            config: strides and depth range.
            rays: ``camera.pixel_rays()`` (H, W, 3), to share the undistortion between frames.

        Raises:
            GeometryError: the depth image does not match the camera.
        """
        d = np.asarray(depth_m, dtype=np.float64)
        if d.shape != (camera.height, camera.width):
            raise GeometryError(f"depth {d.shape} does not match the camera {camera.height}x{camera.width}")
        d = np.where(np.isfinite(d) & (d >= config.min_depth_m) & (d <= config.max_depth_m), d, 0.0)
        rays = camera.pixel_rays() if rays is None else rays
        self.strides = config.strides
        self.vertices: list[F64] = []
        self.normals: list[F64] = []
        for s in config.strides:
            ds = d[::s, ::s]
            V = rays[::s, ::s] * ds[..., None]
            self.vertices.append(np.where(ds[..., None] > 0, V, np.nan))
            self.normals.append(_normals(V, ds, config.max_depth_discontinuity * s))


def _normals(V: F64, d: F64, max_jump: float) -> F64:
    """Unit normals (h, w, 3) from central differences, facing the camera; NaN where undefined."""
    N = np.full(V.shape, np.nan)
    dx = V[1:-1, 2:] - V[1:-1, :-2]
    dy = V[2:, 1:-1] - V[:-2, 1:-1]
    n = np.cross(dx, dy)
    norm = np.linalg.norm(n, axis=2)
    c = d[1:-1, 1:-1]
    ok = (c > 0) & (d[1:-1, 2:] > 0) & (d[1:-1, :-2] > 0) & (d[2:, 1:-1] > 0) & (d[:-2, 1:-1] > 0)
    for nb in (d[1:-1, 2:], d[1:-1, :-2], d[2:, 1:-1], d[:-2, 1:-1]):
        ok &= np.abs(nb - c) <= max_jump * c
    ok &= norm > 1e-12
    n = n / np.where(norm > 1e-12, norm, 1.0)[..., None]
    flip = np.einsum("ijk,ijk->ij", n, V[1:-1, 1:-1]) > 0
    n[flip] *= -1.0
    N[1:-1, 1:-1] = np.where(ok[..., None], n, np.nan)
    return N


def icp(ref: DepthPyramid, cur: DepthPyramid, camera: PinholeCamera, T_ref_cur_guess: F64,
        config: IcpConfig) -> IcpResult:
    """Align ``cur`` to ``ref`` starting from ``T_ref_cur_guess`` (4, 4); see the module docstring."""
    T = check_transform(T_ref_cur_guess, "T_ref_cur_guess").copy()
    cos_max = np.cos(np.radians(config.max_normal_deg))
    frac = rmse = eig = 0.0
    for level, s in enumerate(config.strides):
        Vr, Nr = ref.vertices[level], ref.normals[level]
        Vc, Nc = cur.vertices[level], cur.normals[level]
        src_ok = np.isfinite(Vc[..., 0]) & np.isfinite(Nc[..., 0])
        P, Pn = Vc[src_ok], Nc[src_ok]
        if len(P) < 50:
            return IcpResult(False, T, 0.0, 0.0, 0.0, f"too few depth points ({len(P)})")
        gate = config.max_distance_m[level]
        h, w = Vr.shape[:2]
        for _ in range(config.iterations):
            R, t = T[:3, :3], T[:3, 3]
            Q = P @ R.T + t
            uv, front = camera.project(Q)
            u = np.rint(np.nan_to_num(uv[:, 0], nan=-1e9) / s)
            v = np.rint(np.nan_to_num(uv[:, 1], nan=-1e9) / s)
            inb = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            idx = np.flatnonzero(inb)
            ui, vi = u[idx].astype(np.intp), v[idx].astype(np.intp)
            q, n = Vr[vi, ui], Nr[vi, ui]
            p = Q[idx]
            good = np.isfinite(q[:, 0]) & np.isfinite(n[:, 0])
            diff = p - np.where(good[:, None], q, 0.0)
            # Gate on the point-to-plane distance: on a floor seen at a grazing angle a small
            # pose error moves the associated vertex far along the plane, not off it.
            good &= np.abs(np.einsum("ij,ij->i", diff, np.where(good[:, None], n, 0.0))) <= gate
            good &= np.einsum("ij,ij->i", diff, diff) <= (4.0 * gate) ** 2
            good &= np.einsum("ij,ij->i", Pn[idx] @ R.T, np.where(good[:, None], n, 0.0)) >= cos_max
            idx, p, n, diff = idx[good], p[good], n[good], diff[good]
            if len(idx) < 6:
                return IcpResult(False, T, 0.0, 0.0, 0.0, f"no depth overlap at stride {s}")
            r = np.einsum("ij,ij->i", n, diff)
            J = np.hstack([n, np.cross(p, n)])  # d r / d (rho, omega), left perturbation
            a = np.abs(r)
            wgt = np.where(a <= config.huber_m, 1.0, config.huber_m / np.maximum(a, 1e-12))
            H = (J * wgt[:, None]).T @ J
            g = (J * wgt[:, None]).T @ r
            try:
                xi = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
            except np.linalg.LinAlgError:
                return IcpResult(False, T, 0.0, 0.0, 0.0, "singular ICP system")
            T = se3_exp(xi) @ T
            frac = len(idx) / len(P)
            rmse = float(np.sqrt(np.mean(r * r)))
            eig = float(np.linalg.eigvalsh(J.T @ J / len(idx))[0])
            if np.linalg.norm(xi[:3]) < 1e-5 and np.linalg.norm(xi[3:]) < 1e-5:
                break
    if frac < config.min_inlier_fraction:
        return IcpResult(False, T, frac, rmse, eig, f"only {100 * frac:.0f} % of depth points fit")
    if rmse > config.max_rmse_m:
        return IcpResult(False, T, frac, rmse, eig, f"loose depth fit (RMS {100 * rmse:.1f} cm)")
    if eig < config.min_eigen:
        return IcpResult(False, T, frac, rmse, eig, f"depth geometry leaves a direction free ({eig:.3g})")
    return IcpResult(True, T, frac, rmse, eig)

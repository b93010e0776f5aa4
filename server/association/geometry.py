"""Pose comparison and box projection shared by the association stages.

Poses are (4, 4) float64 ``T_world_object`` (metres); rotations are compared modulo the
symmetries of a gravity-aligned box, because a measurement's yaw is ambiguous by 180 deg
and, for a near-square footprint, by 90 deg (``server/perception/measure.py``).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import NDArray

from wardmap.shared.camera import PinholeCamera
from wardmap.shared.se3 import inverse, yaw_rotation

__all__ = [
    "Symmetry",
    "box_iou",
    "cut_at_side",
    "cut_at_top_or_bottom",
    "is_truncated",
    "pairwise_angles",
    "partial_view_slack",
    "pose_residuals",
    "project_box",
    "symmetry_rotations",
    "world_extents",
]

F64 = NDArray[np.float64]
Symmetry = Literal["none", "half_turn", "quarter_turn"]


def symmetry_rotations(symmetry: Symmetry) -> F64:
    """Rotations (S, 3, 3) about the object z axis under which a box pose is the same pose.

    ``none``: identity only; ``half_turn``: 0 and 180 deg; ``quarter_turn``: multiples of 90 deg.
    """
    steps = {"none": 1, "half_turn": 2, "quarter_turn": 4}[symmetry]
    return np.stack([yaw_rotation(2 * np.pi * k / steps) for k in range(steps)])


def _rotvec(R: F64) -> F64:
    """Axis-angle vectors (..., 3) of rotations (..., 3, 3), angle in [0, pi] (batched log map)."""
    cos_t = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos_t)
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin_t = np.sin(theta)
    small = sin_t < 1e-6
    scale = np.where(small, 0.5, theta / (2.0 * np.where(small, 1.0, sin_t)))
    out = w * scale[..., None]
    # Near pi the antisymmetric part vanishes: take the axis from the symmetric part.
    near_pi = small & (theta > 1.0)
    if np.any(near_pi):
        B = (R[near_pi] + np.eye(3)) / 2.0
        d = np.sqrt(np.clip(np.diagonal(B, axis1=-2, axis2=-1), 0.0, None))
        k = np.argmax(d, axis=-1)
        axis = B[np.arange(len(k)), k] / d[np.arange(len(k)), k][:, None]
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        out[near_pi] = axis * theta[near_pi][:, None]
    return out


def pose_residuals(T_query: F64, T_ref: F64, symmetries: F64) -> F64:
    """6-DoF differences (Q, R, 6) of query poses (Q, 4, 4) to reference poses (R, 4, 4).

    Each row is ``(p_q - p_r, log(R_r^T R_q S*))``: metres, then an axis-angle vector in
    radians, where ``S*`` is the box symmetry (``symmetries`` (S, 3, 3)) giving the
    smallest angle. These are the six "free variables" of paper 000 Eq. 2-3.
    """
    dp = T_query[:, None, :3, 3] - T_ref[None, :, :3, 3]
    rel = np.einsum("rji,qjk->qrik", T_ref[:, :3, :3], T_query[:, :3, :3])  # R_r^T R_q
    cand = np.einsum("qrij,sjk->qrsik", rel, symmetries)
    cos_t = (np.trace(cand, axis1=-2, axis2=-1) - 1.0) / 2.0
    best = np.argmax(cos_t, axis=-1)  # smallest angle
    q_idx, r_idx = np.indices(best.shape)
    chosen = cand[q_idx, r_idx, best]
    return np.concatenate([dp, _rotvec(chosen)], axis=-1)


def pairwise_angles(T: F64, symmetries: F64) -> F64:
    """Rotation angles (Z, Z) in radians between poses (Z, 4, 4), modulo the box symmetries."""
    rel = np.einsum("lji,kjm->klim", T[:, :3, :3], T[:, :3, :3])  # R_l^T R_k
    cand = np.einsum("klij,sjm->klsim", rel, symmetries)
    cos_t = np.clip((np.trace(cand, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.asarray(np.arccos(cos_t.max(axis=-1)), dtype=np.float64)


def project_box(
    T_world_object: F64,
    size: F64,
    T_world_camera: F64,
    camera: PinholeCamera,
    min_depth_m: float = 0.1,
    margin_px: float = 0.0,
) -> F64 | None:
    """Pixel box (4,) ``x1, y1, x2, y2`` of a 3D box seen from a camera, clipped to the image.

    Args:
        T_world_object: (4, 4) box pose (centre, axes) in ``world``.
        size: (3,) box extent along the object axes, metres.
        T_world_camera: (4, 4) camera pose in ``world`` (camera z forward).
        camera: the camera's intrinsics.
        min_depth_m: corners nearer than this (or behind the camera) are left out.
        margin_px: the image is grown by this many pixels on every side before clipping.

    Returns:
        The rectangle enclosing the projected corners in front of the camera, clipped to
        ``[-margin, W + margin] x [-margin, H + margin]``; None when no corner is in front
        or the clipped rectangle is empty.
    """
    half = np.asarray(size, dtype=np.float64) / 2.0
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    corners_obj = signs * half
    T_camera_object = inverse(T_world_camera) @ T_world_object
    corners_cam = corners_obj @ T_camera_object[:3, :3].T + T_camera_object[:3, 3]
    front = corners_cam[:, 2] > min_depth_m
    if not np.any(front):
        return None
    uv, _ = camera.project(corners_cam[front])
    m = margin_px
    x1 = float(np.clip(uv[:, 0].min(), -m, camera.width + m))
    x2 = float(np.clip(uv[:, 0].max(), -m, camera.width + m))
    y1 = float(np.clip(uv[:, 1].min(), -m, camera.height + m))
    y2 = float(np.clip(uv[:, 1].max(), -m, camera.height + m))
    if x2 <= x1 or y2 <= y1:
        return None
    return np.array([x1, y1, x2, y2])


def box_iou(a: F64, b: F64) -> float:
    """Intersection over union of two pixel boxes (4,) ``x1, y1, x2, y2``; 0 when disjoint."""
    iw = min(a[2], b[2]) - max(a[0], b[0])
    ih = min(a[3], b[3]) - max(a[1], b[1])
    if iw <= 0 or ih <= 0:
        return 0.0
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return float(inter / union) if union > 0 else 0.0


def is_truncated(box_xyxy: F64, camera: PinholeCamera, border_px: float) -> bool:
    """True when a pixel box (4,) reaches within ``border_px`` of the image border.

    Such a measurement sees only part of its object, so its centre is biased towards the
    visible part (``server/perception/measure.py``).
    """
    y1, y2 = float(box_xyxy[1]), float(box_xyxy[3])
    return cut_at_side(box_xyxy, camera, border_px) or y1 <= border_px or y2 >= camera.height - border_px


def cut_at_side(box_xyxy: F64, camera: PinholeCamera, border_px: float) -> bool:
    """True when a pixel box (4,) reaches within ``border_px`` of the left or right image border:
    the object may go on beyond the side of the view (the top and bottom borders cut most
    doors and most objects close by, and say less)."""
    x1, x2 = float(box_xyxy[0]), float(box_xyxy[2])
    return x1 <= border_px or x2 >= camera.width - border_px


def cut_at_top_or_bottom(box_xyxy: F64, camera: PinholeCamera, border_px: float) -> bool:
    """True when a pixel box (4,) reaches within ``border_px`` of the top or bottom image
    border: the object may go on above or below the view, so its measured height is a lower
    bound."""
    y1, y2 = float(box_xyxy[1]), float(box_xyxy[3])
    return y1 <= border_px or y2 >= camera.height - border_px


def world_extents(T_world_object: F64, size: F64) -> F64:
    """Extents (..., 3) along the world axes of boxes with poses (..., 4, 4) and sizes (..., 3), metres."""
    R_abs = np.abs(T_world_object[..., :3, :3])
    return np.asarray(np.einsum("...ij,...j->...i", R_abs, size), dtype=np.float64)


def partial_view_slack(residual_p: F64, extents_q: F64, extents_r: F64, factor: float,
                       class_extent: F64 | None = None, *, both_partial: bool = True) -> F64:
    """Position residuals (Q, R, 3) shrunk by the partial-view slack ``factor * |E_q - E_r| / 2`` per axis.

    A partly seen object is measured as a smaller box whose centre moves towards the seen
    part; if one view's box lies inside the other's, their centres differ by at most half
    the difference of their extents along each axis. Two full views of neighbouring
    identical objects have equal extents and keep their whole residual.

    With ``class_extent`` (3,), the largest world-axis extent an object of the class can
    have, extents are first clipped to it: a view larger than any object of its class (a
    mask that joined two chairs) holds more than one object and earns no more slack than a
    full view. With ``both_partial``, two views that are both partial (e.g. a bed seen
    through two doors) may then lie up to ``S - (E_q + E_r) / 2`` apart per axis, which is
    the larger slack when neither box contains the other; for two full views (``E = S``) it
    adds nothing.
    """
    if class_extent is not None:
        bound = np.asarray(class_extent, dtype=np.float64)
        extents_q, extents_r = np.minimum(extents_q, bound), np.minimum(extents_r, bound)
    slack = factor * np.abs(extents_q[:, None, :] - extents_r[None, :, :]) / 2.0
    if class_extent is not None and both_partial:
        both = bound[None, None, :] - (extents_q[:, None, :] + extents_r[None, :, :]) / 2.0
        slack = np.maximum(slack, factor * np.maximum(both, 0.0))
    return np.asarray(np.sign(residual_p) * np.maximum(np.abs(residual_p) - slack, 0.0), dtype=np.float64)

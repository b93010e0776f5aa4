"""Camera rotation between two frames from small blurry images (Klein and Murray, "Improving the
Agility of Keyframe-Based SLAM", ECCV 2008, Sec. 4).

A frame is shrunk to a thumbnail (``scale`` of its size, area-averaged), blurred and made zero
mean. Two thumbnails are aligned by a 2D Euclidean warp (in-plane rotation and shift: what a
camera turning about its centre mostly does to the image), found by OpenCV's ECC maximisation
(Evangelidis and Psarakis 2008) in place of the paper's ESM, starting from the warp of a given
guess rotation. The warp becomes a 3D rotation as the paper's SE(2) -> SO(3) step does: points
spread over the previous thumbnail and their warped images are turned into bearing vectors
through the camera, and the rotation that best maps the first onto the second is solved in
closed form (Kabsch). Translation and depth are left out: a prior for tracking under fast
rotation, where a constant-velocity model is off by tens of pixels, not a measurement.

Frames: ``R_cur_prev`` (3, 3) maps directions in the previous camera frame into the current one
(x right, y down, z forward); thumbnails are float32 (h, w).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.shared.camera import PinholeCamera

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

__all__ = ["SmallBlurryImage", "rotation_between"]

_GRID = 5  # bearing points per side of the thumbnail for the SE(2) -> SO(3) step
_ECC_ITERATIONS = 50
_ECC_EPS = 1e-4


class SmallBlurryImage:
    """Makes thumbnails of one camera's frames.

    Args:
        cam: the full-size camera (its intrinsics give the thumbnail's, scaled).
        scale: thumbnail size / image size (1/16: 40x30 from 640x480, PTAM's size).
        blur_px: Gaussian sigma in thumbnail pixels.
    """

    def __init__(self, cam: PinholeCamera, scale: float = 1 / 16, blur_px: float = 0.75) -> None:
        if not (0 < scale <= 1 and np.isfinite(blur_px) and blur_px >= 0):
            raise ValueError(f"small blurry image: need 0 < scale <= 1 and blur_px >= 0, "
                             f"got {scale}, {blur_px}")
        self.size = (max(8, round(cam.width * scale)), max(6, round(cam.height * scale)))
        sx, sy = self.size[0] / cam.width, self.size[1] / cam.height
        # Pixel centres: thumbnail pixel u covers image pixels [u / sx, (u + 1) / sx).
        self.K = np.array([[cam.fx * sx, 0.0, (cam.cx + 0.5) * sx - 0.5],
                           [0.0, cam.fy * sy, (cam.cy + 0.5) * sy - 0.5],
                           [0.0, 0.0, 1.0]])
        self._K_inv = np.linalg.inv(self.K)
        self.blur_px = blur_px
        u = np.linspace(0.1, 0.9, _GRID) * (self.size[0] - 1)
        v = np.linspace(0.1, 0.9, _GRID) * (self.size[1] - 1)
        uu, vv = np.meshgrid(u, v)
        self._grid = np.column_stack([uu.ravel(), vv.ravel(), np.ones(uu.size)])

    def make(self, gray: NDArray[np.uint8]) -> F32:
        """Thumbnail (h, w) of a grey image (H, W) of the camera's size."""
        small = np.asarray(cv2.resize(gray, self.size, interpolation=cv2.INTER_AREA), np.float32)
        if self.blur_px > 0:
            small = np.asarray(cv2.GaussianBlur(small, (0, 0), self.blur_px), np.float32)
        return np.asarray(small - small.mean(), np.float32)

    def warp_of(self, R_cur_prev: F64) -> F32:
        """The 2D Euclidean warp (2, 3) closest to what rotation ``R_cur_prev`` does to the grid."""
        prev = self._grid
        cur = (self.K @ R_cur_prev @ self._K_inv @ prev.T).T
        if np.any(cur[:, 2] <= 1e-6):
            return np.eye(2, 3, dtype=np.float32)
        cur = cur[:, :2] / cur[:, 2:]
        # Least-squares rotation + shift (Umeyama without scale) of the grid onto its image.
        p, c = prev[:, :2], cur
        pm, cm = p.mean(axis=0), c.mean(axis=0)
        U, _, Vt = np.linalg.svd((c - cm).T @ (p - pm))
        R2 = U @ np.diag([1.0, np.linalg.det(U @ Vt)]) @ Vt
        return np.column_stack([R2, cm - R2 @ pm]).astype(np.float32)

    def rotation_of(self, warp: F32) -> F64:
        """The rotation ``R_cur_prev`` whose bearings best match a warp (2, 3) of the grid (Kabsch)."""
        prev = self._grid
        cur = np.column_stack([(warp.astype(np.float64) @ prev.T).T, np.ones(len(prev))])
        bp = (self._K_inv @ prev.T).T
        bc = (self._K_inv @ cur.T).T
        bp /= np.linalg.norm(bp, axis=1, keepdims=True)
        bc /= np.linalg.norm(bc, axis=1, keepdims=True)
        U, _, Vt = np.linalg.svd(bc.T @ bp)
        return np.asarray(U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt)


def rotation_between(sbi: SmallBlurryImage, prev: F32, cur: F32, R_guess: F64) -> F64 | None:
    """``R_cur_prev`` (3, 3) aligning thumbnail ``cur`` with ``prev`` from the guess ``R_guess``
    (e.g. the motion model's); None when ECC does not converge."""
    warp = sbi.warp_of(R_guess)
    try:
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, _ECC_ITERATIONS, _ECC_EPS)
        # gaussFiltSize 1: the thumbnails are blurred already (the stubs lack this argument)
        _, warp = cv2.findTransformECC(prev, cur, warp, cv2.MOTION_EUCLIDEAN, criteria, None, 1)  # type: ignore[call-overload]
    except cv2.error:
        return None
    if not np.all(np.isfinite(warp)):
        return None
    return sbi.rotation_of(warp)

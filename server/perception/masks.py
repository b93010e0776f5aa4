"""Pixel-mask and depth-image geometry shared by instance splitting, the floor checks and
measurement.

- :func:`box_of_mask`: the pixel box of a mask;
- :func:`clipped_side`: which side border of the image a mask reaches;
- :func:`ring_around`: the pixels around a mask (its surroundings in the image);
- :func:`principal_direction` and :func:`densest_window`: a point set's main axis and its
  densest stretch along a line;
- :func:`fit_inverse_depth_plane`: a plane seen by a pinhole camera, fitted by RANSAC in
  inverse depth over the image.

Pixel boxes follow ``shared/detection.py``: ``(x1, y1, x2, y2)`` with the top-left image
corner at (0, 0), so a mask reaching the last column has ``x2 = W``.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from wardmap.shared.errors import GeometryError

__all__ = [
    "Mask",
    "box_of_mask",
    "clipped_side",
    "densest_window",
    "fit_inverse_depth_plane",
    "principal_direction",
    "ring_around",
]

Mask = NDArray[np.bool_]


def box_of_mask(mask: Mask) -> NDArray[np.float64]:
    """Pixel box (4,) float64 ``x1, y1, x2, y2`` enclosing a non-empty (H, W) bool mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        raise GeometryError("box_of_mask: the mask is empty")
    return np.array([cols[0], rows[0], cols[-1] + 1, rows[-1] + 1], dtype=np.float64)


def clipped_side(mask: Mask) -> int:
    """-1 when an (H, W) mask reaches the left image border only, +1 the right only, else 0
    (neither or both: the object's width is in view, or cannot be placed)."""
    left, right = bool(mask[:, 0].any()), bool(mask[:, -1].any())
    return -1 if left and not right else 1 if right and not left else 0


def ring_around(mask: Mask, ring_px: int) -> tuple[tuple[slice, slice], Mask, Mask] | None:
    """The surroundings of a non-empty mask: ``(window, mask[window], ring)``.

    ``window`` is the mask's bounding box grown to hold the ring; ``ring`` (in the window) is
    ``ring_px`` wide and starts 2 px outside the mask, past the mixed depth at its border.
    None for an empty mask.
    """
    h, w = mask.shape
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    pad = ring_px + 3
    window = np.s_[max(0, rows[0] - pad):min(h, rows[-1] + 1 + pad),
                   max(0, cols[0] - pad):min(w, cols[-1] + 1 + pad)]
    m = mask[window]
    m8 = m.astype(np.uint8)
    near = cv2.dilate(m8, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))).astype(bool)
    side = 2 * ring_px + 5
    far = cv2.dilate(m8, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (side, side))).astype(bool)
    return window, m, far & ~near


def principal_direction(xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """First principal axis (2,) (unit length) of points (N, 2)."""
    centred = xy - xy.mean(axis=0)
    _, vecs = np.linalg.eigh(centred.T @ centred)
    return np.asarray(vecs[:, -1], dtype=np.float64)


def densest_window(along: NDArray[np.float64], width: float) -> NDArray[np.bool_]:
    """Points (N,) of coordinates ``along`` (metres) inside the ``width``-wide interval that
    holds the most of them (the first such interval when several tie)."""
    x = np.sort(along)
    ends = np.searchsorted(x, x + width, side="right")  # window [x[i], x[i] + width]
    start = int(np.argmax(ends - np.arange(x.size)))
    return np.asarray((along >= x[start]) & (along <= x[start] + width), dtype=bool)


def fit_inverse_depth_plane(
    u: NDArray[np.float64], v: NDArray[np.float64], z: NDArray[np.float64], tol: NDArray[np.float64],
    rng: np.random.Generator, iterations: int,
) -> tuple[NDArray[np.float64] | None, Mask]:
    """RANSAC: coefficients ``(a, b, c)`` of ``1/z = a u + b v + c`` with the most inliers
    (``|z - z_plane| <= tol``), refined by least squares on them; None when no sample works.
    All ``iterations`` hypotheses are solved and scored at once."""
    n = u.size
    A = np.column_stack([u, v, np.ones(n)])
    w = 1.0 / z
    picks = np.stack([rng.choice(n, size=3, replace=False) for _ in range(iterations)])
    As, ws = A[picks], w[picks]  # (k, 3, 3), (k, 3)
    ok = np.abs(np.linalg.det(As)) > 1e-12
    if not ok.any():
        return None, np.zeros(n, dtype=bool)
    coefs = np.linalg.solve(As[ok], ws[ok][..., None])[..., 0]  # (k', 3)
    wp = coefs @ A.T  # (k', n)
    inl = (wp > 0) & (np.abs(1.0 / np.where(wp > 0, wp, 1.0) - z) <= tol)
    best = int(np.argmax(inl.sum(axis=1)))
    best_in = inl[best]
    if best_in.sum() < 3:
        return None, best_in
    coef = np.linalg.lstsq(A[best_in], w[best_in], rcond=None)[0]
    return coef, best_in

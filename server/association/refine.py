"""Landmark pose refinement, paper 000 Sec. III-B, Eq. 4-6.

The landmark takes the pose of the measurement whose average normalised angle and
distance difference to all other measurements of the landmark is smallest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wardmap.server.association.geometry import Symmetry, pairwise_angles, symmetry_rotations
from wardmap.shared.errors import GeometryError

__all__ = ["RefineConfig", "landmark_size", "pose_differences", "refine_index"]

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class RefineConfig:
    """Parameters of Eq. 4-6."""

    alpha: float = 0.4
    """Weight of the angle term in Eq. 6 (paper: 0.4)."""
    beta: float = 0.6
    """Weight of the distance term in Eq. 6 (paper: 0.6)."""
    max_angle_rad: float = math.pi / 4
    """A in Eq. 4: angle differences above it count as 1 (radians)."""
    max_distance_m: float = 0.5
    """B in Eq. 5: distance differences above it count as 1 (metres)."""
    symmetry: Symmetry = "quarter_turn"
    """Box symmetry about z when comparing orientations (a measurement's yaw is ambiguous)."""

    def __post_init__(self) -> None:
        if not (self.alpha >= 0 and self.beta >= 0 and self.alpha + self.beta > 0):
            raise ValueError("alpha and beta must be >= 0 and not both 0")
        if not (self.max_angle_rad > 0 and self.max_distance_m > 0):
            raise ValueError("max_angle_rad (A) and max_distance_m (B) must be > 0")


def pose_differences(T_world_object: F64, config: RefineConfig | None = None) -> F64:
    """Average pose difference ``f_{O_p}(L_k)`` (Z,) of each measurement pose (Eq. 6).

    Args:
        T_world_object: (Z, 4, 4) poses of the Z measurements of one landmark, ``world``.
        config: alpha, beta, A, B and the box symmetry.

    Returns:
        (Z,) values in [0, alpha + beta]:
        ``f_k = alpha * mean_{l != k} theta_bar_kl + beta * mean_{l != k} phi_bar_kl`` with
        ``theta_bar = min(theta / A, 1)`` (Eq. 4, theta the rotation angle between the two
        poses) and ``phi_bar = min(phi / B, 1)`` (Eq. 5, phi the distance between their
        centres). Zeros when Z == 1 (no other measurement).

    Raises:
        GeometryError: poses not of shape (Z, 4, 4) with Z >= 1.
    """
    cfg = config or RefineConfig()
    T = np.asarray(T_world_object, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] == 0:
        raise GeometryError(f"pose_differences: expected poses (Z, 4, 4) with Z >= 1, got {T.shape}")
    Z = T.shape[0]
    if Z == 1:
        return np.zeros(1)
    theta = pairwise_angles(T, symmetry_rotations(cfg.symmetry))
    p = T[:, :3, 3]
    phi = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
    theta_bar = np.minimum(theta / cfg.max_angle_rad, 1.0)  # Eq. 4
    phi_bar = np.minimum(phi / cfg.max_distance_m, 1.0)  # Eq. 5
    np.fill_diagonal(theta_bar, 0.0)
    np.fill_diagonal(phi_bar, 0.0)
    # Eq. 6: the sums over l in Z \ k divided by |Z| - 1.
    return np.asarray(
        cfg.alpha * theta_bar.sum(axis=1) / (Z - 1) + cfg.beta * phi_bar.sum(axis=1) / (Z - 1),
        dtype=np.float64,
    )


def refine_index(T_world_object: F64, config: RefineConfig | None = None) -> int:
    """Index of the measurement whose pose becomes the landmark's pose (argmin of Eq. 6).

    Ties go to the earliest measurement.
    """
    return int(np.argmin(pose_differences(T_world_object, config)))


def landmark_size(sizes: F64, percentile: float, full_extent: bool) -> F64:
    """A landmark's size (3,) from its measurements' sizes (N, 3), metres, each in its object
    frame (x the longer horizontal side, y the shorter, z the height; docs/perception.md).

    A view that sees less of an object measures it smaller, never larger: its legs only, a part
    behind a nearer object, a part cut by the image border. The height is therefore the
    ``percentile``-th percentile of the heights; the horizontal extents are too when
    ``full_extent`` (objects mostly seen in parts: beds, cabinets), and their median otherwise
    (a class whose masks spill onto the wall beside it, doors, would grow with every spill).
    ``percentile`` = 50 is the element-wise median of the paper's measurements.

    Raises:
        GeometryError: ``sizes`` is not (N, 3) with N >= 1.
    """
    s = np.asarray(sizes, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 3 or len(s) == 0:
        raise GeometryError(f"landmark_size: expected sizes (N >= 1, 3), got {s.shape}")
    size = np.median(s, axis=0)
    size[2] = np.percentile(s[:, 2], percentile)
    if full_extent:
        size[:2] = np.percentile(s[:, :2], percentile, axis=0)
    return np.asarray(size, dtype=np.float64)

"""Pose refinement, paper 000 Eq. 4-6, on hand-computed numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from factories import object_pose

from wardmap.server.association.refine import RefineConfig, landmark_size, pose_differences, refine_index
from wardmap.shared.errors import GeometryError


def test_eq_4_to_6_known_numbers() -> None:
    """Three poses at x = 0, 0.1, 0.3 m; the second turned 30 deg (A = 45 deg, B = 0.5 m).

    theta_bar: (0,1) = (1,2) = 2/3, (0,2) = 0; phi_bar: 0.2, 0.6, 0.4 for (0,1), (0,2), (1,2).
    f0 = 0.4 * (2/3) / 2 + 0.6 * 0.8 / 2 = 0.37333; f1 = 0.4 * (4/3) / 2 + 0.6 * 0.6 / 2 = 0.44667;
    f2 = 0.4 * (2/3) / 2 + 0.6 * 1.0 / 2 = 0.43333.
    """
    T = np.stack([object_pose(0, 0), object_pose(0.1, 0, yaw=math.radians(30)), object_pose(0.3, 0)])
    cfg = RefineConfig(alpha=0.4, beta=0.6, max_angle_rad=math.pi / 4, max_distance_m=0.5, symmetry="none")
    f = pose_differences(T, cfg)
    np.testing.assert_allclose(f, [0.373333333, 0.446666667, 0.433333333], atol=1e-9)
    assert refine_index(T, cfg) == 0


def test_normalised_differences_saturate_at_one() -> None:
    """Eq. 4-5: differences above A and B count as 1, so one far outlier cannot dominate."""
    T = np.stack([object_pose(0, 0), object_pose(0.05, 0), object_pose(100.0, 0, yaw=3.0)])
    cfg = RefineConfig(symmetry="none")
    f = pose_differences(T, cfg)
    assert f.max() <= cfg.alpha + cfg.beta + 1e-12
    np.testing.assert_allclose(f[2], cfg.alpha + cfg.beta)
    assert refine_index(T, cfg) in (0, 1)


def test_box_symmetry_ignores_quarter_turns() -> None:
    """With quarter-turn symmetry a 90 deg yaw flip is no angle difference."""
    T = np.stack([object_pose(0, 0), object_pose(0, 0, yaw=math.pi / 2)])
    np.testing.assert_allclose(pose_differences(T, RefineConfig(symmetry="quarter_turn")), [0, 0], atol=1e-7)
    assert pose_differences(T, RefineConfig(symmetry="none"))[0] == pytest.approx(0.4)


def test_single_measurement_and_bad_shapes() -> None:
    assert refine_index(object_pose(1, 2)[None]) == 0
    with pytest.raises(GeometryError):
        pose_differences(np.zeros((0, 4, 4)))
    with pytest.raises(ValueError):
        RefineConfig(alpha=0.0, beta=0.0)


def test_landmark_size_takes_the_percentile_where_views_only_see_less() -> None:
    """Heights: the 90th percentile; horizontal extents: the median, or the 90th percentile for
    a class mostly seen in parts; 50 is the element-wise median."""
    partial, whole = [0.6, 0.3, 1.2], [1.0, 0.5, 1.8]
    sizes = np.array([partial] * 8 + [whole] * 4)  # np.percentile(.., 90) of 12: index 9.9, a whole view
    np.testing.assert_allclose(landmark_size(sizes, 90.0, full_extent=False), [0.6, 0.3, 1.8])
    np.testing.assert_allclose(landmark_size(sizes, 90.0, full_extent=True), [1.0, 0.5, 1.8])
    np.testing.assert_allclose(landmark_size(sizes, 50.0, full_extent=True), np.median(sizes, axis=0))
    np.testing.assert_allclose(landmark_size(np.array([whole]), 90.0, full_extent=True), whole)
    with pytest.raises(GeometryError, match="expected sizes"):
        landmark_size(np.zeros((0, 3)), 90.0, full_extent=False)
    with pytest.raises(GeometryError, match="expected sizes"):
        landmark_size(np.zeros((4, 2)), 90.0, full_extent=False)

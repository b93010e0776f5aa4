"""Mask and depth-image geometry (``server/perception/masks.py``)."""

from __future__ import annotations

import numpy as np
import pytest

from wardmap.server.perception.masks import (
    box_of_mask,
    clipped_side,
    densest_window,
    fit_inverse_depth_plane,
    ring_around,
)
from wardmap.shared.errors import GeometryError


def test_densest_window() -> None:
    """The width-wide interval holding the most points; a sparse tail beyond it is left out."""
    rng = np.random.default_rng(5)
    dense = rng.uniform(0.0, 1.0, 900)
    tail = rng.uniform(1.0, 2.5, 60)
    keep = densest_window(np.r_[dense, tail], 1.2)
    assert keep[:900].all() and keep[900:].sum() < 20
    assert densest_window(np.array([0.0, 0.1, 5.0]), 1.0).tolist() == [True, True, False]
    assert densest_window(np.array([3.0]), 1.0).tolist() == [True]


def test_box_and_border_side_of_a_mask() -> None:
    """The box of a mask reaching the last column ends at x = W; a mask at one side border is
    cut there, at both or neither it is not; an empty mask has no box."""
    mask = np.zeros((30, 40), bool)
    mask[5:12, 30:40] = True
    np.testing.assert_array_equal(box_of_mask(mask), [30, 5, 40, 12])
    assert clipped_side(mask) == 1
    assert clipped_side(mask[:, ::-1]) == -1
    mask[20, 0] = True
    assert clipped_side(mask) == 0 and clipped_side(np.zeros((30, 40), bool)) == 0
    with pytest.raises(GeometryError, match="empty"):
        box_of_mask(np.zeros((30, 40), bool))


def test_ring_around_a_mask_starts_two_pixels_out() -> None:
    """The ring is ``ring_px`` wide, 2 px clear of the mask, inside a window holding both."""
    mask = np.zeros((60, 60), bool)
    mask[25:35, 25:35] = True
    window, m, ring = ring_around(mask, 5)
    assert np.array_equal(m, mask[window]) and not (ring & m).any()
    rows, cols = np.nonzero(ring)
    rows, cols = rows + window[0].start, cols + window[1].start
    gap = np.maximum(np.maximum(25 - rows, rows - 34), np.maximum(25 - cols, cols - 34))
    beside = (cols >= 25) & (cols <= 34)  # above and below the mask, away from its corners
    assert gap[beside].min() == 3 and gap[beside].max() == 7  # 2 px clear, then 5 px
    assert gap.min() >= 2 and gap.max() <= 8  # the round dilation cuts the corners
    assert ring_around(np.zeros((60, 60), bool), 5) is None


def test_a_plane_in_inverse_depth_is_found_among_outliers() -> None:
    """Pixels of a slanted plane (1/z affine in u, v) and 30 % random depths: RANSAC finds the
    plane's coefficients and marks the plane's pixels as inliers."""
    rng = np.random.default_rng(2)
    u, v = rng.uniform(0, 320, 500), rng.uniform(0, 240, 500)
    a, b, c = 4e-4, -2e-4, 0.3
    z = 1.0 / (a * u + b * v + c)
    outlier = rng.random(500) < 0.3
    z[outlier] = rng.uniform(1.0, 6.0, int(outlier.sum()))
    coef, inliers = fit_inverse_depth_plane(u, v, z, np.full(500, 0.01), rng, 48)
    assert coef is not None
    np.testing.assert_allclose(coef, [a, b, c], rtol=1e-3, atol=1e-7)
    assert inliers[~outlier].all() and inliers[outlier].mean() < 0.05

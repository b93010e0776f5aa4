"""Pose residuals modulo box symmetry, box projection, partial-view slack and the spatial grid."""

from __future__ import annotations

import math

import numpy as np
from factories import CAMERA, CHAIR_SIZE, camera_looking_along_y, object_pose

from wardmap.server.association.geometry import (
    box_iou,
    is_truncated,
    partial_view_slack,
    pose_residuals,
    project_box,
    symmetry_rotations,
    world_extents,
)
from wardmap.server.association.spatial import SpatialGrid


def test_residuals_respect_box_symmetry() -> None:
    """A 90 deg yaw flip is no rotation residual with quarter-turn symmetry, 90 deg without."""
    a, b = object_pose(1, 2, yaw=0.1)[None], object_pose(1.5, 2, yaw=0.1 + math.pi / 2)[None]
    r4 = pose_residuals(b, a, symmetry_rotations("quarter_turn"))[0, 0]
    r1 = pose_residuals(b, a, symmetry_rotations("none"))[0, 0]
    np.testing.assert_allclose(r4[:3], [0.5, 0, 0])
    np.testing.assert_allclose(r4[3:], 0, atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(r1[3:]), math.pi / 2)
    r2 = pose_residuals(object_pose(0, 0, yaw=0.3)[None], a, symmetry_rotations("none"))[0, 0]
    np.testing.assert_allclose(r2[3:], [0, 0, 0.2], atol=1e-9)


def test_project_box_of_an_object_ahead() -> None:
    """A chair 3 m straight ahead projects to a box centred on the principal point; behind: None."""
    T = camera_looking_along_y(0.0, z=0.465)
    box = project_box(object_pose(0, 3.0), CHAIR_SIZE, T, CAMERA)
    assert box is not None
    np.testing.assert_allclose([(box[0] + box[2]) / 2, (box[1] + box[3]) / 2], [319.5, 239.5], atol=1e-6)
    assert project_box(object_pose(0, -3.0), CHAIR_SIZE, T, CAMERA) is None
    assert not is_truncated(box, CAMERA, 3.0)
    side = project_box(object_pose(1.5, 2.0), CHAIR_SIZE, T, CAMERA)
    assert side is not None and is_truncated(side, CAMERA, 3.0)
    assert box_iou(box, box) == 1.0 and box_iou(box, box + np.array([1000.0, 0, 1000.0, 0])) == 0.0


def test_partial_view_slack() -> None:
    """Residual shrinks by half the extent difference; equal extents keep the full residual."""
    r = np.array([[[0.5, -0.3, 0.0]]])
    full = world_extents(object_pose(0, 0, yaw=math.pi / 2), np.array([2.0, 1.0, 1.0]))
    np.testing.assert_allclose(full, [1.0, 2.0, 1.0])
    part = np.array([0.2, 1.0, 1.0])
    np.testing.assert_allclose(partial_view_slack(r, part[None], full[None], 1.0), [[[0.1, 0.0, 0.0]]])
    np.testing.assert_allclose(partial_view_slack(r, full[None], full[None], 1.0), r)
    # With a class bound S = (2, 2, 1): two partial views (0.2 and 0.4 wide in x) of one object
    # may lie S - (0.2 + 0.4) / 2 = 1.7 m apart in x; views as large as the bound (y here) keep
    # their whole residual, smaller ones get the gap to the bound (x: 2 - 1 = 1 m).
    bound = np.array([2.0, 2.0, 1.0])
    far = np.array([[[1.8, 0.0, 0.0]]])
    a, b = np.array([0.2, 2.0, 1.0]), np.array([0.4, 2.0, 1.0])
    np.testing.assert_allclose(partial_view_slack(far, a[None], b[None], 1.0, bound), [[[0.1, 0.0, 0.0]]])
    np.testing.assert_allclose(partial_view_slack(r, full[None], full[None], 1.0, np.array([2.0, 2.0, 1.0])),
                               r - np.array([[[0.5, 0.0, 0.0]]]))
    # A view larger than the bound (one mask over two doors, 2.7 m wide) is clipped to it: a
    # single door 0.77 m to its side keeps all but (1.3 - 1.16) / 2 of the residual.
    door_bound = np.array([1.3, 1.3, 2.3])
    two, one = np.array([2.7, 0.06, 2.2]), np.array([1.16, 0.06, 2.2])
    side = np.array([[[0.77, 0.0, 0.0]]])
    np.testing.assert_allclose(partial_view_slack(side, one[None], two[None], 1.0), [[[0.0, 0.0, 0.0]]])
    np.testing.assert_allclose(partial_view_slack(side, one[None], two[None], 1.0, door_bound),
                               [[[0.70, 0.0, 0.0]]], atol=1e-9)


def test_grid_query_matches_brute_force() -> None:
    rng = np.random.default_rng(1)
    pts = rng.uniform(-10, 10, (300, 3))
    grid = SpatialGrid(1.5)
    for k, p in enumerate(pts):
        grid.put(k, p)
    grid.put(0, np.array([100.0, 0, 0]))  # move
    grid.remove(1)
    pts[0] = [100.0, 0, 0]
    for q in rng.uniform(-10, 10, (20, 3)):
        expect = sorted(k for k in range(300) if k != 1 and np.linalg.norm(pts[k] - q) <= 2.0)
        assert grid.query(q, 2.0) == expect
    assert len(grid) == 299

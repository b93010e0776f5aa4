"""SE3 and quaternion helpers: invariants on random transforms (seeded)."""

from __future__ import annotations

import numpy as np
import pytest

from wardmap.shared import se3
from wardmap.shared.errors import GeometryError


def _random_T(rng: np.random.Generator) -> np.ndarray:
    return se3.se3_exp(np.concatenate([rng.normal(0, 2, 3), rng.normal(0, 1, 3)]))


def test_inverse_composes_to_identity() -> None:
    """T_a_b @ T_b_a = I for 100 random rigid transforms."""
    rng = np.random.default_rng(0)
    for _ in range(100):
        T = _random_T(rng)
        assert np.allclose(T @ se3.inverse(T), np.eye(4), atol=1e-12)
        assert np.allclose(se3.inverse(T) @ T, np.eye(4), atol=1e-12)
    stack = np.stack([_random_T(rng) for _ in range(7)]).reshape(7, 4, 4)
    np.testing.assert_allclose(se3.inverse(stack), [se3.inverse(T) for T in stack], atol=0)  # batched = each


def test_composition_is_associative_and_maps_points_consistently() -> None:
    """(T_a_b T_b_c) p_c equals T_a_b (T_b_c p_c): the frame-naming convention holds."""
    rng = np.random.default_rng(1)
    T_ab, T_bc = _random_T(rng), _random_T(rng)
    p_c = rng.normal(size=(20, 3))
    direct = se3.transform_points(T_ab @ T_bc, p_c)
    chained = se3.transform_points(T_ab, se3.transform_points(T_bc, p_c))
    assert np.allclose(direct, chained)


def test_rigid_transforms_preserve_distances() -> None:
    """Pairwise point distances are unchanged by a rigid transform."""
    rng = np.random.default_rng(2)
    T = _random_T(rng)
    p = rng.normal(size=(30, 3))
    q = se3.transform_points(T, p)
    dp = np.linalg.norm(p[:, None] - p[None], axis=2)
    dq = np.linalg.norm(q[:, None] - q[None], axis=2)
    assert np.allclose(dp, dq)


def test_quaternion_round_trip_and_sign() -> None:
    """R -> q -> R is exact; q has unit norm and w >= 0 (covers all Shepperd branches)."""
    rng = np.random.default_rng(3)
    cases = [se3.so3_exp(rng.normal(size=3)) for _ in range(200)]
    cases += [se3.so3_exp(np.pi * np.eye(3)[k]) for k in range(3)]  # 180 deg turns
    for R in cases:
        q = se3.rotation_to_quat(R)
        assert np.isclose(np.linalg.norm(q), 1.0)
        assert q[3] >= 0
        assert np.allclose(se3.quat_to_rotation(q), R, atol=1e-9)


def test_tum_row_round_trip() -> None:
    """A pose written as a TUM row and read back is the same transform."""
    rng = np.random.default_rng(4)
    T = _random_T(rng)
    assert np.allclose(se3.transform_from_tum(se3.transform_to_tum(T)), T)


def test_exp_log_are_inverse() -> None:
    """se3_log(se3_exp(xi)) = xi for twists with angles below pi, including tiny ones."""
    rng = np.random.default_rng(5)
    for scale in (1e-10, 1e-4, 0.5, 2.5):
        for _ in range(20):
            xi = np.concatenate([rng.normal(0, 1, 3), rng.normal(0, 1, 3)])
            xi[3:] *= scale / max(np.linalg.norm(xi[3:]), 1e-12)
            assert np.allclose(se3.se3_log(se3.se3_exp(xi)), xi, atol=1e-8)


def test_so3_log_near_pi() -> None:
    """The rotation angle is recovered at (almost) 180 degrees."""
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    for ang in (np.pi - 1e-7, np.pi):
        w = se3.so3_log(se3.so3_exp(axis * ang))
        assert np.isclose(np.linalg.norm(w), ang, atol=1e-5)
        assert np.allclose(se3.so3_exp(w), se3.so3_exp(axis * ang), atol=1e-6)


def test_interpolation_endpoints_and_midpoint() -> None:
    """interpolate_transform hits both ends; the midpoint halves the relative motion."""
    rng = np.random.default_rng(6)
    A, B = _random_T(rng), _random_T(rng)
    assert np.allclose(se3.interpolate_transform(A, B, 0.0), A)
    assert np.allclose(se3.interpolate_transform(A, B, 1.0), B)
    M = se3.interpolate_transform(A, B, 0.5)
    ang_am = se3.rotation_angle(A[:3, :3].T @ M[:3, :3])
    ang_mb = se3.rotation_angle(M[:3, :3].T @ B[:3, :3])
    assert np.isclose(ang_am, ang_mb, atol=1e-9)


@pytest.mark.parametrize(
    "bad",
    [np.eye(3), np.full((4, 4), np.nan), np.diag([1.0, 1.0, -1.0, 1.0]), np.diag([2.0, 1.0, 1.0, 1.0])],
)
def test_check_transform_rejects_non_rigid(bad: np.ndarray) -> None:
    """Wrong shape, NaN, reflection and scaling are all rejected with GeometryError."""
    with pytest.raises(GeometryError):
        se3.check_transform(bad)


def test_zero_quaternion_is_rejected() -> None:
    """A zero quaternion has no rotation: GeometryError."""
    with pytest.raises(GeometryError, match="zero norm"):
        se3.quat_to_rotation([0, 0, 0, 0])


def test_hat_is_the_cross_product_for_one_vector_and_for_many() -> None:
    """``hat(a) @ b == cross(a, b)`` for a (3,) vector and row by row for (N, 3); other shapes
    are refused."""
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    assert se3.hat(a[0]).shape == (3, 3)
    np.testing.assert_allclose(se3.hat(a[0]) @ b[0], np.cross(a[0], b[0]), atol=1e-12)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", se3.hat(a), b), np.cross(a, b), atol=1e-12)
    with pytest.raises(GeometryError, match="3-vectors"):
        se3.hat(np.zeros(4))

"""``wardmap.shared.hamming``: the numba kNN over ORB descriptors equals a brute-force count."""

from __future__ import annotations

import numpy as np
import pytest

from wardmap.shared.hamming import knn2


def _brute(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(axis=2)


@pytest.mark.parametrize(("n", "m"), [(50, 70), (1, 1), (30, 2)])
def test_knn2_equals_brute_force(n: int, m: int) -> None:
    rng = np.random.default_rng(n * 100 + m)
    a = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (m, 32), dtype=np.uint8)
    b[: min(n, m) // 2] = a[: min(n, m) // 2] ^ 1  # a few near copies (distance 8)
    best, d1, d2, back = knn2(a, b)
    D = _brute(a, b)
    np.testing.assert_array_equal(best, D.argmin(axis=1))
    np.testing.assert_array_equal(d1, D.min(axis=1))
    if m >= 2:
        np.testing.assert_array_equal(d2, np.sort(D, axis=1)[:, 1])
    else:
        assert (d2 == 257).all()
    np.testing.assert_array_equal(back, D.argmin(axis=0))


def test_empty_and_bad_shapes() -> None:
    best, _, _, back = knn2(np.zeros((0, 32), np.uint8), np.zeros((3, 32), np.uint8))
    assert best.shape == (0,) and (back == -1).all()
    with pytest.raises(ValueError, match="32"):
        knn2(np.zeros((2, 16), np.uint8), np.zeros((2, 16), np.uint8))

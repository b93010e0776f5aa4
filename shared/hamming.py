"""Hamming distances between binary (ORB) descriptors, compiled with numba.

Both sides match 256-bit ORB descriptors: the edge against its local map, the server's
back-end between keyframes. Descriptors are (N, 32) uint8; viewed as (N, 4) uint64 words.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

__all__ = ["as_words", "knn2", "popcount64"]


@njit(cache=True, nogil=True, inline="always")
def popcount64(x: np.uint64) -> int:
    """Bits set in a 64-bit word (SWAR)."""
    x = x - ((x >> np.uint64(1)) & np.uint64(0x5555555555555555))
    x = (x & np.uint64(0x3333333333333333)) + ((x >> np.uint64(2)) & np.uint64(0x3333333333333333))
    x = (x + (x >> np.uint64(4))) & np.uint64(0x0F0F0F0F0F0F0F0F)
    return int((x * np.uint64(0x0101010101010101)) >> np.uint64(56))


def as_words(descriptors: NDArray[np.uint8]) -> NDArray[np.uint64]:
    """(N, 32) uint8 descriptors as (N, 4) uint64 words (a contiguous copy when needed)."""
    d = np.ascontiguousarray(descriptors, np.uint8)
    if d.ndim != 2 or d.shape[1] != 32:
        raise ValueError(f"descriptors must be (N, 32) uint8, got {d.shape}")
    return d.view(np.uint64)


@njit(cache=True, nogil=True)
def _knn2(a: NDArray[np.uint64], b: NDArray[np.uint64]) -> tuple[
        NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    n, m = a.shape[0], b.shape[0]
    best = np.full(n, -1, np.int64)
    d1 = np.full(n, 257, np.int64)
    d2 = np.full(n, 257, np.int64)
    col_best = np.full(m, -1, np.int64)
    col_d = np.full(m, 257, np.int64)
    for i in range(n):
        for j in range(m):
            s = 0
            for k in range(a.shape[1]):
                s += popcount64(a[i, k] ^ b[j, k])
            if s < d1[i]:
                d2[i] = d1[i]
                d1[i] = s
                best[i] = j
            elif s < d2[i]:
                d2[i] = s
            if s < col_d[j]:
                col_d[j] = s
                col_best[j] = i
    return best, d1, d2, col_best


def knn2(a: NDArray[np.uint8], b: NDArray[np.uint8]) -> tuple[
        NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """For each row of ``a`` (N, 32) uint8, its nearest row of ``b`` (M, 32) uint8 by Hamming
    distance: ``(best (N,) index into b or -1, its distance (N,), the second-best distance (N,),
    and for each row of b the index of its nearest row of a (M,) or -1)``; distances in bits,
    257 where there is no such row. Ties keep the lower index."""
    return _knn2(as_words(a), as_words(b))

"""A uniform grid over landmark positions: radius queries cost O(local density), not O(map size)."""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np
from numpy.typing import NDArray

__all__ = ["SpatialGrid"]

Cell = tuple[int, int, int]


class SpatialGrid:
    """Points with integer keys in a hash grid of cubic cells (side ``cell_m`` metres).

    A radius query visits the ``(2 ceil(r / cell) + 1)^3`` cells around the query point, so
    its cost depends on the number of points near the query, not on the total number.
    """

    def __init__(self, cell_m: float) -> None:
        if not cell_m > 0:
            raise ValueError(f"SpatialGrid: cell size must be > 0, got {cell_m}")
        self.cell_m = float(cell_m)
        self._cells: defaultdict[Cell, set[int]] = defaultdict(set)
        self._where: dict[int, tuple[Cell, NDArray[np.float64]]] = {}

    def __len__(self) -> int:
        return len(self._where)

    def _cell(self, p: NDArray[np.float64]) -> Cell:
        c = np.floor(p / self.cell_m).astype(np.int64)
        return int(c[0]), int(c[1]), int(c[2])

    def put(self, key: int, position: NDArray[np.float64]) -> None:
        """Insert ``key`` at ``position`` (3,) in metres, or move it there."""
        p = np.asarray(position, dtype=np.float64).reshape(3).copy()
        self.remove(key)
        cell = self._cell(p)
        self._cells[cell].add(key)
        self._where[key] = (cell, p)

    def remove(self, key: int) -> None:
        """Remove ``key`` if present."""
        old = self._where.pop(key, None)
        if old is not None:
            members = self._cells[old[0]]
            members.discard(key)
            if not members:
                del self._cells[old[0]]

    def query(self, position: NDArray[np.float64], radius_m: float) -> list[int]:
        """Keys within ``radius_m`` of ``position`` (3,), sorted by key."""
        p = np.asarray(position, dtype=np.float64).reshape(3)
        r = math.ceil(radius_m / self.cell_m)
        cx, cy, cz = self._cell(p)
        out = []
        for dx in range(-r, r + 1):
            for dy in range(-r, r + 1):
                for dz in range(-r, r + 1):
                    for key in self._cells.get((cx + dx, cy + dy, cz + dz), ()):
                        if float(np.linalg.norm(self._where[key][1] - p)) <= radius_m:
                            out.append(key)
        return sorted(out)

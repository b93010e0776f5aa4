"""Baselines behind the associator's method switch.

- ``per_keyframe_hdp`` (HDP-SLAM, paper 000 ref. [7]): every keyframe is its own group,
  every measurement its own word; the HDP likelihood is one Gaussian at the landmark's
  pose, which is the pose of its first measurement. :func:`per_keyframe_items` builds the
  words; the sampler is :func:`~wardmap.server.association.hdp.gibbs_associate` with
  ``likelihood="first_pose"``.
- ``nearest``: greedy nearest neighbour by class and distance: in each keyframe the
  closest (measurement, landmark) pair of the same class within a gate is matched first,
  one-to-one; unmatched measurements start landmarks. :func:`nearest_assign`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wardmap.server.association.hdp import HdpItem
from wardmap.server.association.mot import KeyframeView

__all__ = ["NearestConfig", "nearest_assign", "per_keyframe_items"]

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class NearestConfig:
    """Parameters of the ``nearest`` baseline."""

    max_distance_m: float = 0.5
    """Gate: a measurement joins a landmark only if their centres are this close (metres)."""

    def __post_init__(self) -> None:
        if not self.max_distance_m > 0:
            raise ValueError("nearest.max_distance_m must be > 0")


def per_keyframe_items(view: KeyframeView) -> list[HdpItem]:
    """One HDP word per measurement of one keyframe (HDP-SLAM's grouping)."""
    return [
        HdpItem(m.category, m.T_world_object[None].copy(), (view.index,), (mid,))
        for m, mid in zip(view.measurements, view.mids, strict=True)
    ]


def nearest_assign(
    categories: Sequence[str],
    positions: F64,
    landmarks: Sequence[tuple[int, str, F64]],
    config: NearestConfig | None = None,
) -> list[int | None]:
    """Greedy one-to-one matching of one keyframe's measurements to landmarks.

    Args:
        categories: (N,) class of each measurement.
        positions: (N, 3) measurement centres in ``world``, metres.
        landmarks: candidate landmarks as ``(id, class, centre (3,))``.
        config: the distance gate.

    Returns:
        For each measurement the landmark id it joins, or None (a new landmark).
    """
    cfg = config or NearestConfig()
    P = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    pairs: list[tuple[float, int, int]] = []
    for i, cat in enumerate(categories):
        for lid, lcat, centre in landmarks:
            if lcat != cat:
                continue
            d = float(np.linalg.norm(P[i] - centre))
            if d <= cfg.max_distance_m:
                pairs.append((d, i, lid))
    pairs.sort()
    out: list[int | None] = [None] * len(categories)
    used: set[int] = set()
    for _, i, lid in pairs:
        if out[i] is None and lid not in used:
            out[i] = lid
            used.add(lid)
    return out

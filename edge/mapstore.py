"""The tracker's local map: 3D points with descriptors, and recent keyframes.

One owner (the :class:`~wardmap.edge.tracker.Tracker`); plain arrays, no locks. Points
live in the tracker's world frame (metres). Positions are refined by averaging the
back-projected depth of later inlier observations (depth noise averages out).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass
class MapPoints:
    """Map points (M of them).

    Attributes:
        pos_world: (M, 3) float64 positions, metres, world frame.
        desc: (M, 32) uint8 ORB descriptors (from the creating observation).
        sem: (M, n, n) uint8 semantic descriptors (paper 001 Sec. 3.3) or None.
        weight: (M,) float64 sum of observation weights used in the position average.
        kf_last: (M,) int64 index of the last keyframe that observed the point.
        n_seen: (M,) int64 frames in which the point was an inlier.
        pid: (M,) int64 point ids, increasing, never reused within one map (the local
            bundle adjustment's keyframe observations name points by id).
        n_kf: (M,) int64 keyframes that observed the point (the one that made it included).
        kf_first: (M,) int64 index of the keyframe that made the point.
        next_pid: the id of the next point added.
    """

    pos_world: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    desc: NDArray[np.uint8] = field(default_factory=lambda: np.zeros((0, 32), np.uint8))
    sem: NDArray[np.uint8] | None = None
    weight: F64 = field(default_factory=lambda: np.zeros(0))
    kf_last: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    n_seen: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    pid: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    n_kf: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    kf_first: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    next_pid: int = 0

    def __len__(self) -> int:
        return int(self.pos_world.shape[0])

    def add(
        self, pos_world: F64, desc: NDArray[np.uint8], sem: NDArray[np.uint8] | None, weight: F64, kf: int
    ) -> None:
        n = pos_world.shape[0]
        if n == 0:
            return
        self.pos_world = np.concatenate([self.pos_world, pos_world])
        self.desc = np.concatenate([self.desc, desc])
        if sem is not None and (self.sem is not None or len(self) == n):
            self.sem = sem.copy() if self.sem is None else np.concatenate([self.sem, sem])
        elif self.sem is not None:
            size = self.sem.shape[1]
            self.sem = np.concatenate([self.sem, np.zeros((n, size, size), np.uint8)])
        self.weight = np.concatenate([self.weight, weight])
        self.kf_last = np.concatenate([self.kf_last, np.full(n, kf, np.int64)])
        self.n_seen = np.concatenate([self.n_seen, np.ones(n, np.int64)])
        self.pid = np.concatenate([self.pid, np.arange(self.next_pid, self.next_pid + n, dtype=np.int64)])
        self.n_kf = np.concatenate([self.n_kf, np.ones(n, np.int64)])
        self.kf_first = np.concatenate([self.kf_first, np.full(n, kf, np.int64)])
        self.next_pid += n

    def keep(self, mask: NDArray[np.bool_]) -> None:
        self.pos_world = self.pos_world[mask]
        self.desc = self.desc[mask]
        if self.sem is not None:
            self.sem = self.sem[mask]
        self.weight = self.weight[mask]
        self.kf_last = self.kf_last[mask]
        self.n_seen = self.n_seen[mask]
        self.pid = self.pid[mask]
        self.n_kf = self.n_kf[mask]
        self.kf_first = self.kf_first[mask]

    def fuse(self, idx: NDArray[np.intp], pos_world: F64, weight: F64, max_weight: float) -> None:
        """Weighted running average of positions for points ``idx`` with new estimates."""
        w0 = self.weight[idx]
        w = w0 + weight
        self.pos_world[idx] = (self.pos_world[idx] * w0[:, None] + pos_world * weight[:, None]) / w[:, None]
        self.weight[idx] = np.minimum(w, max_weight)


@dataclass(frozen=True)
class Keyframe:
    """A keyframe kept for relocalisation and for the wire.

    Attributes:
        index: keyframe number (0, 1, ...).
        frame_index: index of the frame in the input stream.
        stamp: seconds.
        T_world_camera: (4, 4) pose when the keyframe was made.
        desc: (K, 32) uint8 ORB descriptors of keypoints with depth.
        points_world: (K, 3) their positions, world frame.
        uv: (K, 2) their pixel coordinates.
    """

    index: int
    frame_index: int
    stamp: float
    T_world_camera: F64
    desc: NDArray[np.uint8]
    points_world: F64
    uv: NDArray[np.float32]

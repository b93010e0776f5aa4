"""Planar motion of robots and people: smooth paths through waypoints, timed.

A path is a polyline with circular fillets of radius ``turn_radius`` at its corners,
driven at ``speed`` with acceleration and yaw-rate limits (like a differential-drive
base). Times in seconds, positions in metres, yaw in radians about world +z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wardmap.shared.errors import SimulationError

F64 = NDArray[np.float64]
_STEP_M = 0.01


@dataclass(frozen=True)
class Track:
    """Densely sampled planar motion: time (N,), x (N,), y (N,), yaw (N,, unwrapped), arc length s (N,)."""

    t: F64
    x: F64
    y: F64
    yaw: F64
    s: F64

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def at(self, t: ArrayLike) -> tuple[F64, F64, F64, F64]:
        """``(x, y, yaw, s)`` at times ``t`` (clamped to the track's span)."""
        tt = np.clip(np.asarray(t, np.float64), self.t[0], self.t[-1])
        return (
            np.interp(tt, self.t, self.x),
            np.interp(tt, self.t, self.y),
            np.interp(tt, self.t, self.yaw),
            np.interp(tt, self.t, self.s),
        )


def _dense_path(waypoints: F64, radius: float) -> tuple[F64, F64]:
    """Points (N, 2) every ~1 cm along the filleted polyline, and heading (N,)."""
    pts: list[F64] = [waypoints[0][None, :]]
    cur = waypoints[0]
    for i in range(1, len(waypoints)):
        B = waypoints[i]
        if i == len(waypoints) - 1:
            seg_end, arc = B, None
        else:
            A, C = waypoints[i - 1], waypoints[i + 1]
            d1 = (B - A) / np.linalg.norm(B - A)
            d2 = (C - B) / np.linalg.norm(C - B)
            cross = d1[0] * d2[1] - d1[1] * d2[0]
            theta = float(np.arccos(np.clip(d1 @ d2, -1.0, 1.0)))
            if theta < 1e-6:
                seg_end, arc = B, None
            else:
                L = min(
                    radius * np.tan(theta / 2), 0.49 * np.linalg.norm(B - A), 0.49 * np.linalg.norm(C - B)
                )
                r = L / np.tan(theta / 2)
                seg_end = B - d1 * L
                normal = np.array([-d1[1], d1[0]]) * np.sign(cross)
                centre = seg_end + normal * r
                a0 = np.arctan2(seg_end[1] - centre[1], seg_end[0] - centre[0])
                n = max(2, int(np.ceil(r * theta / _STEP_M)))
                angles = a0 + np.sign(cross) * theta * np.arange(1, n + 1) / n
                arc = centre + r * np.column_stack([np.cos(angles), np.sin(angles)])
        n = max(1, int(np.ceil(np.linalg.norm(seg_end - cur) / _STEP_M)))
        f = np.arange(1, n + 1)[:, None] / n
        pts.append(cur + f * (seg_end - cur))
        cur = seg_end
        if arc is not None:
            pts.append(arc)
            cur = arc[-1]
    P = np.concatenate(pts)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(P, axis=0), axis=1) > 1e-9])
    P = P[keep]
    d = np.gradient(P, axis=0)
    yaw = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    return P, yaw


def plan_path(
    waypoints: ArrayLike,
    *,
    speed: float,
    turn_radius: float = 0.8,
    max_yaw_rate: float = 0.6,
    accel: float = 0.4,
    t0: float = 0.0,
) -> Track:
    """Time a smooth path through ``waypoints`` (K, 2), starting and ending at rest.

    Speed is limited by ``speed`` (m/s), by ``max_yaw_rate`` (rad/s) on curves and by
    ``accel`` (m/s^2) forward and backward along the path.
    """
    W = np.asarray(waypoints, np.float64)
    if W.ndim != 2 or W.shape[1] != 2 or len(W) < 2:
        raise SimulationError(f"waypoints: expected (K>=2, 2), got {W.shape}")
    if speed <= 0 or accel <= 0:
        raise SimulationError("speed and accel must be positive")
    P, yaw = _dense_path(W, turn_radius)
    ds = np.linalg.norm(np.diff(P, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(ds)])
    kappa = np.abs(np.gradient(yaw, s, edge_order=1))
    v = np.minimum(speed, max_yaw_rate / np.maximum(kappa, 1e-9))
    v = np.convolve(np.pad(v, 25, mode="edge"), np.ones(51) / 51, mode="valid")  # soften limits
    v[0] = v[-1] = 0.0
    for i in range(1, len(v)):  # forward pass: acceleration limit
        v[i] = min(v[i], np.sqrt(v[i - 1] ** 2 + 2 * accel * ds[i - 1]))
    for i in range(len(v) - 2, -1, -1):  # backward pass: deceleration limit
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * accel * ds[i]))
    v_mid = np.maximum((v[1:] + v[:-1]) / 2, 1e-3)
    t = t0 + np.concatenate([[0.0], np.cumsum(ds / v_mid)])
    return Track(t, P[:, 0].copy(), P[:, 1].copy(), yaw, s)


def hold(track: Track, until: float) -> Track:
    """The track extended by standing still at its end until time ``until``."""
    if until <= track.t[-1]:
        return track
    return Track(
        np.append(track.t, until),
        np.append(track.x, track.x[-1]),
        np.append(track.y, track.y[-1]),
        np.append(track.yaw, track.yaw[-1]),
        np.append(track.s, track.s[-1]),
    )


def concat(a: Track, b: Track, pause: float = 0.0) -> Track:
    """``a`` followed (after a pause in seconds) by ``b`` shifted in time and arc length."""
    shift = a.t[-1] + pause - b.t[0]
    yaw_b = b.yaw - np.round((b.yaw[0] - a.yaw[-1]) / (2 * np.pi)) * 2 * np.pi
    return Track(
        np.concatenate([a.t, b.t[1:] + shift]),
        np.concatenate([a.x, b.x[1:]]),
        np.concatenate([a.y, b.y[1:]]),
        np.concatenate([a.yaw, yaw_b[1:]]),
        np.concatenate([a.s, b.s[1:] + a.s[-1]]),
    )

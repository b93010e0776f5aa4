"""Things that move during a sequence: people, what they push, what they carry.

Each actor answers ``at(t)`` with its model parts and ``T_world_model`` at time ``t``
(seconds). People walk along a :class:`~wardmap.sim.motion.Track`; a pushed cart rides in
front of its pusher; a carried item sits in the carrier's hands until it is set down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from wardmap.shared.se3 import yaw_transform
from wardmap.sim import models
from wardmap.sim.geometry import Part
from wardmap.sim.motion import Track
from wardmap.sim.world import object_pose

F64 = NDArray[np.float64]
STRIDE_M = 1.4  # one gait cycle per 1.4 m walked


@dataclass(frozen=True)
class Walker:
    """A person walking along ``track``; ``role`` is staff, patient or visitor."""

    id: int
    track: Track
    outfit: str
    face: str
    hair: str
    role: str = "staff"
    height: float = 1.75
    arms_forward: bool = False
    cls: str = "person"

    def model_pose(self, t: float) -> F64:
        x, y, yaw, _ = self.track.at(t)
        return yaw_transform(float(x), float(y), float(yaw))

    def at(self, t: float) -> tuple[tuple[Part, ...], F64]:
        _, _, _, s = self.track.at(t)
        phase = 2 * np.pi * float(s) / STRIDE_M
        parts = models.person(
            self.outfit, self.face, self.hair, phase, height=self.height, arms_forward=self.arms_forward
        )
        return parts, self.model_pose(t)

    def object_pose(self, t: float) -> tuple[F64, F64]:
        """``(T_world_object, size)``: the standing pose's box, so the centre does not jitter."""
        parts = models.person(
            self.outfit, self.face, self.hair, 0.0, height=self.height, arms_forward=self.arms_forward
        )
        return object_pose(parts, self.model_pose(t))


@dataclass(frozen=True)
class Pushed:
    """An object pushed by ``pusher``, ``distance`` metres in front of the pusher's origin."""

    id: int
    cls: str
    parts: tuple[Part, ...]
    pusher: Walker
    distance: float = 0.75

    def at(self, t: float) -> tuple[tuple[Part, ...], F64]:
        return self.parts, self.pusher.model_pose(t) @ yaw_transform(self.distance, 0.0, 0.0)

    def object_pose(self, t: float) -> tuple[F64, F64]:
        return object_pose(*self.at(t))


@dataclass(frozen=True)
class Carried:
    """An item in ``carrier``'s hands until ``t_drop``; then it moves over ``drop_s`` to
    ``T_world_drop`` (a model pose, e.g. on a desk) and stays there."""

    id: int
    cls: str
    parts: tuple[Part, ...]
    carrier: Walker
    t_drop: float
    T_world_drop: F64
    drop_s: float = 0.6

    def _hand(self, t: float) -> F64:
        k = self.carrier.height / 1.75
        return self.carrier.model_pose(t) @ yaw_transform(0.45, -0.27, 0.0, 0.86 * k + 0.3)

    def at(self, t: float) -> tuple[tuple[Part, ...], F64]:
        if t <= self.t_drop:
            return self.parts, self._hand(t)
        if t >= self.t_drop + self.drop_s:
            return self.parts, self.T_world_drop
        a = (t - self.t_drop) / self.drop_s
        H = self._hand(self.t_drop)
        T = self.T_world_drop.copy()
        T[:3, 3] = (1 - a) * H[:3, 3] + a * self.T_world_drop[:3, 3]
        return self.parts, _blend_rot(H, T, a)

    def object_pose(self, t: float) -> tuple[F64, F64]:
        return object_pose(*self.at(t))


def _blend_rot(H: F64, T: F64, a: float) -> F64:
    """Pose with T's translation and the rotation of H (a <= 0.5) or T (a > 0.5)."""
    out = T.copy()
    if a <= 0.5:
        out[:3, :3] = H[:3, :3]
    return out


Actor = Walker | Pushed | Carried

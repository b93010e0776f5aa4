"""Landmark types handed out by the associator (paper 000 Sec. III).

Frames follow docs/ARCHITECTURE.md: ``T_world_object`` maps object-frame points to
``world`` (the frame of the keyframe poses: a robot session's odom frame on the live
server, the data set's ground-truth frame offline). Object frame: origin at the box
centre, z up, as :class:`~wardmap.server.perception.types.ObjectMeasurement`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from wardmap.server.perception.types import ObjectMeasurement

__all__ = ["Landmark", "LandmarkChange"]


@dataclass(frozen=True, eq=False)
class Landmark:
    """One object of the map: the measurements associated with it and its refined pose.

    Attributes:
        id: landmark id, unique within one :class:`~wardmap.server.association.associator.Associator`
            (ids start at 1 and are never reused).
        category: knowledge-graph class name: the class of its measurements; after a merge
            across classes (``AssociationConfig.merge_across``) the class most of them were
            measured as.
        T_world_object: (4, 4) float64 pose; for ``hierarchical`` the measurement pose
            chosen by paper 000 Eq. 4-6, for ``per_keyframe_hdp`` the first measurement's
            pose (HDP-SLAM), for ``nearest`` the pose of the measurement nearest the mean.
        size: (3,) float64 extent along the object's x, y, z in metres (from its recent
            measurements' sizes: :func:`~wardmap.server.association.refine.landmark_size`,
            ``AssociationConfig.size_percentile``; first measurement's for ``per_keyframe_hdp``).
        confidence: mean confidence of its measurements, in [0, 1].
        measurements: its measurements in the order they were associated (keyframe order);
            with ``AssociationConfig.keep_measurements`` off, only the most recent
            ``max_history`` of them.
        n_measurements: how many measurements it has had in all (0: ``len(measurements)``).
        confirmed: False while it is of a class of ``AssociationConfig.confirm_classes`` or
            ``min_width_m`` and no measurement associated with it shows such an object (every
            view a flat sliver cut by the side of the image, narrower than the class when
            whole, or wider than it; likely a wall or a door frame taken for an object): kept,
            but left out of the map's queries by default.
    """

    id: int
    category: str
    T_world_object: NDArray[np.float64]
    size: NDArray[np.float64]
    confidence: float
    measurements: tuple[ObjectMeasurement, ...]
    n_measurements: int = 0
    confirmed: bool = True

    def __post_init__(self) -> None:
        if self.n_measurements == 0:
            object.__setattr__(self, "n_measurements", len(self.measurements))

    @property
    def position(self) -> NDArray[np.float64]:
        """(3,) position of the object centre in ``world``, metres."""
        return np.asarray(self.T_world_object[:3, 3], dtype=np.float64)

    @property
    def gt_instances(self) -> list[int | None]:
        """Ground-truth instance id of each measurement (None where unknown)."""
        return [m.gt_instance for m in self.measurements]


@dataclass(frozen=True, eq=False)
class LandmarkChange:
    """What one :meth:`Associator.add_keyframe` or :meth:`Associator.flush` call did to one landmark.

    Attributes:
        kind: ``"created"`` (a new landmark), ``"updated"`` (new measurements, maybe a new
            pose) or ``"merged"`` (it was found to be part of landmark ``into``, which took all
            its measurements; it no longer exists).
        landmark: a snapshot of the landmark after the change (for ``merged``: its last state).
        added: the measurements that entered the map with this change: given to the
            associator in this call, or held by a landmark created in this call and merged
            into this one (``merged`` changes add none).
        into: for ``merged``: the id of the landmark that absorbed it (0 otherwise).
    """

    kind: Literal["created", "updated", "merged"]
    landmark: Landmark
    added: tuple[ObjectMeasurement, ...] = ()
    into: int = 0

"""Association scores against simulator ground truth (paper 000 Table II).

- Association accuracy: each landmark takes the ground-truth object most of its
  measurements belong to; accuracy = share of all measurements whose landmark's object is
  their own object. Measurements on no object (``gt_instance`` None) count as errors.
- Object count: the number of confirmed landmarks (:attr:`Landmark.confirmed`: what the
  map's queries return), against the ground-truth count = the number of distinct
  non-moving objects with at least one measurement. The accuracy scores every landmark,
  confirmed or not.
- Completeness (ours, not in the paper): each ground-truth object takes the landmark that
  holds most of its measurements; completeness = share of all measurements in their
  object's landmark. The accuracy is a clustering's purity and the completeness its
  inverse purity: a method that starts a new landmark whenever in doubt keeps its accuracy
  high and loses completeness (one object on two landmarks), and merging views of two
  objects costs accuracy. ``f_measure`` is their harmonic mean.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from wardmap.server.association.types import Landmark

__all__ = ["AssociationScore", "LandmarkError", "landmark_errors", "score_landmarks"]


@dataclass(frozen=True)
class AssociationScore:
    """Scores of one association run.

    Attributes:
        accuracy: share of measurements whose landmark's majority object is their own, in [0, 1].
        measurements: number of measurements scored.
        correct: number of correctly associated measurements.
        landmarks: number of confirmed landmarks (the map's objects).
        gt_objects: distinct non-moving ground-truth objects with at least one measurement.
        unconfirmed: number of landmarks not confirmed (not counted in ``landmarks``).
        completeness: share of measurements in the landmark that holds most of their
            object's measurements, in [0, 1] (measurements on no object count against it).
    """

    accuracy: float
    measurements: int
    correct: int
    landmarks: int
    gt_objects: int
    unconfirmed: int = 0
    completeness: float = 0.0

    @property
    def f_measure(self) -> float:
        """Harmonic mean of ``accuracy`` and ``completeness`` (0 when both are 0)."""
        total = self.accuracy + self.completeness
        return 2 * self.accuracy * self.completeness / total if total > 0 else 0.0


def score_landmarks(
    landmarks: Sequence[Landmark],
    gt_classes: Mapping[int, str] | None = None,
    moving_classes: Collection[str] = (),
) -> AssociationScore:
    """Score landmarks whose measurements carry ``gt_instance``.

    Args:
        landmarks: the associator's landmarks.
        gt_classes: ground-truth id -> class, to leave objects of ``moving_classes`` out of
            the ground-truth count (None: every measured id counts).
        moving_classes: classes that are not map objects (people).
    """
    total = correct = 0
    measured: set[int] = set()
    per_object: dict[int, Counter[int]] = {}  # object id -> landmark index -> measurements
    for k, lm in enumerate(landmarks):
        ids = lm.gt_instances
        votes = Counter(i for i in ids if i is not None)
        major = votes.most_common(1)[0][0] if votes else None
        for i in ids:
            total += 1
            if i is not None:
                measured.add(i)
                per_object.setdefault(i, Counter())[k] += 1
                if i == major:
                    correct += 1
    complete = sum(max(c.values()) for c in per_object.values())
    if gt_classes is not None:
        measured = {i for i in measured if gt_classes.get(i) not in moving_classes}
    unconfirmed = sum(not lm.confirmed for lm in landmarks)
    return AssociationScore(correct / total if total else 0.0, total, correct, len(landmarks) - unconfirmed,
                            len(measured), unconfirmed, complete / total if total else 0.0)


@dataclass(frozen=True)
class LandmarkError:
    """How far one landmark's geometry is from its object's.

    Attributes:
        category: the landmark's class.
        centre_m: distance from the landmark's centre to the object's, metres.
        size_m: (3,) landmark size minus object size, metres: longer horizontal side, shorter
            horizontal side, height (both sizes in their own object frames, z up).
    """

    category: str
    centre_m: float
    size_m: NDArray[np.float64]


def _sides(size: Any) -> NDArray[np.float64]:
    s = np.asarray(size, dtype=np.float64).reshape(3)
    return np.array([max(s[0], s[1]), min(s[0], s[1]), s[2]])


def landmark_errors(landmarks: Sequence[Landmark],
                    objects: Sequence[Mapping[str, Any]]) -> list[LandmarkError]:
    """Centre and size errors of the landmarks that stand for an object of their class.

    Args:
        landmarks: the associator's landmarks, measurements carrying ``gt_instance``.
        objects: ground-truth objects as in the simulator's ``objects.json`` (``id``,
            ``class``, ``T_world_object`` (4, 4), ``size`` (3,) metres).

    Returns:
        One entry per landmark whose majority object (as in :func:`score_landmarks`) is listed
        and of the landmark's class, in landmark order; the others (on no object, or on an object
        of another class) have no true geometry to compare with.
    """
    by_id = {int(o["id"]): o for o in objects}
    out = []
    for lm in landmarks:
        votes = Counter(i for i in lm.gt_instances if i is not None)
        if not votes:
            continue
        obj = by_id.get(votes.most_common(1)[0][0])
        if obj is None or obj["class"] != lm.category:
            continue
        T = np.asarray(obj["T_world_object"], dtype=np.float64)
        out.append(LandmarkError(lm.category, float(np.linalg.norm(lm.T_world_object[:3, 3] - T[:3, 3])),
                                 _sides(lm.size) - _sides(obj["size"])))
    return out

"""Association scores: accuracy (purity), completeness (inverse purity), F-measure, counts."""

from __future__ import annotations

import numpy as np
import pytest
from factories import CHAIR_SIZE, MeasurementFactory, camera_looking_along_y, object_pose

from wardmap.server.association.types import Landmark
from wardmap.tools.evaluate import AssociationScore, landmark_errors, score_landmarks


def _landmarks(make_measurement: MeasurementFactory, groups: list[list[int | None]]) -> list[Landmark]:
    """One landmark per list, holding one chair measurement per ground-truth id in it."""
    out = []
    for k, ids in enumerate(groups):
        ms = tuple(make_measurement(object_pose(0.0, 3.0), camera_looking_along_y(0.0), gt=i,
                                    keyframe=f"kf{j}") for j, i in enumerate(ids))
        out.append(Landmark(k + 1, "chair", object_pose(0.0, 3.0), CHAIR_SIZE.copy(), 1.0, ms))
    return out


def test_splitting_an_object_costs_completeness_and_joining_two_costs_accuracy(
        make_measurement: MeasurementFactory) -> None:
    """Objects 1 and 2, four measurements each. Right: both 1. One object split over three
    landmarks (2 + 1 + 1): accuracy still 1, completeness 6/8. Both objects on one landmark:
    accuracy 4/8 (the majority's share; a tie takes the object counted first), completeness 1.
    A measurement on no object is wrong for both."""
    right = score_landmarks(_landmarks(make_measurement, [[1, 1, 1, 1], [2, 2, 2, 2]]))
    assert (right.accuracy, right.completeness, right.f_measure) == (1.0, 1.0, 1.0)
    assert right.landmarks == right.gt_objects == 2
    split = score_landmarks(_landmarks(make_measurement, [[1, 1], [1], [1], [2, 2, 2, 2]]))
    assert split.accuracy == 1.0 and split.completeness == pytest.approx(6 / 8)
    assert split.f_measure == pytest.approx(2 * 0.75 / 1.75)
    assert split.landmarks == 4
    joined = score_landmarks(_landmarks(make_measurement, [[1, 1, 1, 1, 2, 2, 2, 2]]))
    assert joined.accuracy == pytest.approx(0.5) and joined.completeness == 1.0
    stray = score_landmarks(_landmarks(make_measurement, [[1, 1, 1, None], [2, 2, 2, 2]]))
    assert stray.accuracy == pytest.approx(7 / 8) and stray.completeness == pytest.approx(7 / 8)


def test_empty_scores_are_zero() -> None:
    """No landmarks: every share 0, and the F-measure of two zeros is 0, not a division error;
    accuracy 1 and completeness 0.5 give 2/3."""
    score = score_landmarks([])
    assert (score.accuracy, score.completeness, score.f_measure, score.measurements) == (0.0, 0.0, 0.0, 0)
    assert AssociationScore(0.0, 0, 0, 0, 0).f_measure == 0.0
    assert AssociationScore(1.0, 1, 1, 1, 1, 0, 0.5).f_measure == pytest.approx(2 / 3)


def test_landmark_errors_compare_each_landmark_with_its_majority_object(
        make_measurement: MeasurementFactory) -> None:
    """Landmark 1 (object 1, a chair 0.5 m away from it, sides given in the other order): centre
    0.5 m, size error per sorted side and height. Landmark 2 is on no object, landmark 3 on an
    object of another class: neither is scored."""
    lms = _landmarks(make_measurement, [[1, 1, 2], [None, None], [3]])
    objects = [{"id": i, "class": c, "T_world_object": object_pose(x, y).tolist(), "size": size}
               for i, c, x, y, size in ((1, "chair", 0.3, 3.4, [0.4, 0.5, 1.0]),
                                        (2, "chair", 5.0, 3.0, [0.5, 0.5, 1.0]),
                                        (3, "cart", 0.0, 3.0, [0.9, 0.5, 1.0]))]
    (err,) = landmark_errors(lms, objects)
    assert err.category == "chair" and err.centre_m == pytest.approx(0.5)
    np.testing.assert_allclose(err.size_m, CHAIR_SIZE[[0, 1, 2]] - np.array([0.5, 0.4, 1.0]))
    assert landmark_errors(lms, []) == []

"""In-group tracking: Hungarian assignment on distance, reprojected box overlap, class and appearance."""

from __future__ import annotations

import numpy as np
from factories import CAMERA, MeasurementFactory, camera_looking_along_y, object_pose

from wardmap.server.association.baselines import nearest_assign
from wardmap.server.association.mot import KeyframeView, MotConfig, appearance_similarity, track_group


def _view(index: int, T_wc: np.ndarray, ms: list, first_mid: int) -> KeyframeView:
    return KeyframeView(index, T_wc, CAMERA, tuple(ms), tuple(range(first_mid, first_mid + len(ms))))


def test_two_identical_chairs_side_by_side_stay_two(make_measurement: MeasurementFactory) -> None:
    """Chairs A (x = 0) and B (x = 0.55) 3 m ahead; in keyframe 1 both are measured biased to +x
    (A at 0.30, B at 0.83) so that B's track is nearer to A's measurement. A greedy nearest
    match takes that pair first and loses B; the joint (Hungarian) assignment keeps both."""
    A, B = object_pose(0.0, 3.0), object_pose(0.55, 3.0)
    T0, T1 = camera_looking_along_y(0.2), camera_looking_along_y(0.3)
    kf0 = [make_measurement(A, T0, gt=1), make_measurement(B, T0, gt=2)]
    kf1 = [make_measurement(A, T1, gt=1, offset=(0.30, 0, 0)),
           make_measurement(B, T1, gt=2, offset=(0.28, 0, 0))]
    lms = track_group([_view(0, T0, kf0, 0), _view(1, T1, kf1, 2)], MotConfig())
    assert len(lms) == 2
    assert sorted([m.gt_instance for m in lm.measurements] for lm in lms) == [[1, 1], [2, 2]]
    assert sorted(lm.mids for lm in lms) == [[0, 2], [1, 3]]
    # The greedy baseline on the same numbers takes the wrong pair first (B's track, A's measurement).
    tracks = [(1, "chair", np.array([0.0, 3, 0.465])), (2, "chair", np.array([0.55, 3, 0.465]))]
    greedy = nearest_assign(["chair", "chair"], np.array([[0.30, 3, 0.465], [0.83, 3, 0.465]]), tracks)
    assert greedy[0] == 2


def test_a_row_of_chairs_over_a_group(make_measurement: MeasurementFactory) -> None:
    """Five identical chairs 0.55 m apart, camera sliding sideways over 6 keyframes, 5 cm noise:
    five tracks, each holding only its own chair."""
    rng = np.random.default_rng(3)
    chairs = [object_pose(0.55 * k, 3.5) for k in range(5)]
    views, mid = [], 0
    for i in range(6):
        T = camera_looking_along_y(0.2 * i + 0.6)
        ms = [make_measurement(c, T, gt=k + 1, offset=tuple(rng.normal(0, 0.05, 3)))
              for k, c in enumerate(chairs)]
        views.append(_view(i, T, ms, mid))
        mid += len(ms)
    lms = track_group(views)
    assert len(lms) == 5
    for lm in lms:
        assert len({m.gt_instance for m in lm.measurements}) == 1
        assert lm.keyframes == list(range(6))


def test_class_disagreement_is_forbidden(make_measurement: MeasurementFactory) -> None:
    """A chair followed by a cart at the same place: two tracks, never one."""
    T = camera_looking_along_y(0.0)
    P = object_pose(0.0, 3.0)
    lms = track_group([_view(0, T, [make_measurement(P, T)], 0),
                       _view(1, T, [make_measurement(P, T, category="cart")], 1)])
    assert [lm.category for lm in lms] == ["chair", "cart"]


def test_distance_gate(make_measurement: MeasurementFactory) -> None:
    """A same-class measurement 1 m away (both fully in view) starts a new track."""
    T = camera_looking_along_y(0.0)
    lms = track_group([_view(0, T, [make_measurement(object_pose(-0.5, 4.0), T)], 0),
                       _view(1, T, [make_measurement(object_pose(0.5, 4.0), T)], 1)])
    assert len(lms) == 2


def test_appearance_similarity_bounds(make_measurement: MeasurementFactory) -> None:
    import dataclasses

    T = camera_looking_along_y(0.0)
    a = make_measurement(object_pose(0, 3), T)
    b = dataclasses.replace(a, color_hist=np.eye(8, dtype=np.float32)[0])
    assert appearance_similarity(a, a) == 1.0
    assert appearance_similarity(a, b) == 0.125
    rng = np.random.default_rng(0)
    d = rng.integers(0, 256, (40, 32), dtype=np.uint8)
    with_desc = dataclasses.replace(a, descriptors=d)
    assert appearance_similarity(with_desc, with_desc) == 1.0


def test_a_door_cut_by_the_border_is_gated_as_a_whole_view(make_measurement: MeasurementFactory) -> None:
    """A door cut by the left image border, then a door 0.6 m to its right, whole: within the
    partial-view gate (0.8 m) they share a track; for a class the perception completes beyond the
    border (``completed_when_cut``) the whole-view gate (0.45 m) holds and they stay two."""
    T = camera_looking_along_y(0.0)
    door = np.array([0.06, 1.16, 2.18])
    cut = make_measurement(object_pose(-2.4, 4.0, 1.09, np.pi / 2), T, category="door", size=door, gt=1)
    whole = make_measurement(object_pose(-1.8, 4.0, 1.09, np.pi / 2), T, category="door", size=door, gt=2,
                             keyframe="kf1")
    assert cut.box_xyxy[0] <= 0.0 < whole.box_xyxy[0]
    views = [_view(0, T, [cut], 0), _view(1, T, [whole], 1)]
    assert len(track_group(views, MotConfig())) == 1
    assert len(track_group(views, MotConfig(), completed_when_cut=("door",))) == 2
    assert len(track_group(views, MotConfig(), completed_when_cut=("chair",))) == 1

"""Back-end scores (tools/backend_eval.py) on synthetic trajectories with known answers."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from factories import MeasurementFactory

from wardmap.server.association.types import Landmark
from wardmap.shared.errors import WardmapError
from wardmap.shared.se3 import inverse, se3_exp, yaw_transform
from wardmap.tools.backend_eval import (
    RevisitEvent,
    alignment_error,
    check_closure,
    duplicated_objects,
    fit_pairs,
    fit_to_world,
    fitted_alignment_error,
    frame_rmse,
    majority_object,
    map_ate,
    pair_landmarks,
    pose_error,
    pose_graph_floor,
    recalled,
    revisit_events,
    same_place_errors,
    trajectory_ate,
)


def circle(n: int, *, radius: float = 5.0, step_s: float = 1.0, speed: float = 0.5, t0: float = 0.0,
           phase: float = 0.0) -> tuple[list[float], list[np.ndarray]]:
    """Keyframes every ``step_s`` on a circle driven counter-clockwise at ``speed``, looking ahead."""
    stamps, poses = [], []
    for i in range(n):
        a = phase + speed * step_s * i / radius
        stamps.append(t0 + step_s * i)
        poses.append(yaw_transform(radius * math.cos(a), radius * math.sin(a), a + math.pi / 2))
    return stamps, poses


def test_pose_error_is_the_relative_translation_and_angle() -> None:
    """0.3 m along x and 10 deg about z between two poses."""
    ref = se3_exp(np.array([0.1, -0.2, 0.3, 1.0, 2.0, 3.0]))
    est = ref @ yaw_transform(0.3, 0.0, math.radians(10.0))
    m, deg = pose_error(est, ref)
    assert m == pytest.approx(0.3) and deg == pytest.approx(10.0)
    assert pose_error(ref, ref) == pytest.approx((0.0, 0.0), abs=1e-7)


def test_a_closure_to_a_twin_is_false() -> None:
    """A loop edge measured at the right place is true; one that put keyframe b at the identical
    twin door 1.24 m to the side is false."""
    Ta = yaw_transform(2.0, 1.5, 0.0)
    Tb = yaw_transform(5.0, 1.5, 0.05)
    T_a_b = inverse(Ta) @ Tb
    good = check_closure(("r", "s", 9), ("r", "s", 1), T_a_b @ yaw_transform(0.01, 0.0, 0.002), Ta, Tb)
    assert good.true and good.error_m == pytest.approx(0.01, abs=1e-9)
    twin = check_closure(("r", "s", 9), ("r", "s", 1), T_a_b @ yaw_transform(0.0, 1.24, 0.0), Ta, Tb)
    assert not twin.true and twin.error_m == pytest.approx(1.24)


def test_revisits_of_one_session_need_thirty_seconds() -> None:
    """A 31.4 m circle at 0.5 m/s, 10 keyframes past the start: one event, starting at the first
    keyframe back within 1 m of the start; the first half minute revisits nothing (it is the
    recent past)."""
    stamps, poses = circle(73)
    keys = [("r", "s", i) for i in range(73)]
    events = revisit_events(keys, stamps, poses)
    assert len(events) == 1
    first = events[0].first[2]
    assert 60 <= first <= 63 and events[0].keys[-1] == keys[-1]
    assert all(e.first[2] > 30 for e in events)


def test_another_sessions_past_counts_at_once() -> None:
    """A second session starting on the first one's path revisits from its first keyframe; one
    driving the circle the other way round (views 180 deg apart) does not revisit."""
    s1, p1 = circle(40)
    s2, p2 = circle(10, t0=5.0, phase=0.5)
    keys = [("r", "a", i) for i in range(40)] + [("r", "b", i) for i in range(10)]
    events = revisit_events(keys, s1 + s2, p1 + p2)
    assert [e.first for e in events] == [("r", "b", 0)]
    back = [T @ yaw_transform(0.0, 0.0, math.pi) for T in p2]
    assert revisit_events(keys, s1 + s2, p1 + back) == []


def test_short_gaps_join_and_short_runs_do_not_count() -> None:
    """Two revisiting runs 2 keyframes apart are one event; a run of 2 keyframes is none."""
    s1, p1 = circle(20)
    far = yaw_transform(100.0, 100.0, 0.0)
    p2 = [p1[i] for i in range(5)] + [far, far] + [p1[i] for i in range(8, 12)] + [far] * 6 + p1[:2]
    s2 = [100.0 + i for i in range(len(p2))]
    keys = [("r", "a", i) for i in range(20)] + [("r", "b", i) for i in range(len(p2))]
    events = revisit_events(keys, s1 + s2, p1 + p2)
    assert len(events) == 1
    assert [k[2] for k in events[0].keys] == list(range(11))


def test_recall_window() -> None:
    """A closure counts for an event only from its first ``window`` keyframes."""
    event = RevisitEvent(tuple(("r", "s", i) for i in range(20, 40)))
    assert recalled(event, {("r", "s", 25)}, window=10)
    assert not recalled(event, {("r", "s", 31)}, window=10)
    assert not recalled(event, set())


def test_alignment_error_ignores_the_map_gauge() -> None:
    """The map frame is any rigid motion G of the world: the relative alignment of two sessions
    is unaffected; an error of robot 1's T_map_odom by 2 cm and 0.5 deg is reported as such."""
    rng = np.random.default_rng(3)
    W0, W1 = se3_exp(rng.normal(size=6)), se3_exp(rng.normal(size=6))
    G = se3_exp(rng.normal(size=6))
    assert alignment_error(G @ W1, G @ W0, W1, W0) == pytest.approx((0.0, 0.0), abs=1e-6)
    off = yaw_transform(0.02, 0.0, math.radians(0.5))
    m, deg = alignment_error(G @ W1 @ off, G @ W0, W1, W0)
    assert m == pytest.approx(0.02) and deg == pytest.approx(0.5)


def test_frame_rmse_does_not_align() -> None:
    """Cameras in a frame placed at its true place have no error; the frame 2 cm off gives 2 cm."""
    _, truth = circle(20)
    G = se3_exp(np.array([0.0, 0.0, 1.0, 4.0, -2.0, 0.5]))
    in_frame = [inverse(G) @ T for T in truth]
    assert frame_rmse(G, in_frame, truth) == pytest.approx(0.0, abs=1e-9)
    assert frame_rmse(G @ yaw_transform(0.0, 0.02, 0.0), in_frame, truth) == pytest.approx(0.02)


def test_ate_aligns_a_rigidly_moved_trajectory() -> None:
    """The estimate in another frame (a rigid motion of the truth) has no ATE; 3 cm of noise does."""
    stamps, truth = circle(40)
    G = se3_exp(np.array([0.0, 0.0, 1.0, 4.0, -2.0, 0.5]))
    assert trajectory_ate(stamps, [G @ T for T in truth], truth) == pytest.approx(0.0, abs=1e-6)
    rng = np.random.default_rng(0)
    noisy = [T @ yaw_transform(*rng.normal(0, 0.03, 2), 0.0) for T in truth]
    assert 0.02 < trajectory_ate(stamps, noisy, truth) < 0.06


def landmark(make: MeasurementFactory, lid: int, category: str, x: float, y: float, gts: list[int | None],
             confirmed: bool = True) -> Landmark:
    """A landmark at (x, y, 0.5) whose measurements are on the ground-truth objects ``gts``."""
    T = yaw_transform(x, y, 0.0, 0.5)
    cam = yaw_transform(x - 3.0, y, 0.0, 1.0) @ np.array(
        [[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]], float)  # looking along +x
    ms = tuple(make(T, cam, category=category, gt=g) for g in gts)
    return Landmark(lid, category, T, np.array([0.5, 0.5, 0.9]), 1.0, ms, confirmed=confirmed)


def test_landmarks_pair_by_category_and_nearest_centre(make_measurement: MeasurementFactory) -> None:
    """Two chairs and a door in map a; map b has the chairs 3 cm and 8 cm off, a bed where the door
    was, and an unconfirmed chair: the chairs pair with their nearest partners, nothing else."""
    m = make_measurement
    a = [landmark(m, 1, "chair", 0.0, 0.0, [5]), landmark(m, 2, "chair", 0.6, 0.0, [6]),
         landmark(m, 3, "door", 4.0, 0.0, [7])]
    b = [landmark(m, 11, "chair", 0.63, 0.0, [6]), landmark(m, 12, "chair", 0.08, 0.0, [5]),
         landmark(m, 13, "bed", 4.0, 0.0, [8]), landmark(m, 14, "chair", 0.3, 0.0, [5], confirmed=False)]
    pairs = pair_landmarks(a, b)
    assert sorted((p.a.id, p.b.id) for p in pairs) == [(1, 12), (2, 11)]
    assert sorted(round(p.offset_m, 6) for p in pairs) == [0.03, 0.08]
    assert pair_landmarks(a, b, max_m=0.05)[0].b.id == 11


def test_paired_landmarks_fit_one_map_onto_the_other(make_measurement: MeasurementFactory) -> None:
    """Map b is map a turned by 1 deg and shifted 5 cm: the fit of the pairs undoes it; fewer
    than three pairs leave the identity."""
    m = make_measurement
    spots = [(0.0, 0.0), (5.0, 0.0), (5.0, 4.0), (0.0, 6.0)]
    a = [landmark(m, i, "chair", x, y, [i]) for i, (x, y) in enumerate(spots)]
    D = yaw_transform(0.05, -0.02, math.radians(1.0))
    b = [landmark(m, 10 + i, "chair", *(D @ np.array([x, y, 0.5, 1.0]))[:2], [i])
         for i, (x, y) in enumerate(spots)]
    pairs = pair_landmarks(a, b)
    assert len(pairs) == 4 and max(p.offset_m for p in pairs) > 0.05
    np.testing.assert_allclose(fit_pairs(pairs), inverse(D), atol=1e-9)
    np.testing.assert_array_equal(fit_pairs(pairs[:2]), np.eye(4))


def test_duplicated_objects_count_confirmed_landmarks(make_measurement: MeasurementFactory) -> None:
    """Object 5 is the majority object of two confirmed landmarks (a duplicate); object 6 of one
    confirmed and one unconfirmed landmark (no duplicate)."""
    lms = [landmark(make_measurement, 1, "chair", 0.0, 0.0, [5, 5, 6]),
           landmark(make_measurement, 2, "chair", 1.0, 0.0, [5, None]),
           landmark(make_measurement, 3, "chair", 2.0, 0.0, [6]),
           landmark(make_measurement, 4, "chair", 3.0, 0.0, [6], confirmed=False)]
    assert majority_object(lms[0]) == 5
    assert majority_object(landmark(make_measurement, 9, "chair", 0.0, 0.0, [None])) is None
    assert duplicated_objects(lms) == {5: 2}


def test_same_place_errors_measure_how_two_sessions_disagree_where_they_overlap() -> None:
    _, poses = circle(20)
    keys = [("a", "s", i) for i in range(20)] + [("b", "s", i) for i in range(20)]
    truth = poses + poses
    shift = yaw_transform(0.03, 0.04, 0.0)  # session b's estimates 5 cm off, rotation-free
    estimates = poses + [shift @ T for T in poses]
    errors = same_place_errors(keys, truth, estimates, ("b", "s"))
    assert len(errors) == 20
    assert all(abs(m - 0.05) < 1e-9 and deg < 1e-6 for m, deg in errors)
    assert all(m < 1e-9 for m, _ in same_place_errors(keys, truth, poses + poses, ("b", "s")))
    # a session alone has nothing to agree with
    assert same_place_errors(keys[:20], truth[:20], estimates[:20], ("a", "s")) == []


def test_the_pose_graph_floor_removes_drift_where_the_session_revisits() -> None:
    from wardmap.server.backend.graph import GraphConfig

    stamps, truth = circle(126, step_s=1.0, speed=0.5)  # two laps of a 5 m circle, 63 s each
    bias = se3_exp(np.array([0.0, 0.0, math.radians(0.3), 0.0, 0.0, 0.0]))  # heading drift per step
    odom = [truth[0]]
    for a, b in itertools.pairwise(truth):
        odom.append(odom[-1] @ inverse(a) @ b @ bias)
    keys = [("r", "s", i) for i in range(len(truth))]
    floor = pose_graph_floor(keys, stamps, odom, ["rgb"] * len(keys), truth, GraphConfig())
    est = floor[("r", "s")]
    assert est.shape == (126, 4, 4)
    drifted = trajectory_ate(stamps, odom, truth)
    assert trajectory_ate(stamps, list(est), truth) < 0.3 * drifted


def test_fitted_alignment_is_the_placement_of_whole_trajectories() -> None:
    """Two sessions in one map: the error is how differently their own best fits place them,
    not their shape (a bent trajectory placed right scores 0), and a map rotated as a whole is
    no error; one session rotated against the other by 0.5 deg is."""
    _, ref_truth = circle(40)
    _, truth = circle(30, radius=3.0, phase=1.0)
    W = se3_exp(np.array([0.0, 0.0, 0.3, 4.0, -2.0, 0.1]))  # the map in the world, arbitrary
    est_ref = [inverse(W) @ T for T in ref_truth]
    est = [inverse(W) @ T for T in truth]
    Wr, Ws = fit_to_world(est_ref, ref_truth, rotation="orientations"), fit_to_world(est, truth)
    np.testing.assert_allclose(Wr, W, atol=1e-9)
    np.testing.assert_allclose(Ws, W, atol=1e-9)
    m, deg = fitted_alignment_error(Ws, Wr, est)
    assert m < 1e-9 and deg < 1e-6
    assert map_ate(est_ref + est, ref_truth + truth) < 1e-9
    # session s misplaced by a 0.5 deg turn about its own first camera
    turn = yaw_transform(0.0, 0.0, math.radians(0.5))
    P = est[0] @ turn @ inverse(est[0])
    bad = [P @ T for T in est]
    m, deg = fitted_alignment_error(fit_to_world(bad, truth, rotation="orientations"), Wr, bad)
    spread = np.sqrt(np.mean([np.sum((T[:3, 3] - est[0][:3, 3]) ** 2) for T in est]))
    assert deg == pytest.approx(0.5, abs=1e-6)
    assert m == pytest.approx(spread * math.radians(0.5), rel=0.01)
    assert map_ate(est_ref + bad, ref_truth + truth) > 0.2 * m
    # a bend inside a session (shape error) with the same placement: ATE, not misalignment
    bent = [T.copy() for T in est]
    for i, T in enumerate(bent):
        T[2, 3] += 0.01 * math.sin(i)
    m, deg = fitted_alignment_error(fit_to_world(bent, truth, rotation="orientations"), Wr, bent)
    assert m < 0.002 and deg < 0.1
    # a camera turning on the spot: positions say nothing of the rotation, orientations do
    spin = [yaw_transform(0.0, 0.0, 0.05 * i) @ se3_exp(np.array([0, 0, 0, 1e-4 * (i % 2), 0, 0]))
            for i in range(20)]
    np.testing.assert_allclose(fit_to_world([inverse(W) @ T for T in spin], spin, rotation="orientations"),
                               W, atol=1e-3)
    with pytest.raises(WardmapError, match="need >= 3"):
        fit_to_world(est[:2], truth[:2])

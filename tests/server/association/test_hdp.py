"""Across-group HDP association (paper 000 Eq. 2-3) by seeded Gibbs sampling."""

from __future__ import annotations

import numpy as np
from factories import object_pose

from wardmap.server.association.hdp import HdpConfig, HdpItem, HdpTopic, gibbs_associate, gmm_log_density


def _item(x: float, kf: int, mid: int, y: float = 3.0) -> HdpItem:
    return HdpItem("chair", object_pose(x, y)[None], (kf,), (mid,))


def _topic(tid: int, xs: list[float], kf0: int = 0, y: float = 3.0, tables: int = 2) -> HdpTopic:
    poses = np.stack([object_pose(x, y) for x in xs])
    kfm = {kf0 + k: frozenset({1000 * tid + k}) for k in range(len(xs))}
    return HdpTopic(tid, "chair", poses, tables, kfm)


def test_gmm_density_is_eq_2_3() -> None:
    """Eq. 3 for one component at Mahalanobis distance d: -d^2/2 - log((2 pi)^3 sp^3 sr^3)."""
    cfg = HdpConfig(sigma_position_m=0.1, sigma_angle_rad=0.5, symmetry="none")
    q = object_pose(0.2, 0)[None]
    c = object_pose(0.0, 0)[None]
    expected = -0.5 * (0.2 / 0.1) ** 2 - 3 * np.log(2 * np.pi) - 3 * np.log(0.1) - 3 * np.log(0.5)
    np.testing.assert_allclose(gmm_log_density(q, c, cfg), [expected])
    # Two components: log of the sum.
    two = gmm_log_density(q, np.stack([c[0], q[0]]), cfg)
    np.testing.assert_allclose(two, [np.logaddexp(expected, expected + 2.0)])


def test_near_joins_far_is_new_and_same_keyframe_conflicts() -> None:
    """Item 0 lies on landmark 7, item 1 is 3 m away, item 2 (same keyframe as item 0) lies
    20 cm from landmark 7 but cannot share it with item 0 (one keyframe, two measurements)."""
    topic = _topic(7, [0.0, 0.02, -0.01])
    items = [_item(0.01, kf=10, mid=1), _item(3.0, kf=10, mid=2), _item(0.2, kf=10, mid=3)]
    z = gibbs_associate(items, [[topic], [], [topic]], HdpConfig(), rng=np.random.default_rng(3))
    assert z[1] < 0
    assert (z[0] == 7) != (z[2] == 7)  # exactly one of them joins 7
    assert z[0] == 7  # the nearer one (1 cm vs 20 cm) wins in the most frequent state


def test_landmark_with_a_measurement_in_the_same_keyframe_is_excluded() -> None:
    """A landmark that already has a different measurement in the item's keyframe is no candidate."""
    topic = _topic(5, [0.0], kf0=10)  # holds mid 5000 in keyframe 10
    z = gibbs_associate([_item(0.0, kf=10, mid=1)], [[topic]], rng=np.random.default_rng(3))
    assert z == [-1]


def test_deterministic_with_a_seed() -> None:
    """Ambiguous items (between two landmarks) give the same assignment for the same seed."""
    cfg = HdpConfig(sigma_position_m=0.3)
    topics = [_topic(1, [0.0]), _topic(2, [0.5], kf0=50)]
    items = [_item(0.25 + 0.01 * k, kf=100 + k, mid=k) for k in range(6)]
    runs = [gibbs_associate(items, [topics] * 6, cfg, rng=np.random.default_rng([4, 2])) for _ in range(3)]
    assert runs[0] == runs[1] == runs[2]
    outcomes = {tuple(gibbs_associate(items, [topics] * 6, cfg, rng=np.random.default_rng([s, 2])))
                for s in range(8)}
    assert len(outcomes) > 1  # the sampler really is random across seeds


def test_overlap_boost_favours_the_landmark_sharing_a_measurement() -> None:
    """An item halfway between landmarks 1 and 2 that shares a measurement with 1 goes to 1
    more often than to 2 over many seeds (boost 1.5); without the boost the split is even-ish."""
    cfg = HdpConfig(sigma_position_m=0.3, sweeps=3, burn_in=0)
    t1 = HdpTopic(1, "chair", object_pose(0.0, 3)[None], 2, {9: frozenset({42})})
    t2 = HdpTopic(2, "chair", object_pose(0.5, 3)[None], 2, {8: frozenset({43})})
    item = HdpItem("chair", np.stack([object_pose(0.25, 3), object_pose(0.25, 3)]), (9, 11), (42, 44))
    picks = [gibbs_associate([item], [[t1, t2]], cfg, rng=np.random.default_rng(s))[0] for s in range(300)]
    assert picks.count(1) > 1.2 * picks.count(2)


def test_new_landmarks_are_shared_by_compatible_items() -> None:
    """Two items of one new object from different keyframes form one new landmark (-1)."""
    items = [_item(5.0, kf=1, mid=1), _item(5.02, kf=2, mid=2)]
    assert gibbs_associate(items, [[], []], rng=np.random.default_rng(0)) == [-1, -1]


def _box(x: float, width: float, y: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    return np.array([x - width / 2, y - 0.25, 0.0]), np.array([x + width / 2, y + 0.25, 0.9])


def test_fragments_of_one_keyframe_may_share_a_landmark() -> None:
    """A chair's seat (landmark 5's measurement 5000 in keyframe 10) and its back (the item, also
    keyframe 10) fit in one chair's box: with boxes the item joins 5; a neighbouring chair of that
    keyframe 0.55 m away does not fit with the seat and stays excluded; without boxes, or with
    ``join_fragments`` off, both are excluded."""
    topic = _topic(5, [0.0], kf0=10)
    back, neighbour = _item(0.05, kf=10, mid=1), _item(0.55, kf=10, mid=2)
    boxes = {5000: _box(0.0, 0.45), 1: _box(0.05, 0.4), 2: _box(0.55, 0.45)}
    rng = np.random.default_rng
    assert gibbs_associate([back], [[topic]], rng=rng(3), boxes=boxes) == [5]
    assert gibbs_associate([neighbour], [[topic]], HdpConfig(sigma_position_m=0.5), rng=rng(3),
                           boxes=boxes) == [-1]
    assert gibbs_associate([back], [[topic]], rng=rng(3)) == [-1]
    strict = HdpConfig(join_fragments=False)
    assert gibbs_associate([back], [[topic]], strict, rng=rng(3), boxes=boxes) == [-1]

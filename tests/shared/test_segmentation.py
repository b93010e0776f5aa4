"""Post-processing of the segmentation contract: boundary upsampling, unsure regions, placement check."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from wardmap.shared.errors import ConfigError
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.segmentation import PlacementRule, SegContract, drop_unsure_regions, upsample_classes

KG = KnowledgeGraph.load()
NAMES = ("background", *KG.names)


def idx(name: str) -> int:
    return NAMES.index(name)


def test_boundary_pixels_follow_the_bilinear_logits() -> None:
    """Two classes with a score difference rising along x that crosses 0 at cell 3.1: the
    bilinear boundary falls at image column 6.7, the nearest cell's at column 8."""
    h, w = 6, 10
    scores = np.zeros((2, h, w), np.float32)
    scores[1] = np.arange(w, dtype=np.float32)[None, :] - 3.1
    classes = np.argmax(scores, axis=0).astype(np.uint8)
    out = upsample_classes(scores, classes, (2 * h, 2 * w))
    nearest = cv2.resize(classes, (2 * w, 2 * h), interpolation=cv2.INTER_NEAREST)
    assert np.all(nearest[:, 7] == 0) and np.all(out[:, 7] == 1)
    assert np.all(out[:, :7] == 0) and np.all(out[:, 8:] == 1)


def test_boundary_upsampling_equals_the_full_bilinear_argmax_for_two_classes() -> None:
    """With two classes every pixel's choice is one of its cells' classes, so computing only
    the boundary pixels gives exactly the argmax of the whole upsampled score map."""
    rng = np.random.default_rng(3)
    small = rng.normal(size=(2, 6, 8)).astype(np.float32)
    scores = np.stack([cv2.resize(c, (40, 30), interpolation=cv2.INTER_CUBIC) for c in small])
    classes = np.argmax(scores, axis=0).astype(np.uint8)
    out = upsample_classes(scores, classes, (60, 80))
    hwc = np.ascontiguousarray(scores.transpose(1, 2, 0))
    full = cv2.resize(hwc, (80, 60), interpolation=cv2.INTER_LINEAR)
    assert np.array_equal(out, np.argmax(full, axis=2).astype(np.uint8))
    assert (out != cv2.resize(classes, (80, 60), interpolation=cv2.INTER_NEAREST)).any()


def test_boundary_upsampling_never_brings_in_a_class_no_cell_has() -> None:
    """Class 2 is second everywhere and never first: between classes 0 and 1 the bilinear
    mean can favour it, but no pixel takes it."""
    scores = np.zeros((3, 4, 4), np.float32)
    scores[0, :, :2], scores[1, :, 2:] = 10.0, 10.0
    scores[2] = 8.0
    classes = np.argmax(scores, axis=0).astype(np.uint8)
    full = cv2.resize(np.ascontiguousarray(scores.transpose(1, 2, 0)), (8, 8), interpolation=cv2.INTER_LINEAR)
    assert (np.argmax(full, axis=2) == 2).any()  # what a plain bilinear argmax would do
    out = upsample_classes(scores, classes, (8, 8))
    assert set(np.unique(out).tolist()) == {0, 1}


def test_placement_rule_reads_the_knowledge_graph() -> None:
    rule = PlacementRule.from_knowledge(KG, NAMES)
    expected = frozenset(idx(c) for c in ("desk", "cabinet", "cart", "person"))
    assert rule.supports == {idx("cup"): expected, idx("temperature_gun"): expected}
    with pytest.raises(ConfigError, match="ring_px"):
        PlacementRule.from_knowledge(KG, NAMES, ring_px=0)


def _scores(first: np.ndarray, second: int) -> np.ndarray:
    """Scores (C, h, w): 5 for the class in ``first`` (h, w), 2 for ``second``, 0 otherwise."""
    s = np.zeros((len(NAMES), *first.shape), np.float32)
    for c in np.unique(first):
        s[c][first == c] = 5.0
    s[second] = np.maximum(s[second], 2.0)
    return s


def test_an_item_on_furniture_it_is_not_placed_on_takes_its_next_class() -> None:
    """A cup region on a sink touches no desk, cabinet, cart or person: its pixels take their
    second class. A cup on a cart, and one in a person's hand, stay cups."""
    rule = PlacementRule.from_knowledge(KG, NAMES)
    first = np.zeros((30, 40), np.int64)
    first[20:30, 0:12] = idx("sink")
    first[17:20, 4:7] = idx("cup")  # on the sink
    first[20:30, 20:30] = idx("cart")
    first[17:20, 24:27] = idx("cup")  # on the cart
    first[0:15, 33:40] = idx("person")
    first[8:10, 31:33] = idx("cup")  # in the hand
    scores = _scores(first, idx("sink"))
    vetoed, out = rule.apply(scores)
    assert np.array_equal(out, np.argmax(vetoed, axis=0))
    assert np.all(out[17:20, 4:7] == idx("sink"))
    assert np.all(out[17:20, 24:27] == idx("cup")) and np.all(out[8:10, 31:33] == idx("cup"))
    assert np.array_equal(out[first != idx("cup")], first[first != idx("cup")])


def test_a_vetoed_item_that_turns_into_another_checked_item_is_checked_again() -> None:
    """A cup region on a wall whose second class is a temperature gun becomes neither: the
    gun region it turns into has no support either, so the third class (background) wins."""
    rule = PlacementRule.from_knowledge(KG, NAMES)
    first = np.full((20, 20), idx("door"), np.int64)
    first[8:12, 8:12] = idx("cup")
    scores = _scores(first, idx("temperature_gun"))
    scores[0][8:12, 8:12] = 1.0
    vetoed, out = rule.apply(scores)
    assert np.array_equal(out, np.argmax(vetoed, axis=0))
    assert np.all(out[8:12, 8:12] == 0)
    unchanged = _scores(np.full((20, 20), idx("door"), np.int64), 0)
    assert rule.apply(unchanged)[0] is unchanged  # nothing checked in view: no copy


def test_decode_applies_the_check_and_renormalises_the_confidence() -> None:
    """A vetoed pixel's confidence is the softmax of its new class among the classes left."""
    contract = SegContract(NAMES, (20, 20))
    first = np.full((20, 20), idx("door"), np.int64)
    first[8:12, 8:12] = idx("cup")
    scores = _scores(first, idx("sink"))
    rule = PlacementRule.from_knowledge(KG, NAMES)
    classes, _, confidence = contract.decode(scores[None], (20, 20), "test", placement=rule)
    assert np.all(classes[8:12, 8:12] == idx("sink"))
    others = len(NAMES) - 2  # every class but sink and the vetoed cup scores 0
    assert confidence[10, 10] == pytest.approx(1.0 / (1.0 + others * np.exp(-2.0)), rel=1e-5)
    plain = contract.decode(scores[None], (20, 20), "test").classes
    assert np.all(plain[8:12, 8:12] == idx("cup"))
    coarse = contract.decode(scores[None], (40, 40), "test", placement=rule, refine_edges=False).classes
    assert coarse.shape == (40, 40) and np.all(coarse[16:24, 16:24] == idx("sink"))


def _speck_scores(shape: tuple[int, int], around: str, speck: tuple[slice, slice]) -> np.ndarray:
    """Scores (C, h, w): class ``around`` everywhere (10 against 0), and a speck where cup,
    desk and sink score 3.1, 3.05 and 3.0 and ``around`` 2.95 (cup wins, softmax 0.24)."""
    s = np.zeros((len(NAMES), *shape), np.float32)
    s[idx(around)] = 10.0
    s[:, speck[0], speck[1]] = 0.0
    for name, value in (("cup", 3.1), ("desk", 3.05), ("sink", 3.0), (around, 2.95)):
        s[idx(name), speck[0], speck[1]] = value
    return s


def _softmax(s: np.ndarray) -> np.ndarray:
    e = np.exp(s - s.max(axis=0)[None])
    return e / e.sum(axis=0)


SPECK, SURE = (slice(2, 5), slice(2, 5)), (slice(10, 14), slice(10, 14))


def test_an_unsure_speck_joins_the_sure_region_around_it() -> None:
    """Inside a door, a cup speck the network is unsure of (softmax 0.24) loses cup, then
    desk and sink (0.23 and 0.22 by the network's own softmax), and joins the door around it;
    a sure cup elsewhere stays, and nothing else moves."""
    s = _speck_scores((16, 16), "door", SPECK)
    s[:, SURE[0], SURE[1]] = 0.0
    s[idx("cup"), SURE[0], SURE[1]] = 10.0
    classes, top = np.argmax(s, axis=0).astype(np.uint8), s.max(axis=0)
    p = _softmax(s)
    assert np.all(classes[SPECK] == idx("cup")) and p[idx("cup"), 3, 3] < 0.35
    out, new, new_top, conf = drop_unsure_regions(s, classes, top, 0.35)
    assert np.all(new[SPECK] == idx("door")) and np.all(new[SURE] == idx("cup"))
    assert (new != classes).sum() == 9 and np.all(new_top[SPECK] == pytest.approx(2.95))
    for name in ("cup", "desk", "sink"):
        assert np.isneginf(out[idx(name)][SPECK]).all()
    # the returned confidence: the door's softmax among the classes left
    left = np.exp(2.95) / (np.exp(2.95) + len(NAMES) - 4)
    assert np.all(conf[SPECK] == pytest.approx(left, rel=1e-5))
    assert np.all(classes[SPECK] == idx("cup"))  # the caller's arrays are untouched
    # nothing unsure: the very arrays come back
    same = drop_unsure_regions(s, classes, top, 0.1)
    assert same[0] is s and same[1] is classes and same[2] is top


def test_an_unsure_speck_is_judged_by_the_network_not_by_what_is_left() -> None:
    """On background, the speck's next classes have no sure region to join. At a floor of
    0.25, desk would score 0.30 among the classes left after cup, but the network gave it
    0.23: it is vetoed too, and so is sink; the speck ends as background, never vetoed."""
    s = _speck_scores((16, 16), "background", SPECK)
    classes, top = np.argmax(s, axis=0).astype(np.uint8), s.max(axis=0)
    without_cup = np.exp(3.05) / (np.exp([3.05, 3.0, 2.95]).sum() + len(NAMES) - 4)
    assert without_cup > 0.25 > _softmax(s)[idx("cup"), 3, 3] > _softmax(s)[idx("desk"), 3, 3] > 0.2
    _, new, _, _ = drop_unsure_regions(s, classes, top, 0.25)
    assert np.all(new[SPECK] == 0)
    _, kept, _, _ = drop_unsure_regions(s, classes, top, 0.2)  # a lower floor keeps the cup
    assert np.all(kept[SPECK] == idx("cup"))


def test_decode_drops_unsure_regions_before_the_placement_check() -> None:
    """A hesitant cup speck on a door is not reported at 0.35; at 0 (off) it is a cup, and
    outside 0..1 is a ConfigError."""
    contract = SegContract(NAMES, (16, 16))
    s = _speck_scores((16, 16), "door", SPECK)[None]
    rule = PlacementRule.from_knowledge(KG, NAMES)
    dropped = contract.decode(s, (16, 16), "test", min_region_confidence=0.35).classes
    assert np.all(dropped[SPECK] == idx("door"))
    plain = contract.decode(s, (16, 16), "test").classes
    assert np.all(plain[SPECK] == idx("cup"))
    # the placement check alone also removes this cup (no support), but gives it desk
    checked = contract.decode(s, (16, 16), "test", placement=rule).classes
    assert np.all(checked[SPECK] == idx("desk"))
    for bad in (-0.1, 1.5):
        with pytest.raises(ConfigError, match="min_region_confidence"):
            contract.decode(s, (16, 16), "test", min_region_confidence=bad)


def _unsure_reference(s: np.ndarray, floor: float) -> np.ndarray:
    """Every class region checked, every cell recomputed, each round: the slow definition."""
    p = _softmax(s)
    s = s.copy()
    while True:
        classes = np.argmax(s, axis=0)
        judge = np.take_along_axis(p, classes[None], axis=0)[0]
        hit = False
        for c in range(1, len(s)):
            n, regions = cv2.connectedComponents((classes == c).astype(np.uint8), connectivity=8)
            for k in range(1, n):
                if judge[regions == k].mean() < floor:
                    s[c][regions == k] = -np.inf
                    hit = True
        if not hit:
            return classes.astype(np.uint8)


def test_unsure_regions_match_the_slow_definition_on_noisy_scores() -> None:
    """Smooth random scores for five classes (many small hesitant regions): the incremental
    version (only classes with an unsure cell, only vetoed cells recomputed) gives the same map."""
    rng = np.random.default_rng(7)
    small = rng.normal(scale=1.5, size=(5, 12, 16)).astype(np.float32)
    s = np.stack([cv2.resize(c, (64, 48), interpolation=cv2.INTER_CUBIC) for c in small])
    classes, top = np.argmax(s, axis=0).astype(np.uint8), s.max(axis=0)
    for floor in (0.4, 0.5, 0.6):
        expected = _unsure_reference(s, floor)
        _, got, _, conf = drop_unsure_regions(s, classes, top, floor)
        assert np.array_equal(got, expected)
        assert (got != classes).any()
        assert conf.shape == classes.shape and np.all(conf > 0) and np.all(conf <= 1 + 1e-6)

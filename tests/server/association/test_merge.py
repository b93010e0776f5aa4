"""Landmarks that turn out to be one object are merged (``AssociationConfig.merge_inside``, and
``merge_across`` for a class confusion), and the server's object map follows: the absorbed
object is deleted, its observations moved."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from wardmap.server.association.associator import AssociationConfig, Associator
from wardmap.server.association.hdp import HdpConfig
from wardmap.server.association.types import Landmark, LandmarkChange
from wardmap.server.mapping import MappedKeyframe, MapWriter
from wardmap.server.objectmap import ObjectMap
from wardmap.server.store import MapStore, SqliteMapStore
from wardmap.shared.knowledge import KnowledgeGraph

from .conftest import CAMERA, MeasurementFactory, camera_looking_along_y, object_pose

CART = np.array([0.6, 0.6, 0.9])
WIDE = np.array([1.2, 0.6, 0.9])
PIECE = np.array([0.2, 0.2, 0.3])


def _keyframes(make: MeasurementFactory) -> list[tuple[list, np.ndarray]]:
    """A cart seen first as two disjoint boxes (its left part, and a piece 0.5 m to the right:
    two landmarks), then whole: its landmark grows over the piece."""
    out = []
    for i in range(16):
        T = camera_looking_along_y(0.2 + 0.02 * i)
        key = dict(keyframe=f"r1/s1/{i}", stamp=1.0 + i, category="cart", gt=1)
        if i < 6:
            ms = [make(object_pose(0.0, 3.0, 0.45), T, size=CART, **key),
                  make(object_pose(0.5, 3.0, 0.45), T, size=PIECE, **key)]
        else:
            ms = [make(object_pose(0.3, 3.0, 0.45), T, size=WIDE, **key)]
        out.append((ms, T))
    return out


def _inside_other_class(make: MeasurementFactory, big: tuple[str, np.ndarray],
                        small: tuple[str, np.ndarray], small_at: float) -> list[tuple[list, np.ndarray]]:
    """One object of class ``big[0]`` measured whole in 12 keyframes; in each of the first 6 a
    second measurement, of class ``small[0]``, lies inside it ``small_at`` m along x (the network
    calling part of the object by another class, or a small object on it)."""
    out = []
    for i in range(12):
        T = camera_looking_along_y(0.3 + 0.02 * i, y=-1.0)
        key = dict(keyframe=f"r1/s1/{i}", stamp=1.0 + i)
        ms = [make(object_pose(0.3, 3.0, big[1][2] / 2), T, size=big[1], category=big[0], gt=1, **key)]
        if i < 6:
            ms.append(make(object_pose(0.3 + small_at, 3.0, small[1][2] / 2), T, size=small[1],
                           category=small[0], gt=1, **key))
        out.append((ms, T))
    return out


def _map_scene(store: MapStore, scene: list, association: AssociationConfig | None = None,
               ) -> tuple[list[Landmark], ObjectMap, set[tuple[int, str]]]:
    """Run the server's map writer over ``scene`` (one session); returns the associator's
    landmarks, the object map and every (object id, category) the map held after some keyframe,
    confirmed or not (a 0.2 m piece of a cart is narrower than any cart:
    ``AssociationConfig.min_width_m``)."""
    objects = ObjectMap(store)
    writer = MapWriter(objects, association)
    seen: set[tuple[int, str]] = set()
    for ms, T in scene:
        writer.add([MappedKeyframe("r1/s1", T, CAMERA, ms)])
        page = objects.query(include_unconfirmed=True)
        seen |= {(h.record.object_id, h.record.category) for h in page.hits}
    writer.close(["r1/s1"])
    return writer.landmarks(), objects, seen


def _run(assoc: Associator, scene: list) -> list[LandmarkChange]:
    changes = [c for ms, T in scene for c in assoc.add_keyframe(ms, T, CAMERA)]
    return changes + assoc.flush()


def test_a_landmark_grown_over_another_absorbs_it(make_measurement: MeasurementFactory) -> None:
    """With one measurement per keyframe and landmark (``join_fragments`` off) the two parts
    start as two landmarks, and merging joins them."""
    scene = _keyframes(make_measurement)
    strict = HdpConfig(join_fragments=False)
    apart = Associator(AssociationConfig(merge_inside=0.0, merge_fragments=0.0, hdp=strict))
    _run(apart, scene)
    assert len(apart.landmarks()) == 2
    assoc = Associator(AssociationConfig(merge_fragments=0.0, hdp=strict))
    changes = _run(assoc, scene)
    (one,) = assoc.landmarks()
    assert one.n_measurements == sum(len(ms) for ms, _ in scene)  # nothing lost
    merged = [c for c in changes if c.kind == "merged"]
    assert len(merged) == 1 and merged[0].into == one.id and merged[0].landmark.id != one.id
    assert merged[0].added == ()
    # Every measurement entered the map exactly once, through some change's ``added``.
    added = [id(m) for c in changes for m in c.added]
    assert sorted(added) == sorted(id(m) for ms, _ in scene for m in ms)
    # Two keyframes' measurements of one object now share a landmark.
    assert len({m.keyframe for m in one.measurements}) < len(one.measurements)


def test_fragments_of_one_keyframe_join_one_landmark(make_measurement: MeasurementFactory) -> None:
    """The same scene with ``join_fragments`` (default): the left part and the piece fit in one
    cart's box, so the association puts them in one landmark from the first group, no merge
    needed; with ``merge_inside`` off as well it is still one landmark."""
    scene = _keyframes(make_measurement)
    for cfg in (AssociationConfig(), AssociationConfig(merge_inside=0.0)):
        assoc = Associator(cfg)
        changes = _run(assoc, scene)
        (one,) = assoc.landmarks()
        assert one.n_measurements == sum(len(ms) for ms, _ in scene)
        assert not [c for c in changes if c.kind == "merged"]


def test_identical_neighbours_are_not_merged(make_measurement: MeasurementFactory) -> None:
    """Two carts side by side (boxes touching) stay two landmarks."""
    assoc = Associator(AssociationConfig())
    for i in range(12):
        T = camera_looking_along_y(0.3 + 0.02 * i)
        key = dict(keyframe=f"r1/s1/{i}", stamp=float(i), category="cart")
        assoc.add_keyframe([make_measurement(object_pose(0.0, 3.0, 0.45), T, size=CART, gt=1, **key),
                            make_measurement(object_pose(0.62, 3.0, 0.45), T, size=CART, gt=2, **key)],
                           T, CAMERA)
    assoc.flush()
    assert sorted(lm.n_measurements for lm in assoc.landmarks()) == [12, 12]


def test_the_object_map_follows_a_merge(tmp_path: Path, make_measurement: MeasurementFactory) -> None:
    """The mapping stage deletes the absorbed object and moves its observations to the survivor."""
    with SqliteMapStore.open(tmp_path / "map.db") as store:
        strict = AssociationConfig(hdp=HdpConfig(join_fragments=False))  # two objects, then a merge
        (survivor,), objects, seen = _map_scene(store, _keyframes(make_measurement), strict)
        page = objects.query()
        assert [h.record.object_id for h in page.hits] == [survivor.id]
        assert len({oid for oid, _ in seen}) == 2  # the piece was an object of its own before the merge
        assert store.observation_counts() == {survivor.id: survivor.n_measurements}
        assert page.hits[0].record.n_observations == survivor.n_measurements


BED = np.array([2.0, 0.9, 0.6])
FOOT = np.array([0.6, 0.8, 0.55])


def test_a_class_confusion_inside_a_landmark_is_merged_into_it(make_measurement: MeasurementFactory) -> None:
    """The foot of a bed measured as a cart in some keyframes: one landmark, a bed, with all of
    its measurements (two with ``merge_across`` off)."""
    scene = _inside_other_class(make_measurement, ("bed", BED), ("cart", np.array([0.6, 0.7, 0.55])), 0.6)
    apart = Associator(AssociationConfig(merge_across=0.0))
    _run(apart, scene)
    assert sorted(lm.category for lm in apart.landmarks()) == ["bed", "cart"]
    assoc = Associator(AssociationConfig())
    changes = _run(assoc, scene)
    (bed,) = assoc.landmarks()
    assert bed.category == "bed" and bed.n_measurements == 18
    assert sorted({m.category for m in bed.measurements}) == ["bed", "cart"]
    # Merged in the call that created it, so the cart was never reported; nothing is lost.
    assert sorted(id(m) for c in changes for m in c.added) == sorted(id(m) for ms, _ in scene for m in ms)


def test_classes_the_knowledge_graph_relates_are_not_merged(make_measurement: MeasurementFactory) -> None:
    """A cup on a cart (``cup placed_on cart``) lies inside the cart's box and stays an object of
    its own; with a knowledge graph that lacks that fact it would be merged."""
    scene = _inside_other_class(make_measurement, ("cart", np.array([0.8, 0.6, 1.0])),
                                ("cup", np.array([0.1, 0.1, 0.12])), 0.1)
    assoc = Associator(AssociationConfig())
    _run(assoc, scene)
    assert sorted(lm.category for lm in assoc.landmarks()) == ["cart", "cup"]
    kg = KnowledgeGraph.load()
    unrelated = KnowledgeGraph([c for c in kg.classes], [r for r in kg.relations() if r.subject != "cup"],
                               {p: p for p in kg.predicates})
    blind = Associator(AssociationConfig(), knowledge=unrelated)
    _run(blind, scene)
    assert [lm.category for lm in blind.landmarks()] == ["cart"]


def test_a_merge_across_classes_must_leave_an_object_of_the_surviving_class(
        make_measurement: MeasurementFactory) -> None:
    """An IV pole standing in front of a sink: their hulls overlap, but a sink 1.9 m tall would
    be taller than any sink (``HdpConfig.class_size_m``), so the two stay apart."""
    scene = _inside_other_class(make_measurement, ("sink", np.array([0.55, 0.45, 0.95])),
                                ("iv_pole", np.array([0.5, 0.5, 1.9])), 0.1)
    assoc = Associator(AssociationConfig())
    _run(assoc, scene)
    apart = sorted((lm.category, lm.n_measurements) for lm in assoc.landmarks())
    assert apart == [("iv_pole", 6), ("sink", 12)]


def test_merge_shares_outside_0_1_are_rejected() -> None:
    for key in ("merge_inside", "merge_fragments", "merge_across"):
        for bad in (-0.1, 1.5):
            with pytest.raises(ValueError, match=key):
                AssociationConfig(**{key: bad})


def test_a_confusion_is_merged_where_the_landmark_was_seen_in_parts(
        make_measurement: MeasurementFactory) -> None:
    """A bed seen mostly as its foot half, now and then as its head half: its box (the foot
    half's pose, the median size) misses the head end, the hull of its measurements holds the
    whole bed, and a "cart" at the head end is merged into it (a cart landmark with boxes only)."""
    make = make_measurement
    half = np.array([1.0, 0.9, 0.6])
    cart = np.array([0.4, 0.7, 0.55])
    scene = []
    for i in range(12):
        T = camera_looking_along_y(0.3 + 0.02 * i, y=-1.0)
        key = dict(keyframe=f"r1/s1/{i}", stamp=1.0 + i)
        x = -0.2 if i % 3 == 0 else 0.8
        ms = [make(object_pose(x, 3.0, 0.3), T, size=half, category="bed", gt=1, **key)]
        if i % 3 == 0:
            ms.append(make(object_pose(-0.1, 3.0, 0.3), T, size=cart, category="cart", gt=1, **key))
        scene.append((ms, T))
    assoc = Associator(AssociationConfig())
    _run(assoc, scene)
    landmarks = assoc.landmarks()
    assert {lm.category for lm in landmarks} == {"bed"}
    assert sum(lm.n_measurements for lm in landmarks) == 16


def test_the_object_map_follows_a_merge_across_classes(tmp_path: Path,
                                                       make_measurement: MeasurementFactory) -> None:
    """A bed's foot seen alone first and called a cart is a cart object; once the whole bed is
    measured more often than the foot, the map holds one object, a bed, whose observations still
    say which were measured as a cart."""
    scene = []
    for i in range(16):
        T = camera_looking_along_y(0.3 + 0.02 * i, y=-1.0)
        key = dict(keyframe=f"r1/s1/{i}", stamp=1.0 + i, gt=1)
        if i < 6:
            m = make_measurement(object_pose(0.9, 3.0, 0.3), T, size=FOOT, category="cart", **key)
        else:
            m = make_measurement(object_pose(0.3, 3.0, 0.3), T, size=BED, category="bed", **key)
        scene.append(([m], T))
    with SqliteMapStore.open(tmp_path / "map.db") as store:
        _, objects, seen = _map_scene(store, scene)
        assert {category for _, category in seen} == {"bed", "cart"}
        (bed,) = objects.query().hits
        assert bed.record.category == "bed" and bed.record.n_observations == 16
        detail = objects.get(bed.record.object_id)
        assert detail is not None
        assert sorted(o.category for o in detail.observations) == ["bed"] * 10 + ["cart"] * 6


CHAIR = np.array([0.47, 0.44, 0.67])
BACKREST = np.array([0.47, 0.06, 0.41])


def _backrest_scene(make: MeasurementFactory, gap: float) -> list[tuple[list, np.ndarray]]:
    """A chair seen whole in 12 keyframes; in the first 6 the network also cut its backrest off
    as a second chair mask, ``gap`` m behind the chair's back along y (0: the chair's own)."""
    out = []
    for i in range(12):
        T = camera_looking_along_y(0.3 + 0.02 * i, y=-1.0)
        key = dict(keyframe=f"r1/s1/{i}", stamp=1.0 + i, category="chair")
        ms = [make(object_pose(0.3, 3.0, 0.47), T, size=CHAIR, gt=1, **key)]
        if i < 6:
            back = object_pose(0.3, 2.8 - gap, 0.72)
            ms.append(make(back, T, size=BACKREST, gt=1 if gap == 0 else 2, **key))
        out.append((ms, T))
    return out


def test_two_parts_that_fit_one_object_of_their_class_are_merged(
        make_measurement: MeasurementFactory) -> None:
    """A backrest landmark overlapping a chair landmark by 59 % of its box (under
    ``merge_inside``), both inside one chair's size bound: one chair (``merge_fragments``). The
    same backrest 0.4 m behind the chair overlaps nothing and stays apart. (``join_fragments``
    off, so the two start apart, as they did on the benchmark's worlds. By footprint, which
    chairs are compared by, the backrest lies wholly over the chair, and its centre lies within
    ``merge_within_m`` of the chair's, and the two fit one chair (``merge_fitting``): the control
    compares volumes only.)"""
    scene = _backrest_scene(make_measurement, 0.0)
    strict = HdpConfig(join_fragments=False)
    apart = Associator(AssociationConfig(merge_fragments=0.0, merge_by_footprint=(), merge_within_m=(),
                                         merge_fitting=(), hdp=strict))
    _run(apart, scene)
    assert len(apart.landmarks()) == 2
    merged = Associator(AssociationConfig(hdp=strict))
    _run(merged, scene)
    assert [lm.n_measurements for lm in merged.landmarks()] == [18]
    behind = Associator(AssociationConfig(hdp=strict))
    _run(behind, _backrest_scene(make_measurement, 0.4))
    assert sorted(lm.n_measurements for lm in behind.landmarks()) == [6, 12]


Part = tuple[str, np.ndarray, float]


def _stacked(make: MeasurementFactory, low: Part, high: Part) -> list[tuple[list, np.ndarray]]:
    """An object measured as its lower part ``low`` = (class, size, centre height) in 12
    keyframes and once, in keyframe 7, as its upper part ``high``: two boxes one above the other,
    with no volume in common."""
    out = []
    for i in range(12):
        T = camera_looking_along_y(0.3 + 0.02 * i, y=-1.0)
        key = dict(keyframe=f"r1/s1/{i}", stamp=1.0 + i, gt=1)
        ms = [make(object_pose(0.3, 3.0, low[2]), T, size=low[1], category=low[0], **key)]
        if i == 7:
            ms.append(make(object_pose(0.3, 3.0, high[2]), T, size=high[1], category=high[0], **key))
        out.append((ms, T))
    return out


@pytest.mark.parametrize(("low", "high", "survivor"), [
    # A chair seen as its legs, and once as its seat and back, called a wheelchair.
    (("chair", np.array([0.45, 0.45, 0.45]), 0.225),
     ("wheelchair", np.array([0.46, 0.4, 0.5]), 0.7), "chair"),
    # An IV pole's pole, and once its stand on the floor apart from it.
    (("iv_pole", np.array([0.1, 0.1, 1.5]), 1.15),
     ("iv_pole", np.array([0.5, 0.5, 0.08]), 0.04), "iv_pole"),
])
def test_parts_one_above_the_other_merge_by_their_footprints(
        make_measurement: MeasurementFactory, low: tuple, high: tuple, survivor: str) -> None:
    """Floor-standing classes (``merge_by_footprint``) compare footprints: the two parts of one
    object stacked one above the other become one landmark; compared by volume they stay two."""
    scene = _stacked(make_measurement, low, high)
    by_volume = Associator(AssociationConfig(merge_by_footprint=()))
    _run(by_volume, scene)
    assert sorted(lm.n_measurements for lm in by_volume.landmarks()) == [1, 12]
    assoc = Associator(AssociationConfig())
    _run(assoc, scene)
    (one,) = assoc.landmarks()
    assert one.category == survivor and one.n_measurements == 13


def test_a_footprint_merge_must_fit_one_object_of_the_class(make_measurement: MeasurementFactory) -> None:
    """A chair under a piece 1.2 m above its seat (a cart's top taken for a wheelchair, say):
    the footprints match, but a chair 1.9 m tall fits no chair, so the two stay apart."""
    scene = _stacked(make_measurement, ("chair", np.array([0.45, 0.45, 0.9]), 0.45),
                     ("wheelchair", np.array([0.46, 0.4, 0.3]), 1.75))
    assoc = Associator(AssociationConfig())
    _run(assoc, scene)
    apart = sorted((lm.category, lm.n_measurements) for lm in assoc.landmarks())
    assert apart == [("chair", 12), ("wheelchair", 1)]


def test_footprint_classes_must_be_knowledge_graph_classes() -> None:
    with pytest.raises(ValueError, match="merge_by_footprint: not knowledge-graph classes: sofa"):
        Associator(AssociationConfig(merge_by_footprint=("chair", "sofa")))


def _spill_scene(make: MeasurementFactory, offset: float) -> list[tuple[list, np.ndarray]]:
    """A chair seen whole in 12 keyframes; in the first 6 the network also measured a second
    chair mask ``offset`` m to its side, 0.7 m wide (chair and the wall beside it)."""
    out = []
    for i in range(12):
        T = camera_looking_along_y(0.3 + 0.02 * i, y=-1.0)
        key = dict(keyframe=f"r1/s1/{i}", stamp=1.0 + i, category="chair")
        ms = [make(object_pose(0.3, 3.0), T, size=CHAIR, gt=1, **key)]
        if i < 6:
            ms.append(make(object_pose(0.3 + offset, 3.0), T, size=np.array([0.7, 0.46, 0.93]),
                           gt=1 if offset < 0.4 else 2, **key))
        out.append((ms, T))
    return out


def test_chair_landmarks_closer_than_any_two_chairs_are_merged(make_measurement: MeasurementFactory) -> None:
    """Two chair landmarks 0.25 m apart: the box holding both (0.83 m) fits no chair and the
    smaller lies 72 % inside the other, so no share merges them, but no two chairs stand that
    close (``merge_within_m``): one chair. A second mask 0.5 m away stays apart."""
    strict = HdpConfig(join_fragments=False)
    off = Associator(AssociationConfig(merge_within_m=(), hdp=strict))
    _run(off, _spill_scene(make_measurement, 0.25))
    assert sorted(lm.n_measurements for lm in off.landmarks()) == [6, 12]
    on = Associator(AssociationConfig(hdp=strict))
    _run(on, _spill_scene(make_measurement, 0.25))
    assert [lm.n_measurements for lm in on.landmarks()] == [18]
    far = Associator(AssociationConfig(hdp=strict))
    _run(far, _spill_scene(make_measurement, 0.5))
    assert sorted(lm.n_measurements for lm in far.landmarks()) == [6, 12]
    alone = Associator(AssociationConfig(merge_inside=0.0, merge_fragments=0.0, merge_across=0.0, hdp=strict))
    _run(alone, _spill_scene(make_measurement, 0.25))  # the only merge rule left on
    assert [lm.n_measurements for lm in alone.landmarks()] == [18]


def test_merge_within_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="merge_within_m entries are"):
        AssociationConfig(merge_within_m=(("chair", 0.0),))
    with pytest.raises(ValueError, match="merge_within_m: not knowledge-graph classes: stool"):
        Associator(AssociationConfig(merge_within_m=(("stool", 0.3),)))


SEAT = np.array([0.46, 0.25, 0.47])
"""A chair's seat and legs, measured without its backrest (front 0.25 m of a 0.46 m chair)."""


def _parts_scene(make: MeasurementFactory, spacing: float) -> list[tuple[list, np.ndarray]]:
    """A chair whose backrest (a 6 cm slab, 0.72 m up) and seat with legs (0.25 m up, centred
    0.35 m in front of the backrest) the network measured as two chair masks in each of 12
    keyframes. ``spacing`` > 0: the seat is the next chair's, that far along x."""
    out = []
    for i in range(12):
        T = camera_looking_along_y(0.3 + 0.02 * i, y=-1.0)
        key = dict(keyframe=f"r1/s1/{i}", stamp=1.0 + i, category="chair")
        out.append(([make(object_pose(0.3, 3.2, 0.72), T, size=BACKREST, gt=1, **key),
                     make(object_pose(0.3 + spacing, 2.85, 0.25), T, size=SEAT, gt=1 if spacing == 0 else 2,
                          **key)], T))
    return out


def test_two_chair_landmarks_that_fit_one_chair_are_merged_however_little_they_overlap(
        make_measurement: MeasurementFactory) -> None:
    """A backrest landmark and a seat landmark of one chair share no footprint and their centres
    lie 0.35 m apart, so neither the shares nor ``merge_within_m`` (0.3 m here) join them, but
    the box holding both (0.47 x 0.47 x 0.95 m) fits one chair (``merge_fitting``): one chair.
    The same seat under the next chair of a row (0.55 m along) makes a box 1 m wide: two.
    (``join_fragments`` off, so the parts start as two landmarks.)"""
    within, strict = (("chair", 0.3),), HdpConfig(join_fragments=False)
    off = Associator(AssociationConfig(merge_fitting=(), merge_within_m=within, hdp=strict))
    _run(off, _parts_scene(make_measurement, 0.0))
    assert sorted(lm.n_measurements for lm in off.landmarks()) == [12, 12]
    on = Associator(AssociationConfig(merge_within_m=within, hdp=strict))
    _run(on, _parts_scene(make_measurement, 0.0))
    assert [lm.n_measurements for lm in on.landmarks()] == [24]
    alone = Associator(AssociationConfig(merge_inside=0.0, merge_fragments=0.0, merge_across=0.0,
                                         merge_within_m=(), hdp=strict))
    _run(alone, _parts_scene(make_measurement, 0.0))  # the only merge rule left on
    assert [lm.n_measurements for lm in alone.landmarks()] == [24]
    row = Associator(AssociationConfig(merge_within_m=within, hdp=strict))
    _run(row, _parts_scene(make_measurement, 0.55))
    assert sorted(lm.n_measurements for lm in row.landmarks()) == [12, 12]


def test_merge_fitting_classes_need_a_size_bound() -> None:
    with pytest.raises(ValueError, match="merge_fitting: not knowledge-graph classes: stool"):
        Associator(AssociationConfig(merge_fitting=("stool",)))
    with pytest.raises(ValueError, match="merge_fitting: classes without a size bound"):
        Associator(AssociationConfig(merge_fitting=("cup",)))

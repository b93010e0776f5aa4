"""Protocol tests of the store's object rows (:class:`~wardmap.server.store.ObjectStore`), run
against every backend (``conftest.BACKENDS``). Objects are axis-aligned boxes at known places, so
every filter's answer is known; the object map's own checks are in tests/server/test_objectmap.py."""

from __future__ import annotations

import numpy as np
import pytest

from wardmap.server.store import MapStore, ObjectRow, Observation, UnknownObjectError
from wardmap.shared.se3 import yaw_transform

from .conftest import T0, keyframe


def _row(oid: int, x: float, y: float = 0.0, *, category: str = "door", confidence: float = 0.9,
         confirmed: bool = True, color: tuple[float, float, float] | None = None) -> ObjectRow:
    """A 1 x 0.5 x 2 m box centred at (x, y, 1), not turned."""
    size = (1.0, 0.5, 2.0)
    return ObjectRow(oid, category, confidence, yaw_transform(x, y, 0.0, 1.0), 0.0, (0.0, 0.0, 0.0, 1.0),
                     size, (x - 0.5, y - 0.25, 0.0), (x + 0.5, y + 0.25, 2.0), color, confirmed)


def _obs(oid: int, robot: str, seq: int, *, box: float = 0.0) -> Observation:
    return Observation(oid, robot, "s1", seq, T0 + seq, "door", 0.8,
                       np.array([box, box, box + 10.0, box + 20.0]), yaw_transform(1.0, 2.0, 0.3, 0.5),
                       np.array([1.0, 0.5, 2.0]))


def _ids(store: MapStore, **kwargs: object) -> list[int]:
    return [h.record.object_id for h in store.find_objects(**kwargs).hits]  # type: ignore[arg-type]


def test_write_creates_then_updates_and_derives_from_observations(store: MapStore) -> None:
    """A new object is created with the write's time; a second write of it is an update that keeps
    its first-seen time; observations set its count, last-seen time and robots."""
    (w,) = store.write_objects([_row(7, 3.0, color=(10.0, 20.0, 30.0))], [], 100.0)
    assert w.created and w.record.object_id == 7 and w.record.position == (3.0, 0.0, 1.0)
    assert (w.record.n_observations, w.record.first_seen_s, w.record.last_seen_s) == (0, 100.0, 100.0)
    assert w.record.color_rgb == (10.0, 20.0, 30.0) and w.record.robots == ()
    (w,) = store.write_objects([_row(7, 4.0, confirmed=False)], [_obs(7, "r2", 0), _obs(7, "r1", 1)], 105.0)
    assert not w.created and w.record.position == (4.0, 0.0, 1.0) and w.record.color_rgb is None
    assert (w.record.n_observations, w.record.first_seen_s, w.record.last_seen_s) == (2, 100.0, 105.0)
    assert w.record.robots == ("r1", "r2") and w.record.confirmed is False
    assert store.observation_counts() == {7: 2}


def test_an_observation_stored_again_moves_to_its_new_object(store: MapStore) -> None:
    """The same keyframe and box under another object moves the observation: both objects are
    touched (given ones first) and counted again; nothing is duplicated."""
    store.write_objects([_row(1, 0.0), _row(2, 5.0)], [_obs(1, "r1", 0), _obs(1, "r1", 1)], 100.0)
    written = store.write_objects([], [_obs(2, "r1", 1)], 101.0)
    assert [(w.record.object_id, w.created, w.record.n_observations) for w in written] == [
        (1, False, 1), (2, False, 1)]
    assert store.observation_counts() == {1: 1, 2: 1}


def test_an_observation_of_an_unknown_object_writes_nothing(store: MapStore) -> None:
    store.write_objects([_row(1, 0.0)], [], 100.0)
    with pytest.raises(UnknownObjectError, match=r"\[9\]"):
        store.write_objects([_row(2, 1.0)], [_obs(9, "r1", 0)], 101.0)
    assert store.count_objects() == 1 and store.observation_counts() == {}


def test_delete_and_merge(store: MapStore) -> None:
    """A merged object's observations and robots move to the survivor; a plain delete takes them
    along; unknown ids raise and change nothing."""
    store.write_objects([_row(1, 0.0), _row(2, 0.5), _row(3, 9.0)],
                        [_obs(1, "r1", 0), _obs(1, "r2", 1), _obs(2, "r3", 2), _obs(3, "r1", 3)], 100.0)
    before, after = store.delete_object(1, merged_into=2)
    assert before.object_id == 1 and before.n_observations == 2
    assert after is not None and after.n_observations == 3 and after.robots == ("r1", "r2", "r3")
    gone, none = store.delete_object(3)
    assert gone.object_id == 3 and none is None
    assert store.observation_counts() == {2: 3}
    assert _ids(store, near=(0.0, 0.0, 1.0), radius_m=100.0) == [2]
    with pytest.raises(UnknownObjectError, match="unknown object 1"):
        store.delete_object(1)
    with pytest.raises(UnknownObjectError, match=r"unknown object 42 \(merged_into\)"):
        store.delete_object(2, merged_into=42)
    assert store.count_objects() == 1


def test_find_filters_orders_and_pages(store: MapStore) -> None:
    """Each filter keeps exactly the objects it names; ``near`` orders by centre distance (ties by
    id) and gives distances; pages follow each other."""
    store.write_objects(
        [_row(1, 0.0), _row(2, 3.0, category="bed", confidence=0.5), _row(3, -1.0, 1.0),
         _row(4, 10.0, confirmed=False), _row(5, 1.0)],
        [_obs(3, "r2", 0)], 100.0)
    assert _ids(store) == [1, 2, 3, 5]
    assert _ids(store, include_unconfirmed=True) == [1, 2, 3, 4, 5]
    assert _ids(store, category="bed") == [2]
    assert _ids(store, min_confidence=0.6) == [1, 3, 5]
    assert _ids(store, robot="r2") == [3]
    page = store.find_objects(near=(0.0, 0.0, 1.0))
    assert [h.record.object_id for h in page.hits] == [1, 5, 3, 2]
    assert [h.distance_m for h in page.hits] == pytest.approx([0.0, 1.0, np.sqrt(2.0), 3.0])
    assert _ids(store, near=(0.0, 0.0, 1.0), radius_m=1.0) == [1, 5]
    assert store.find_objects().hits[0].distance_m is None
    first = store.find_objects(limit=2)
    assert [h.record.object_id for h in first.hits] == [1, 2] and first.next_offset == 2
    last = store.find_objects(limit=2, offset=2)
    assert [h.record.object_id for h in last.hits] == [3, 5] and last.next_offset is None


def test_compact_pages_are_the_found_records_columns(store: MapStore) -> None:
    """find_compact gives, for every filter and page of find_objects, the same objects in the same
    order with the same next offset, each as (id, category, centre, yaw, size) of its record."""
    turned = ObjectRow(6, "cart", 0.8, yaw_transform(2.0, -1.0, 0.7, 0.4), 0.7,
                       (0.0, 0.0, float(np.sin(0.35)), float(np.cos(0.35))), (0.9, 0.6, 1.1),
                       (1.4, -1.6, 0.0), (2.6, -0.4, 1.1), None, True)
    store.write_objects(
        [_row(1, 0.0), _row(2, 3.0, category="bed", confidence=0.5), _row(3, -1.0, 1.0),
         _row(4, 10.0, confirmed=False), _row(5, 1.0), turned],
        [_obs(3, "r2", 0)], 100.0)
    queries: list[dict[str, object]] = [
        {}, {"include_unconfirmed": True}, {"category": "bed"}, {"min_confidence": 0.6}, {"robot": "r2"},
        {"near": (0.0, 0.0, 1.0)}, {"near": (0.0, 0.0, 1.0), "radius_m": 1.5}, {"limit": 2},
        {"limit": 2, "offset": 2}, {"limit": 2, "offset": 4}, {"category": "door", "robot": "nobody"},
    ]
    for q in queries:
        full, compact = store.find_objects(**q), store.find_compact(**q)  # type: ignore[arg-type]
        assert compact.next_offset == full.next_offset, q
        want = [(h.record.object_id, h.record.category, *h.record.position, h.record.yaw, *h.record.size)
                for h in full.hits]
        assert compact.rows == want, q
        assert all(type(v) is float for row in compact.rows for v in row[2:]), q
    assert store.find_compact(category="cart").rows == [(6, "cart", 2.0, -1.0, 0.4, 0.7, 0.9, 0.6, 1.1)]


def test_detail_and_counts(store: MapStore) -> None:
    """object_detail gives the newest observations first (capped) and their keyframes, saying which
    the store holds; counts split by confirmation and category."""
    msg, payload = keyframe(seq=1)
    store.insert(msg, payload, 1.0)
    store.write_objects([_row(1, 0.0), _row(2, 1.0, category="bed", confirmed=False)], [_obs(1, "r1", 0)],
                        100.0)
    store.write_objects([], [_obs(1, "r1", 1), _obs(1, "r2", 2, box=5.0)], 101.0)
    detail = store.object_detail(1, 10)
    assert detail is not None and detail.record.n_observations == 3
    assert [(o.robot_id, o.seq, o.added_s) for o in detail.observations] == [
        ("r2", 2, 101.0), ("r1", 1, 101.0), ("r1", 0, 100.0)]
    assert [(k.robot_id, k.seq, k.stored) for k in detail.keyframes] == [
        ("r1", 0, False), ("r1", 1, True), ("r2", 2, False)]
    capped = store.object_detail(1, 1)
    assert capped is not None and len(capped.observations) == 1 and len(capped.keyframes) == 1
    assert store.object_detail(3, 10) is None
    assert store.count_objects() == 2
    assert (store.count_objects(unconfirmed=True), store.count_objects(unconfirmed=False)) == (1, 1)
    assert store.category_counts() == {"door": 1}
    assert store.category_counts(include_unconfirmed=True) == {"bed": 1, "door": 1}

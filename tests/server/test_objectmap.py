"""Tests of the object map (``wardmap.server.objectmap``) on a temporary SQLite store.

Scenes are synthetic with known ground truth: objects at seeded random poses on a floor,
so every query can be checked against a brute-force filter over the same objects. The
clock is a counter, so first/last-seen values are exact.
"""

from __future__ import annotations

import itertools
import math
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import closing
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from wardmap.server.objectmap import (
    MAX_LIMIT,
    ObjectChange,
    ObjectMap,
    ObjectMapError,
    ObjectQuery,
    ObjectState,
    Observation,
    from_landmark,
    parse_near,
)
from wardmap.server.store import (
    APPLICATION_ID,
    MIGRATIONS,
    MapStore,
    StoreError,
    open_store,
    pose_blob,
)
from wardmap.shared import sqlitedb
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.se3 import yaw_transform

from .store.conftest import keyframe

KG = KnowledgeGraph.load()
CATS = KG.names
T0 = 1_714_557_600.0


class Clock:
    """Server clock that advances by one second per call."""

    def __init__(self) -> None:
        self.t = T0

    def __call__(self) -> float:
        self.t += 1.0
        return self.t


@pytest.fixture
def store(tmp_path: Path) -> Iterator[MapStore]:
    with open_store(f"sqlite:///{tmp_path / 'map.db'}") as s:
        yield s


@pytest.fixture
def om(store: MapStore) -> ObjectMap:
    return ObjectMap(store, knowledge=KG, clock=Clock())


def _obj(
    oid: int,
    x: float,
    y: float,
    z: float = 0.5,
    *,
    yaw: float = 0.0,
    category: str = "door",
    confidence: float = 0.9,
    size: tuple[float, float, float] = (1.0, 0.5, 2.0),
    color: tuple[float, float, float] | None = None,
) -> ObjectState:
    return ObjectState(oid, category, confidence, yaw_transform(x, y, yaw, z), np.array(size), color)


def _obs(
    oid: int, robot: str, seq: int, *, session: str = "s1", box: float = 0.0, category: str = "door"
) -> Observation:
    return Observation(
        oid,
        robot,
        session,
        seq,
        T0 + seq,
        category,
        0.8,
        np.array([box, box, box + 10.0, box + 20.0]),
        yaw_transform(1.0, 2.0, 0.3, 0.5),
        np.array([1.0, 0.5, 2.0]),
    )


def _random_scene(
    rng: np.random.Generator, n: int, floor: tuple[float, float] = (40.0, 20.0)
) -> list[ObjectState]:
    return [
        ObjectState(
            i + 1,
            CATS[int(rng.integers(len(CATS)))],
            float(rng.random()),
            yaw_transform(
                rng.uniform(0, floor[0]),
                rng.uniform(0, floor[1]),
                rng.uniform(-np.pi, np.pi),
                rng.uniform(0.0, 2.0),
            ),
            rng.uniform(0.1, 2.5, 3),
        )
        for i in range(n)
    ]


def _ids(page) -> list[int]:
    return [h.record.object_id for h in page.hits]


# --------------------------------------------------------------------------- writes


def test_upsert_creates_then_updates_with_derived_geometry(om: ObjectMap) -> None:
    """A door of size (2, 1, 1) turned by 90 degrees has world bounds 1 m wide in x and 2 m in y;
    a second upsert of the same id is an update that keeps first_seen_s."""
    changes = om.upsert([_obj(7, 3.0, 4.0, 1.0, yaw=math.pi / 2, size=(2.0, 1.0, 1.0), color=(10, 20, 30))])
    assert [c.kind for c in changes] == ["created"]
    r = changes[0].record
    assert r.object_id == 7 and r.category == "door" and r.position == pytest.approx((3.0, 4.0, 1.0))
    assert r.yaw == pytest.approx(math.pi / 2)
    assert r.bounds_min == pytest.approx((2.5, 3.0, 0.5)) and r.bounds_max == pytest.approx((3.5, 5.0, 1.5))
    assert r.color_rgb == (10.0, 20.0, 30.0) and r.n_observations == 0 and r.robots == ()
    assert r.first_seen_s == r.last_seen_s == T0 + 1
    assert np.allclose(r.T_world_object, yaw_transform(3.0, 4.0, math.pi / 2, 1.0))

    changes = om.upsert([_obj(7, 3.5, 4.0, 1.0, confidence=0.5)])
    assert [c.kind for c in changes] == ["updated"]
    r2 = changes[0].record
    assert r2.position == pytest.approx((3.5, 4.0, 1.0)) and r2.confidence == 0.5 and r2.color_rgb is None
    assert r2.first_seen_s == T0 + 1
    assert om.count() == 1


def test_observations_derive_count_robots_and_seen_times(om: ObjectMap) -> None:
    """Observations from two robots set the count, robots and last_seen; re-sending a measurement
    (same keyframe and box) under another object moves it and updates both objects."""
    om.upsert([_obj(1, 0, 0), _obj(2, 5, 0)])  # t = T0+1
    changes = om.add_observations([_obs(1, "r1", 0), _obs(1, "r2", 1), _obs(1, "r1", 2)])  # T0+2
    assert [(c.kind, c.record.object_id) for c in changes] == [("updated", 1)]
    r = changes[0].record
    assert r.n_observations == 3 and r.robots == ("r1", "r2")
    assert r.first_seen_s == T0 + 1 and r.last_seen_s == T0 + 2

    changes = om.add_observations([_obs(2, "r2", 1)])  # the r2 measurement now belongs to object 2
    by_id = {c.record.object_id: c.record for c in changes}
    assert set(by_id) == {1, 2} and all(c.kind == "updated" for c in changes)
    assert by_id[1].n_observations == 2 and by_id[1].robots == ("r1",)
    assert by_id[2].n_observations == 1 and by_id[2].robots == ("r2",)
    # Same measurement again: no new row.
    om.add_observations([_obs(2, "r2", 1)])
    assert om.get(2).record.n_observations == 1  # type: ignore[union-attr]


def test_upsert_objects_and_observations_in_one_transaction(om: ObjectMap) -> None:
    """New objects and their observations go in together; an observation of an unknown object
    rejects the whole call, so nothing of it is stored."""
    changes = om.upsert([_obj(1, 0, 0)], [_obs(1, "r1", 0)])
    assert changes[0].kind == "created" and changes[0].record.n_observations == 1
    with pytest.raises(ObjectMapError, match=r"neither given nor stored: \[99\]"):
        om.upsert([_obj(2, 1, 1)], [_obs(99, "r1", 5)])
    assert om.get(2) is None and om.count() == 1


@pytest.mark.parametrize(
    ("obj", "match"),
    [
        (_obj(1, 0, 0, category="unicorn"), "unknown category 'unicorn'; known: person, wheelchair"),
        (_obj(1, 0, 0, confidence=1.5), r"confidence: expected a number in \[0, 1\]"),
        (_obj(0, 0, 0), r"object_id: expected an int in \[1, 2\*\*63\)"),
        (_obj(1, 0, 0, size=(1.0, -1.0, 1.0)), "size: expected 3 finite extents >= 0"),
        (_obj(1, 0, 0, color=(0, 0, 300)), r"color_rgb: expected 3 values in \[0, 255\]"),
        (ObjectState(1, "door", 0.5, np.diag([2.0, 1, 1, 1]), np.ones(3)), "not a proper rotation"),
        (ObjectState(1, "door", 0.5, np.full((4, 4), np.nan), np.ones(3)), "non-finite"),
    ],
)
def test_bad_objects_are_rejected(om: ObjectMap, obj: ObjectState, match: str) -> None:
    """Every bad field of an object raises ObjectMapError naming it; nothing is stored."""
    with pytest.raises(ObjectMapError, match=match):
        om.upsert([obj])
    assert om.count() == 0


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"robot_id": "bad robot"}, "robot_id"),
        ({"session_id": ""}, "session_id"),
        ({"seq": -1}, "seq"),
        ({"stamp": float("nan")}, "stamp"),
        ({"category": "ghost"}, "unknown category"),
        ({"box_xyxy": np.array([5.0, 0.0, 1.0, 1.0])}, "box_xyxy"),
        ({"size": np.ones(2)}, "size"),
    ],
)
def test_bad_observations_are_rejected(om: ObjectMap, change: dict, match: str) -> None:
    """Every bad field of an observation raises ObjectMapError naming it."""
    om.upsert([_obj(1, 0, 0)])
    fields = dict(_obs(1, "r1", 0).__dict__)
    fields.update(change)
    with pytest.raises(ObjectMapError, match=match):
        om.add_observations([Observation(**fields)])
    assert om.get(1).record.n_observations == 0  # type: ignore[union-attr]


def test_duplicate_ids_in_one_upsert_are_rejected(om: ObjectMap) -> None:
    with pytest.raises(ObjectMapError, match="more than once"):
        om.upsert([_obj(1, 0, 0), _obj(1, 1, 1)])


def test_delete_and_merge(om: ObjectMap, store: MapStore) -> None:
    """Deleting removes an object from queries, the R*Tree and get; merging moves its observations
    and robots to the surviving object; unknown ids raise."""
    om.upsert(
        [_obj(1, 0, 0), _obj(2, 0.5, 0), _obj(3, 10, 10)],
        [_obs(1, "r1", 0), _obs(1, "r2", 1), _obs(2, "r3", 2)],
    )
    changes = om.delete(1, merged_into=2)
    assert [(c.kind, c.record.object_id, c.merged_into) for c in changes] == [
        ("deleted", 1, 2),
        ("updated", 2, None),
    ]
    assert changes[0].record.n_observations == 2  # the record as it was
    assert changes[1].record.n_observations == 3 and changes[1].record.robots == ("r1", "r2", "r3")
    assert om.get(1) is None
    assert _ids(om.query(near=(0, 0, 0.5), radius=2.0)) == [2]
    gone = om.delete(3)
    assert [(c.kind, c.record.object_id, c.merged_into) for c in gone] == [("deleted", 3, None)]
    assert om.get(3) is None and om.count() == 1
    with pytest.raises(ObjectMapError, match="unknown object 3"):
        om.delete(3)
    with pytest.raises(ObjectMapError, match=r"unknown object 42 \(merged_into\)"):
        om.delete(2, merged_into=42)
    with pytest.raises(ObjectMapError, match="into itself"):
        om.delete(2, merged_into=2)
    # The deleted object's observations went with it (the R*Tree: tests/server/store/test_sqlite.py).
    assert store.observation_counts() == {2: 3}


def test_listeners_get_changes_in_commit_order(om: ObjectMap) -> None:
    """Listeners see every change after its commit; a failing listener does not undo the write;
    a removed listener sees nothing more."""
    seen: list[tuple[str, int]] = []

    def bad(change: ObjectChange) -> None:
        raise RuntimeError("listener bug")

    remove = om.add_listener(lambda c: seen.append((c.kind, c.record.object_id)))
    om.add_listener(bad)
    om.upsert([_obj(1, 0, 0), _obj(2, 1, 0)])
    om.upsert([_obj(1, 0, 1)])
    om.delete(2)
    assert seen == [("created", 1), ("created", 2), ("updated", 1), ("deleted", 2)]
    assert om.count() == 1
    remove()
    om.upsert([_obj(3, 0, 0)])
    assert len(seen) == 4


# --------------------------------------------------------------------------- queries


def _brute(objs: list[ObjectState], q: ObjectQuery, robots: dict[int, set[str]]) -> list[int]:
    """The expected ids of ``q`` over ``objs`` (ignoring limit/offset)."""
    keep = []
    for o in objs:
        p = o.T_world_object[:3, 3]
        if q.category is not None and o.category != q.category:
            continue
        if q.min_confidence is not None and o.confidence < q.min_confidence:
            continue
        if q.robot is not None and q.robot not in robots.get(o.object_id, set()):
            continue
        d = None if q.near is None else float(np.linalg.norm(p - np.array(q.near)))
        if q.radius_m is not None and d is not None and d > q.radius_m:
            continue
        keep.append((d if d is not None else 0.0, o.object_id))
    return [oid for _, oid in sorted(keep)]


def test_every_filter_agrees_with_brute_force(om: ObjectMap) -> None:
    """400 random objects, observations by three robots: 60 random queries mixing every filter
    (R*Tree radius search included) return exactly the brute-force ids, in order, with
    distances that match."""
    rng = np.random.default_rng(1)
    objs = _random_scene(rng, 400)
    robots: dict[int, set[str]] = {}
    observations = []
    for k, o in enumerate(objs[::3]):
        robot = f"r{k % 3}"
        robots.setdefault(o.object_id, set()).add(robot)
        observations.append(_obs(o.object_id, robot, k))
    om.upsert(objs, observations)
    by_id = {o.object_id: o for o in objs}
    for i in range(60):
        near = tuple(float(v) for v in rng.uniform([0, 0, 0], [40, 20, 2])) if i % 4 else None
        q = ObjectQuery(
            category=CATS[int(rng.integers(len(CATS)))] if i % 3 == 0 else None,
            near=near,  # type: ignore[arg-type]
            radius_m=float(rng.uniform(0, 8)) if near is not None and i % 2 else None,
            min_confidence=float(rng.random()) if i % 5 == 0 else None,
            robot=f"r{i % 3}" if i % 7 == 0 else None,
            limit=MAX_LIMIT,
        )
        page = om.find(q)
        assert _ids(page) == _brute(objs, q, robots), q
        assert page.next_offset is None
        for h in page.hits:
            if near is None:
                assert h.distance_m is None
            else:
                p = by_id[h.record.object_id].T_world_object[:3, 3]
                assert h.distance_m == pytest.approx(np.linalg.norm(p - np.array(near)), abs=1e-9)


def test_rtree_radius_agrees_with_brute_force(om: ObjectMap) -> None:
    """1500 objects of random size and yaw: for 100 random centres and radii the R*Tree query
    returns the same set as an exact scan of the centres (that it searches the R*Tree:
    tests/server/store/test_sqlite.py)."""
    rng = np.random.default_rng(2)
    objs = _random_scene(rng, 1500, floor=(60.0, 30.0))
    om.upsert(objs)
    centres = np.array([o.T_world_object[:3, 3] for o in objs])
    for _ in range(100):
        c = rng.uniform([-5, -5, -1], [65, 35, 3])
        r = float(rng.choice([0.5, 2.0, 5.0, 12.0]))
        expected = {objs[i].object_id for i in np.flatnonzero(np.linalg.norm(centres - c, axis=1) <= r)}
        got = _ids(om.query(near=tuple(c), radius=r, limit=MAX_LIMIT))
        assert set(got) == expected and len(got) == len(expected)


def test_nearest_first_and_radius_edge(om: ObjectMap) -> None:
    """Objects on the x axis at 1, 2, 3 m (and a tie at 2 m on y) come nearest first with ties by id;
    an object exactly at the radius is included, one a hair beyond is not; radius 0 finds
    the object at the centre."""
    om.upsert([_obj(10, 3, 0, 0), _obj(11, 1, 0, 0), _obj(12, 2, 0, 0), _obj(13, 0, 2, 0), _obj(14, 0, 0, 0)])
    page = om.query(near=(0, 0, 0))
    assert _ids(page) == [14, 11, 12, 13, 10]
    assert [h.distance_m for h in page.hits] == pytest.approx([0, 1, 2, 2, 3])
    assert _ids(om.query(near=(0, 0, 0), radius=2.0)) == [14, 11, 12, 13]
    assert _ids(om.query(near=(0, 0, 0), radius=math.nextafter(2.0, 0.0))) == [14, 11]
    assert _ids(om.query(near=(0, 0, 0), radius=0.0)) == [14]
    assert _ids(om.query(near=(100, 100, 0), radius=5.0)) == []


def test_limit_and_offset_page_through_results(om: ObjectMap) -> None:
    """Pages of 7 with offsets concatenate to the full, ordered result; next_offset is None on the
    last page and an offset past the end gives an empty page."""
    rng = np.random.default_rng(3)
    om.upsert(_random_scene(rng, 50))
    for near in (None, (20.0, 10.0, 1.0)):
        full = _ids(om.query(near=near, limit=MAX_LIMIT))
        got, offset = [], 0
        while True:
            page = om.query(near=near, limit=7, offset=offset)
            got += _ids(page)
            if page.next_offset is None:
                break
            assert page.next_offset == offset + 7
            offset = page.next_offset
        assert got == full and len(full) == 50
        assert _ids(om.query(near=near, offset=50)) == []
    last = om.query(limit=10, offset=40)
    assert len(last.hits) == 10 and last.next_offset is None


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"radius_m": 3.0}, "radius needs near"),
        ({"near": (0, 0, 0), "radius_m": -1.0}, "radius must be a finite number >= 0"),
        ({"near": (0, 0, 0), "radius_m": float("inf")}, "radius must be"),
        ({"near": (0, float("nan"), 0)}, "near must be three finite numbers"),
        ({"near": (0, 1e155, 0)}, r"within \+-1e\+06 m"),
        ({"min_confidence": 1.5}, r"min_confidence must be in \[0, 1\]"),
        ({"robot": "no spaces"}, "bad robot id"),
        ({"limit": 0}, "limit must be"),
        ({"limit": MAX_LIMIT + 1}, "limit must be"),
        ({"offset": -1}, "offset must be"),
        ({"category": ""}, "category must be a non-empty str"),
    ],
)
def test_bad_queries_raise(kwargs: dict, match: str) -> None:
    with pytest.raises(ObjectMapError, match=match):
        ObjectQuery(**kwargs)


def test_unknown_category_lists_the_knowledge_graph(om: ObjectMap) -> None:
    with pytest.raises(
        ObjectMapError, match="unknown category 'unicorn'; known categories: person, wheelchair"
    ):
        om.query(category="unicorn")


def test_query_from_text_parameters() -> None:
    """The zenoh selector form parses into the same query; bad, unknown and repeated keys raise."""
    q = ObjectQuery.from_params(
        [
            ("category", "door"),
            ("near", "1,2.5,-3"),
            ("radius", "3"),
            ("min_confidence", "0.5"),
            ("robot", "r1"),
            ("limit", "5"),
            ("offset", "10"),
        ]
    )
    assert q == ObjectQuery("door", (1.0, 2.5, -3.0), 3.0, 0.5, "r1", 5, 10)
    assert ObjectQuery.from_params([]) == ObjectQuery()
    assert ObjectQuery.from_params([("include_unconfirmed", "true")]).include_unconfirmed
    for params, match in [
        ([("near", "1,2")], "near must be three finite numbers"),
        ([("near", "a,b,c")], "near must be"),
        ([("radius", "x"), ("near", "0,0,0")], "radius must be a number"),
        ([("limit", "1.5")], "limit must be an integer"),
        ([("colour", "red")], "unknown parameter 'colour'"),
        ([("limit", "1"), ("limit", "2")], "given twice"),
        ([("radius", "2")], "radius needs near"),
        ([("include_unconfirmed", "yes")], "include_unconfirmed must be true or false"),
    ]:
        with pytest.raises(ObjectMapError, match=match):
            ObjectQuery.from_params(params)
    assert parse_near(" 1, 2 ,3") == (1.0, 2.0, 3.0)


# --------------------------------------------------------------------------- get / categories


def test_get_returns_observations_and_keyframes(om: ObjectMap, store: MapStore) -> None:
    """get() gives the newest observations first (capped), the keyframes they came from and whether
    the store holds each keyframe; unknown ids give None."""
    store.insert(*keyframe("r1", "s1", 1, stamp=T0 + 1), T0)
    om.upsert([_obj(1, 0, 0)], [_obs(1, "r1", 0)])
    om.add_observations([_obs(1, "r1", 1), _obs(1, "r2", 2, box=5.0)])
    detail = om.get(1)
    assert detail is not None and detail.record.n_observations == 3
    assert [(o.robot_id, o.seq) for o in detail.observations] == [("r2", 2), ("r1", 1), ("r1", 0)]
    o = detail.observations[0]
    assert o.box_xyxy.tolist() == [5.0, 5.0, 15.0, 25.0] and o.stamp == T0 + 2 and o.category == "door"
    assert np.allclose(o.T_world_object, yaw_transform(1.0, 2.0, 0.3, 0.5))
    assert [(k.robot_id, k.seq, k.stored) for k in detail.keyframes] == [
        ("r1", 0, False),
        ("r1", 1, True),
        ("r2", 2, False),
    ]
    capped = om.get(1, max_observations=1)
    assert capped is not None and len(capped.observations) == 1 and len(capped.keyframes) == 1
    assert om.get(2) is None
    with pytest.raises(ObjectMapError):
        om.get(0)
    with pytest.raises(ObjectMapError):
        om.get(1, max_observations=-1)


def test_categories_count_every_class(om: ObjectMap) -> None:
    om.upsert([_obj(1, 0, 0), _obj(2, 1, 0), _obj(3, 2, 0, category="bed")])
    counts = om.categories()
    assert list(counts) == list(CATS)
    assert counts["door"] == 2 and counts["bed"] == 1 and sum(counts.values()) == 3


def test_from_landmark_adapter(om: ObjectMap) -> None:
    """A landmark's plain fields and measurements (server keyframe keys) become an ObjectState and
    Observations the map stores; offline keyframe keys are refused."""
    m = SimpleNamespace(
        keyframe="r7/sessA/12",
        stamp=T0,
        category="bed",
        confidence=0.7,
        box_xyxy=np.array([1.0, 2.0, 3.0, 4.0]),
        T_world_object=yaw_transform(1, 1, 0, 0.5),
        size=np.array([2.0, 1.0, 0.6]),
    )
    state, obs = from_landmark(5, "bed", 0.8, yaw_transform(1, 1, 0, 0.5), [2.0, 1.0, 0.6], [m])
    assert (obs[0].robot_id, obs[0].session_id, obs[0].seq) == ("r7", "sessA", 12)
    changes = om.upsert([state], obs)
    assert changes[0].record.robots == ("r7",) and changes[0].record.n_observations == 1
    with pytest.raises(ObjectMapError, match="is not '<robot>/<session>/<seq>'"):
        from_landmark(
            6, "bed", 0.8, np.eye(4), [1, 1, 1], [SimpleNamespace(**{**m.__dict__, "keyframe": "ds/1.5"})]
        )


def test_readers_on_other_threads_see_committed_state(om: ObjectMap) -> None:
    """Queries from several threads while one thread writes: each sees a whole batch of 10
    (transactions are atomic), and never an error."""
    errors: list[BaseException] = []
    stop = threading.Event()

    def reader() -> None:
        try:
            while not stop.is_set():
                n = len(om.query(limit=MAX_LIMIT).hits)
                assert n % 10 == 0, n
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=reader) for _ in range(3)]
    for t in threads:
        t.start()
    ids = itertools.count(1)
    for _ in range(20):
        om.upsert([_obj(next(ids), float(k), 0.0) for k in range(10)])
    stop.set()
    for t in threads:
        t.join(10)
    assert not errors and om.count() == 200


# --------------------------------------------------------------------------- migration


def test_v1_store_migrates_to_the_object_map(tmp_path: Path) -> None:
    """A keyframe store written at schema v1 opens at the latest version with its rows intact, and
    the object map (tables and R*Tree) works on it."""
    path = tmp_path / "v1.db"
    v1 = sqlitedb.SqliteKind("keyframe store", APPLICATION_ID, MIGRATIONS[:1], StoreError)
    conn = sqlitedb.connect(path, v1)
    sqlitedb.check_and_migrate(conn, path, v1)
    conn.execute("INSERT INTO robots VALUES ('r1', 1.0, 2.0)")
    conn.close()
    with closing(sqlite3.connect(path)) as raw:
        assert raw.execute("PRAGMA user_version").fetchone()[0] == 1
        assert raw.execute("SELECT name FROM sqlite_master WHERE name = 'objects'").fetchone() is None
    with open_store(f"sqlite:///{path}") as store:
        assert store.stats().schema_version == len(MIGRATIONS) == 14
        assert [(r.robot_id, r.keyframes) for r in store.robots()] == [("r1", 0)]
        om = ObjectMap(store, knowledge=KG, clock=Clock())
        om.upsert([_obj(1, 0, 0)])
        assert _ids(om.query(near=(0, 0, 0), radius=1.0)) == [1]


# --------------------------------------------------------------------------- confirmation


def test_unconfirmed_objects_are_kept_but_left_out_of_queries_unless_asked(om: ObjectMap) -> None:
    """An object stored with ``confirmed=False`` is in the map (get, count) but every query, the
    radius query included, and the category counts leave it out unless asked; once association
    confirms it, an upsert brings it back to every query."""
    cabinet = replace(_obj(2, 1.0, 0.0, category="cabinet"), confirmed=False)
    om.upsert([_obj(1, 0.0, 0.0, category="cabinet"), cabinet])
    assert _ids(om.query()) == [1]
    assert _ids(om.query(category="cabinet", near=(1.0, 0.0, 0.5), radius=2.0)) == [1]
    assert _ids(om.query(near=(1.0, 0.0, 0.5), radius=2.0, include_unconfirmed=True)) == [2, 1]
    assert _ids(om.find(ObjectQuery.from_params([("include_unconfirmed", "true")]))) == [1, 2]
    assert om.categories()["cabinet"] == 1 and om.categories(include_unconfirmed=True)["cabinet"] == 2
    assert (om.count(), om.count(unconfirmed=True), om.count(unconfirmed=False)) == (2, 1, 1)
    detail = om.get(2)
    assert detail is not None and detail.record.confirmed is False
    (change,) = om.upsert([replace(cabinet, confirmed=True)])
    assert change.record.confirmed is True
    assert _ids(om.query()) == [1, 2]
    with pytest.raises(ObjectMapError, match=r"objects\[0\].confirmed: expected a bool"):
        om.upsert([replace(cabinet, confirmed=1)])  # type: ignore[arg-type]


def test_v6_store_migrates_with_its_objects_confirmed(tmp_path: Path) -> None:
    """An object written at schema v6 (no ``confirmed`` column) opens at the latest version as a
    confirmed object: the map shows what it showed before."""
    path = tmp_path / "v6.db"
    v6 = sqlitedb.SqliteKind("keyframe store", APPLICATION_ID, MIGRATIONS[:6], StoreError)
    conn = sqlitedb.connect(path, v6)
    sqlitedb.check_and_migrate(conn, path, v6)
    T = pose_blob(np.eye(4))
    conn.execute(
        "INSERT INTO objects VALUES (7, 'door', 0.9, ?, 0, 0, 1, 0, 0, 0, 0, 1, 1, 0.1, 2, "
        "-0.5, -0.05, 0, 0.5, 0.05, 2, NULL, NULL, NULL, 0, 1.0, 1.0)",
        (T,),
    )
    conn.execute("INSERT INTO objects_rtree VALUES (7, -0.5, 0.5, -0.05, 0.05, 0, 2)")
    conn.close()
    with open_store(f"sqlite:///{path}") as store:
        assert store.stats().schema_version == len(MIGRATIONS)
        om = ObjectMap(store, knowledge=KG, clock=Clock())
        assert _ids(om.query(near=(0, 0, 1), radius=1.0)) == [7]
        assert om.query().hits[0].record.confirmed is True

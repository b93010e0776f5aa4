"""Tests of the zenoh map service (``wardmap.server.mapserve``) on loopback.

A real zenoh router runs on a thread (``run_router``, free port, shared memory and multicast
scouting off); the service's session (opened with the server's one helper,
``open_session``) and this test's client session connect to it as clients. The test waits
on zenoh replies and channel receives with timeouts, never on sleeps.
"""

from __future__ import annotations

import json
import queue
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

zenoh = pytest.importorskip("zenoh")

from wardmap.server.mapmessages import map_object, objects_reply  # noqa: E402  (after the importorskip guard)
from wardmap.server.mapserve import (  # noqa: E402
    OBJECTS_KEY,
    UPDATES_KEY,
    MapServe,
    MapServeError,
)
from wardmap.server.objectmap import ObjectMap, ObjectState  # noqa: E402
from wardmap.server.store import SqliteKeyframeStore, open_store  # noqa: E402
from wardmap.server.zenoh_session import open_session  # noqa: E402
from wardmap.shared.knowledge import KnowledgeGraph  # noqa: E402
from wardmap.shared.mapwire import (  # noqa: E402
    MapError,
    MapUpdate,
    ObjectsReply,
    decode_map_message,
    encode_map_message,
)
from wardmap.shared.se3 import quat_to_rotation, yaw_transform  # noqa: E402
from wardmap.shared.zenoh_config import client_config  # noqa: E402

pytestmark = pytest.mark.timeout(60)

TIMEOUT_S = 10.0


def _obj(oid: int, category: str, x: float, y: float, confidence: float = 0.9, **kw: Any) -> ObjectState:
    return ObjectState(
        oid, category, confidence, yaw_transform(x, y, 0.1 * oid, 0.0), np.array([1.0, 0.5, 2.0]), **kw
    )


@pytest.fixture
def objects(tmp_path: Path) -> Iterator[ObjectMap]:
    store: SqliteKeyframeStore = open_store(f"sqlite:///{tmp_path / 'map.db'}")
    try:
        om = ObjectMap(store)
        om.upsert(
            [_obj(1, "door", 1, 2), _obj(2, "door", 2, 2), _obj(3, "door", 20, 2), _obj(4, "bed", 1, 3)]
        )
        yield om
    finally:
        store.close()


@pytest.fixture
def session(router: str) -> Iterator[Any]:
    """The server side's session, as the composition root opens it."""
    with open_session([router]) as s:
        yield s


@pytest.fixture
def service(session: Any, objects: ObjectMap) -> Iterator[MapServe]:
    with MapServe(session, objects) as ms:
        yield ms


@pytest.fixture
def client(router: str) -> Iterator[Any]:
    with zenoh.open(zenoh.Config.from_json5(json.dumps(client_config([router])))) as session:
        yield session


def _get(client: Any, selector: str) -> list[Any]:
    """All replies to ``selector`` (blocks until the query is finished)."""
    return list(client.get(selector, timeout=TIMEOUT_S))


def _ok(client: Any, selector: str) -> ObjectsReply:
    replies = _get(client, selector)
    assert len(replies) == 1, replies
    assert replies[0].ok is not None, decode_map_message(replies[0].err.payload.to_bytes())
    assert str(replies[0].ok.key_expr) == OBJECTS_KEY
    msg = decode_map_message(replies[0].ok.payload.to_bytes())
    assert isinstance(msg, ObjectsReply)
    return msg


def _err(client: Any, selector: str) -> str:
    replies = _get(client, selector)
    assert len(replies) == 1 and replies[0].err is not None, replies
    message = decode_map_message(replies[0].err.payload.to_bytes())
    assert isinstance(message, MapError)
    return message.detail


def test_queryable_answers_with_the_rest_filters(service: MapServe, client: Any, objects: ObjectMap) -> None:
    """The selector parameters filter like GET /v1/objects; the reply is the same page the
    map gives, nearest first, with poses in the wire convention."""
    msg = _ok(client, f"{OBJECTS_KEY}?category=door;near=1,2,0;radius=3")
    assert msg.next_offset is None
    assert [o.object_id for o in msg.objects] == [1, 2]
    assert [o.distance_m for o in msg.objects] == pytest.approx([0.0, 1.0])
    first = msg.objects[0]
    assert first.category == "door" and first.position == pytest.approx([1, 2, 0])
    assert np.allclose(quat_to_rotation(first.q_xyzw), yaw_transform(0, 0, 0.1)[:3, :3])
    assert first.size == (1.0, 0.5, 2.0) and first.robots == () and first.color_rgb is None

    everything = _ok(client, OBJECTS_KEY)
    assert [o.object_id for o in everything.objects] == [1, 2, 3, 4]
    assert all(o.distance_m is None for o in everything.objects)
    page = _ok(client, f"{OBJECTS_KEY}?limit=2;offset=1")
    assert [o.object_id for o in page.objects] == [2, 3] and page.next_offset == 3
    assert [o.object_id for o in _ok(client, f"{OBJECTS_KEY}?min_confidence=0.95").objects] == []
    assert service.counters().queries == 4


def test_reply_is_the_documented_object_map(service: MapServe, client: Any, objects: ObjectMap) -> None:
    """On the wire a reply is ``{schema, version, objects, next_offset}`` and each object carries
    its colour and the pose both as ``T_world_object`` and flat (the REST fields)."""
    objects.upsert([_obj(9, "chair", 5, 5, color_rgb=(10.0, 20.0, 30.0))])
    replies = _get(client, f"{OBJECTS_KEY}?category=chair")
    raw = msgpack.unpackb(replies[0].ok.payload.to_bytes())
    assert raw["schema"] == "wardmap.map.objects" and raw["version"] == 1 and raw["next_offset"] is None
    (obj,) = raw["objects"]
    assert obj["color_rgb"] == [10.0, 20.0, 30.0] and obj["distance_m"] is None
    assert obj["T_world_object"] == {"t": obj["position"], "q_xyzw": obj["q_xyzw"]}
    assert obj["T_world_object"]["t"] == pytest.approx([5, 5, 0])


@pytest.mark.parametrize(
    ("params", "detail"),
    [
        ("radius=3", "radius needs near"),
        ("near=1,2", "near must be three finite numbers"),
        ("near=0,0,0;radius=-2", "radius must be a finite number >= 0"),
        ("category=unicorn", "unknown category 'unicorn'; known categories: person"),
        ("colour=red", "unknown parameter 'colour'"),
        ("limit=0", "limit must be an int in [1, 1000]"),
        ("limit=1;limit=2", "given twice"),
    ],
)
def test_bad_parameters_get_a_reply_error(service: MapServe, client: Any, params: str, detail: str) -> None:
    """Bad parameters are answered with a reply error naming the problem; the service keeps serving."""
    assert detail in _err(client, f"{OBJECTS_KEY}?{params}")
    assert service.counters().query_errors == 1
    assert len(_ok(client, f"{OBJECTS_KEY}?category=bed").objects) == 1


def test_every_change_is_published_in_order(service: MapServe, client: Any, objects: ObjectMap) -> None:
    """Creations, updates and a merge-delete reach a subscriber of wardmap/v1/map/updates in commit order."""
    samples: queue.Queue[Any] = queue.Queue()
    client.declare_subscriber(UPDATES_KEY, samples.put)
    _ok(client, f"{OBJECTS_KEY}?limit=1")  # a round trip through the router: the subscription is known there
    objects.upsert([_obj(10, "wheelchair", 5, 5), _obj(1, "door", 1.5, 2)])
    objects.delete(2, merged_into=1)
    got: list[MapUpdate] = []
    for _ in range(4):
        try:
            sample = samples.get(timeout=TIMEOUT_S)
        except queue.Empty:
            pytest.fail(f"only {len(got)} updates arrived")
        assert str(sample.key_expr) == UPDATES_KEY
        update = decode_map_message(sample.payload.to_bytes())
        assert isinstance(update, MapUpdate)
        got.append(update)
    assert [(m.kind, m.object.object_id, m.merged_into) for m in got] == [
        ("created", 10, None),
        ("updated", 1, None),
        ("deleted", 2, 1),
        ("updated", 1, None),
    ]
    assert got[0].object.category == "wheelchair" and got[1].object.position[0] == 1.5
    assert service.counters().updates == 4 and service.counters().update_failures == 0


def test_stop_is_clean_and_idempotent(session: Any, objects: ObjectMap) -> None:
    """After stop() the map still accepts writes (the listener is gone, nothing is counted as lost),
    a second stop() is harmless, a started service cannot be started again, and the session it
    was given stays open for its owner: a new service starts on it."""
    ms = MapServe(session, objects)
    ms.start()
    with pytest.raises(MapServeError, match="already started"):
        ms.start()
    ms.stop()
    ms.stop()
    objects.upsert([_obj(11, "bed", 0, 0)])
    assert ms.counters().updates == 0 and ms.counters().update_failures == 0
    assert not session.is_closed()
    with MapServe(session, objects):
        pass


def test_closed_session_is_a_clear_error(router: str, objects: ObjectMap) -> None:
    """A service given a session that is already closed fails to start with MapServeError."""
    s = open_session([router])
    s.close()
    with pytest.raises(MapServeError, match="cannot declare the queryable"):
        MapServe(s, objects).start()


def test_wire_round_trip(objects: ObjectMap) -> None:
    """A page of the map encodes to the reply the queryable sends and decodes to the same objects."""
    page = objects.query(near=(1.0, 2.0, 0.0), radius=1.0)
    msg = decode_map_message(encode_map_message(objects_reply(page)))
    assert isinstance(msg, ObjectsReply)
    assert [o.object_id for o in msg.objects] == [1, 2, 4]  # ties (1 m) by id
    assert msg.objects[0] == map_object(page.hits[0].record, page.hits[0].distance_m)


def test_run_server_serves_the_map_over_rest_and_zenoh(router: str, client: Any, tmp_path: Path) -> None:
    """``run_server`` (what ``wardmap server`` runs) serves the object map over both REST and the
    zenoh queryable, with the same validation and the same object fields and values, and stops
    cleanly."""
    import httpx

    from wardmap.server.app import run_server

    db = f"sqlite:///{tmp_path / 'server.db'}"
    with open_store(db) as store:
        ObjectMap(store).upsert([_obj(5, "chair", 3, 4, color_rgb=(1.0, 2.0, 3.0))])
    stop, ready = threading.Event(), threading.Event()
    urls: list[str] = []
    errors: list[BaseException] = []

    def on_ready(url: str) -> None:
        urls.append(url)
        ready.set()

    def target() -> None:
        try:
            run_server([router], db, "127.0.0.1", 0, stop=stop, on_ready=on_ready, insecure_loopback=True)
        except BaseException as exc:  # surfaced below
            errors.append(exc)
            ready.set()

    worker = threading.Thread(target=target, daemon=True)
    worker.start()
    try:
        assert ready.wait(30) and not errors, errors
        assert _ok(client, f"{OBJECTS_KEY}?category=door").objects == ()
        (reply,) = _get(client, f"{OBJECTS_KEY}?near=0,0,0")
        zenoh_objects = msgpack.unpackb(reply.ok.payload.to_bytes())["objects"]
        with httpx.Client(base_url=urls[0], timeout=TIMEOUT_S) as http:
            resp = http.get("/v1/objects", params={"category": "door"})
            assert resp.status_code == 200 and resp.json()["objects"] == []
            assert http.get("/v1/objects", params={"radius": "1"}).status_code == 422
            cats = http.get("/v1/categories").json()
            assert cats["total"] == 1 and len(cats["categories"]) == len(KnowledgeGraph.load().names)
            rest_objects = http.get("/v1/objects", params={"near": "0,0,0"}).json()["objects"]
        assert rest_objects == zenoh_objects and rest_objects[0]["color_rgb"] == [1.0, 2.0, 3.0]
    finally:
        stop.set()
        worker.join(30)
    assert not worker.is_alive()

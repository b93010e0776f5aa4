"""``GET /v1/objects`` and ``/v1/objects/{id}`` (``server/api/routes/objects.py``) over the
object scene of ``conftest.py``: doors, a bed and a wheelchair on a line, observed by two
robots. Every filter and every 404/422 path is hit, and every list response is validated
against the documented :class:`ObjectList` model."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from wardmap.server.api import ObjectList, ObjectOut
from wardmap.server.app import MapServer
from wardmap.server.objectmap import ObjectMap, ObjectState
from wardmap.server.store import open_store
from wardmap.shared.knowledge import KnowledgeGraph
from wardmap.shared.mapwire import MapObject, object_from_wire
from wardmap.shared.se3 import quat_to_rotation, yaw_transform


def _ids(resp: Any) -> list[int]:
    assert resp.status_code == 200, resp.text
    ObjectList.model_validate(resp.json(), strict=True)  # the documented schema is the one served
    return [o["object_id"] for o in resp.json()["objects"]]


def test_list_all_objects_with_every_field(object_client: TestClient) -> None:
    """Without filters every object comes, by id, with its pose, size, bounds and robots."""
    resp = object_client.get("/v1/objects")
    assert _ids(resp) == [1, 2, 3, 4, 5]
    body = resp.json()
    assert body["limit"] == 100 and body["offset"] == 0 and body["next_offset"] is None
    o = body["objects"][2]
    assert o["category"] == "bed" and o["confidence"] == 0.95 and o["robots"] == ["r1", "r2"]
    assert o["position"] == pytest.approx([1.0, 0.0, 0.5]) and o["size"] == [1.0, 0.5, 2.0]
    assert o["yaw"] == pytest.approx(0.75) and o["distance_m"] is None and o["n_observations"] == 2
    R = quat_to_rotation(o["q_xyzw"])
    assert np.allclose(R, yaw_transform(0, 0, 0.75)[:3, :3])
    half_x = 0.5 * (abs(math.cos(0.75)) * 1.0 + abs(math.sin(0.75)) * 0.5)
    assert o["bounds_min"][0] == pytest.approx(1.0 - half_x) and o["bounds_max"][2] == pytest.approx(1.5)
    assert body["objects"][3]["robots"] == [] and body["objects"][3]["n_observations"] == 0


def test_objects_are_the_shared_map_message(object_client: TestClient) -> None:
    """An object's JSON is the map message Zenoh sends (``shared/mapwire.py``): the documented
    fields exactly, the pose both flat (``position``, ``q_xyzw``) and as ``T_world_object``,
    ``color_rgb`` null when unknown; it decodes as a :class:`MapObject`."""
    wire_fields = [f.name for f in dataclasses.fields(MapObject)] + ["T_world_object"]
    assert set(ObjectOut.model_fields) == set(wire_fields)
    for path in ("/v1/objects", "/v1/objects?near=1,0,0.5"):
        for o in object_client.get(path).json()["objects"]:
            assert set(o) == set(wire_fields)
            assert o["T_world_object"] == {"t": o["position"], "q_xyzw": o["q_xyzw"]}
            assert o["color_rgb"] is None
            assert object_from_wire(o).object_id == o["object_id"]
    detail = object_client.get("/v1/objects/3").json()["object"]
    assert detail == object_client.get("/v1/objects").json()["objects"][2]


def test_colour_is_listed(tmp_path: Path) -> None:
    """An object with a known mean colour carries it as ``color_rgb`` in both routes."""
    url = f"sqlite:///{tmp_path / 'map.db'}"
    with open_store(url) as store:
        ObjectMap(store).upsert([ObjectState(1, "chair", 0.8, yaw_transform(1.0, 2.0, 0.0, 0.5),
                                             np.array([0.5, 0.5, 0.9]), color_rgb=(200.0, 30.5, 12.0))])
    with TestClient(MapServer(url, require_tokens=False).app) as c:
        assert c.get("/v1/objects").json()["objects"][0]["color_rgb"] == [200.0, 30.5, 12.0]
        assert c.get("/v1/objects/1").json()["object"]["color_rgb"] == [200.0, 30.5, 12.0]


def test_category_filter(object_client: TestClient) -> None:
    assert _ids(object_client.get("/v1/objects", params={"category": "door"})) == [1, 2, 5]
    assert _ids(object_client.get("/v1/objects", params={"category": "sink"})) == []


def test_near_orders_nearest_first_with_distance(object_client: TestClient) -> None:
    """near=3,0,0.5: distances 3 (id 1), 1 (2), 2 (3), 0.5 (4), 7 (5) give the order 4, 2, 3, 1, 5."""
    resp = object_client.get("/v1/objects", params={"near": "3,0,0.5"})
    assert _ids(resp) == [4, 2, 3, 1, 5]
    assert [o["distance_m"] for o in resp.json()["objects"]] == pytest.approx([0.5, 1, 2, 3, 7])


def test_near_with_radius(object_client: TestClient) -> None:
    c = object_client
    assert _ids(c.get("/v1/objects", params={"near": "3,0,0.5", "radius": 2})) == [4, 2, 3]
    assert _ids(c.get("/v1/objects", params={"near": "3,0,0.5", "radius": 0.25})) == []
    assert _ids(c.get("/v1/objects", params={"near": "3,0,0.5", "radius": 3, "category": "door"})) == [2, 1]


def test_min_confidence_and_robot_filters(object_client: TestClient) -> None:
    c = object_client
    assert _ids(c.get("/v1/objects", params={"min_confidence": 0.8})) == [1, 3, 5]
    assert _ids(c.get("/v1/objects", params={"robot": "r2"})) == [2, 3]
    assert _ids(c.get("/v1/objects", params={"robot": "r1", "min_confidence": 0.85})) == [1, 3]
    assert _ids(c.get("/v1/objects", params={"robot": "r9"})) == []


def test_limit_and_offset(object_client: TestClient) -> None:
    c = object_client
    first = c.get("/v1/objects", params={"limit": 2})
    assert _ids(first) == [1, 2] and first.json()["next_offset"] == 2
    second = c.get("/v1/objects", params={"limit": 2, "offset": 2})
    assert _ids(second) == [3, 4] and second.json()["next_offset"] == 4
    last = c.get("/v1/objects", params={"limit": 2, "offset": 4})
    assert _ids(last) == [5] and last.json()["next_offset"] is None
    assert _ids(c.get("/v1/objects", params={"near": "3,0,0.5", "limit": 2, "offset": 1})) == [2, 3]


@pytest.mark.parametrize(
    ("params", "detail"),
    [
        ({"near": "1,2"}, "near must be three finite numbers 'x,y,z' in metres, got '1,2'"),
        ({"near": "a,b,c"}, "near must be three finite numbers"),
        ({"near": "1,2,nan"}, "near must be three finite numbers"),
        ({"near": "1e155,0,0"}, "each within +-1e+06"),  # its distance overflowed: a 500 once
        ({"near": "0,-1e300,0", "radius": "1e300"}, "each within +-1e+06"),
        ({"radius": "2"}, "radius needs near=x,y,z"),
        ({"near": "0,0,0", "radius": "-1"}, "radius must be a finite number >= 0 metres, got -1.0"),
        ({"near": "0,0,0", "radius": "inf"}, "radius must be a finite number >= 0"),
        ({"min_confidence": "1.5"}, "min_confidence must be in [0, 1], got 1.5"),
        ({"robot": "r 1"}, "bad robot id 'r 1'"),
    ],
)
def test_bad_filters_are_422_with_a_message(object_client: TestClient, params: dict, detail: str) -> None:
    resp = object_client.get("/v1/objects", params=params)
    assert resp.status_code == 422
    assert detail in resp.json()["detail"]


def test_unknown_category_is_422_listing_the_knowledge_graph(object_client: TestClient) -> None:
    resp = object_client.get("/v1/objects", params={"category": "unicorn"})
    assert resp.status_code == 422
    detail = resp.json()["detail"]
    assert detail.startswith("unknown category 'unicorn'; known categories: ")
    assert detail.endswith(", ".join(KnowledgeGraph.load().names))


@pytest.mark.parametrize(
    "params",
    [{"limit": 0}, {"limit": 1001}, {"offset": -1}, {"limit": "ten"}, {"radius": "x", "near": "0,0,0"}],
)
def test_bad_numbers_are_422(object_client: TestClient, params: dict) -> None:
    """Type and range errors of numeric parameters are FastAPI's 422 (a list naming the parameter)."""
    resp = object_client.get("/v1/objects", params=params)
    assert resp.status_code == 422
    assert resp.json()["detail"][0]["loc"][-1] in params


def test_object_detail(object_client: TestClient, object_scene: Any) -> None:
    """GET /v1/objects/3: the bed with both observations (newest first) and their keyframes."""
    resp = object_client.get("/v1/objects/3")
    assert resp.status_code == 200, resp.text
    body = resp.json()
    assert body["object"]["object_id"] == 3 and body["object"]["category"] == "bed"
    assert [(o["robot_id"], o["seq"]) for o in body["observations"]] == [("r2", 31), ("r1", 30)]
    o = body["observations"][0]
    assert o["box_xyxy"] == [0.0, 0.0, 8.0, 9.0] and o["position"] == pytest.approx([1.0, 0.1, 0.5])
    assert o["stamp"] == object_scene.t0 + 3 and o["q_xyzw"] == pytest.approx([0, 0, 0, 1])
    assert [(k["robot_id"], k["session_id"], k["seq"], k["stored"]) for k in body["keyframes"]] == [
        ("r1", "s1", 30, False),
        ("r2", "s1", 31, False),
    ]
    one = object_client.get("/v1/objects/3", params={"observations": 1}).json()
    assert len(one["observations"]) == 1 and len(one["keyframes"]) == 1


def test_object_detail_errors(object_client: TestClient) -> None:
    c = object_client
    resp = c.get("/v1/objects/999")
    assert resp.status_code == 404 and resp.json() == {"detail": "unknown object 999"}
    resp = c.get("/v1/objects/0")
    assert resp.status_code == 422 and "object_id: expected an int in [1, 2**63)" in resp.json()["detail"]
    assert c.get("/v1/objects/door").status_code == 422
    assert c.get("/v1/objects/3", params={"observations": 5000}).status_code == 422


def test_openapi_documents_the_object_routes(object_client: TestClient) -> None:
    spec = object_client.get("/openapi.json").json()
    params = {p["name"] for p in spec["paths"]["/v1/objects"]["get"]["parameters"]}
    assert params == {
        "category", "near", "radius", "min_confidence", "robot", "limit", "offset", "include_unconfirmed",
        "format",
    }
    assert {"200", "400", "422"} <= set(spec["paths"]["/v1/objects"]["get"]["responses"])
    assert {"200", "404", "422"} <= set(spec["paths"]["/v1/objects/{object_id}"]["get"]["responses"])
    assert "/v1/categories" in spec["paths"]
    properties = spec["components"]["schemas"]["ObjectOut"]["properties"]
    assert {"distance_m", "confirmed", "color_rgb", "T_world_object"} <= set(properties)


def test_unconfirmed_objects_only_when_asked(tmp_path: Path) -> None:
    """An unconfirmed object (a flat sliver association has not confirmed) is left out of the list,
    the radius query and the category counts unless ``include_unconfirmed=true``; the detail
    route and /metrics still show it; a bad flag is a 422."""
    url = f"sqlite:///{tmp_path / 'map.db'}"
    with open_store(url) as store:
        ObjectMap(store).upsert([
            ObjectState(1, "cabinet", 0.9, yaw_transform(0.0, 0.0, 0.0, 0.5), np.array([0.8, 0.5, 1.7])),
            ObjectState(2, "cabinet", 0.7, yaw_transform(1.0, 0.0, 0.0, 0.5), np.array([0.3, 0.02, 0.6]),
                        confirmed=False),
        ])
    with TestClient(MapServer(url, require_tokens=False).app) as c:
        assert _ids(c.get("/v1/objects")) == [1]
        assert _ids(c.get("/v1/objects", params={"near": "1,0,0.5", "radius": 2})) == [1]
        resp = c.get("/v1/objects", params={"near": "1,0,0.5", "radius": 2, "include_unconfirmed": "true"})
        assert _ids(resp) == [2, 1]
        assert [o["confirmed"] for o in resp.json()["objects"]] == [False, True]
        listed = c.get("/v1/categories").json()
        counts = {k["name"]: k["count"] for k in listed["categories"]}
        assert counts["cabinet"] == 1
        every = c.get("/v1/categories", params={"include_unconfirmed": "true"}).json()
        assert {k["name"]: k["count"] for k in every["categories"]}["cabinet"] == 2 and every["total"] == 2
        assert c.get("/v1/objects/2").json()["object"]["confirmed"] is False
        samples = {}
        for line in c.get("/metrics").text.splitlines():
            if line and not line.startswith("#"):
                name, value = line.rsplit(" ", 1)
                samples[name] = float(value)
        assert samples['wardmap_map_objects{confirmed="true"}'] == 1
        assert samples['wardmap_map_objects{confirmed="false"}'] == 1
        for word in ("maybe", "1", "yes", "True"):  # the Zenoh parser's words only: true, false
            for path in ("/v1/objects", "/v1/categories"):
                bad = c.get(path, params={"include_unconfirmed": word})
                assert bad.status_code == 422, (path, word)
                assert bad.json()["detail"][0]["loc"] == ["query", "include_unconfirmed"]
        assert c.get("/v1/categories", params={"include_unconfirmed": "false"}).json() == listed


def test_geojson_by_parameter_or_accept(object_client: TestClient) -> None:
    """``format=geojson`` or ``Accept: application/geo+json`` answer the same filtered page as
    a valid GeoJSON FeatureCollection (the ``geojson`` library's check): a Point at each
    object's centre, its id, the list's fields as properties, paging as foreign members."""
    import geojson as gj

    plain = object_client.get("/v1/objects", params={"category": "door", "near": "1,0,0.5"}).json()
    by_param = object_client.get("/v1/objects",
                                 params={"category": "door", "near": "1,0,0.5", "format": "geojson"})
    by_accept = object_client.get("/v1/objects", params={"category": "door", "near": "1,0,0.5"},
                                  headers={"Accept": "application/geo+json"})
    for resp in (by_param, by_accept):
        assert resp.status_code == 200 and resp.headers["content-type"] == "application/geo+json"
        doc = resp.json()
        assert gj.loads(resp.text).is_valid, gj.loads(resp.text).errors()
        assert doc["type"] == "FeatureCollection" and doc["wardmap"] == {"frame": "map", "units": "m"}
        assert (doc["limit"], doc["offset"], doc["next_offset"]) == (100, 0, None)
        assert [f["id"] for f in doc["features"]] == [o["object_id"] for o in plain["objects"]] == [1, 2, 5]
        for f, o in zip(doc["features"], plain["objects"], strict=True):
            assert f["geometry"] == {"type": "Point", "coordinates": o["position"]}
            assert f["properties"] == {k: v for k, v in o.items() if k not in ("position", "T_world_object")}
    assert object_client.get("/v1/objects", params={"format": "json"}).json() == object_client.get(
        "/v1/objects").json()


def test_unknown_format_is_400(object_client: TestClient) -> None:
    """A format the route does not write is refused with a message naming the choices (it
    was once ignored silently)."""
    for fmt in ("csv", "GEOJSON", ""):
        resp = object_client.get("/v1/objects", params={"format": fmt})
        assert resp.status_code == 400, fmt
        assert resp.json()["detail"] == f"unknown format {fmt!r}: expected one of json, geojson, compact"


def test_compact_rows_are_the_objects_rounded(object_client: TestClient) -> None:
    """``format=compact`` (the web page's map) gives, per object of the same filtered page,
    id, category, centre, yaw and size rounded to 1 mm / 1 mrad, in ``columns`` order."""
    params = {"near": "1,0,0.5", "limit": "3"}
    full = object_client.get("/v1/objects", params=params).json()
    compact = object_client.get("/v1/objects", params={**params, "format": "compact"}).json()
    assert compact["columns"] == ["object_id", "category", "x", "y", "z", "yaw", "size_x", "size_y", "size_z"]
    assert full["next_offset"] == 3
    assert (compact["limit"], compact["offset"], compact["next_offset"]) == (3, 0, 3)
    for row, o in zip(compact["rows"], full["objects"], strict=True):
        assert row[:2] == [o["object_id"], o["category"]]
        assert np.allclose(row[2:], [*o["position"], o["yaw"], *o["size"]], atol=5e-4, rtol=0)
        assert all(round(v, 3) == v for v in row[2:])
    # The compact path validates as the others do: an unknown category is 422, not an empty page.
    bad = object_client.get("/v1/objects", params={"format": "compact", "category": "unicorn"})
    assert bad.status_code == 422 and "unknown category" in bad.json()["detail"]

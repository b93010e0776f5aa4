"""``GET /v1/keyframes`` and its cursor (``server/api/routes/keyframes.py``) over the keyframe
scene of ``conftest.py``."""

from __future__ import annotations

from typing import Any

import factories
import numpy as np
import pytest
from fastapi.testclient import TestClient

from wardmap.server.api import decode_cursor, encode_cursor
from wardmap.server.store import open_store


def test_keyframes_pagination_visits_each_once(keyframe_client: TestClient, keyframe_scene: Any) -> None:
    """Pages of 3 walk r1's keyframes in stamp order, each exactly once, ending with a null cursor."""
    client = keyframe_client
    seen: list[tuple[str, int]] = []
    cursor: str | None = None
    pages = 0
    while True:
        params: dict[str, str | int] = {"robot": "r1", "limit": 3}
        if cursor is not None:
            params["cursor"] = cursor
        r = client.get("/v1/keyframes", params=params)
        assert r.status_code == 200, r.text
        body = r.json()
        assert len(body["keyframes"]) <= 3
        seen += [(k["session_id"], k["seq"]) for k in body["keyframes"]]
        pages += 1
        cursor = body["next_cursor"]
        if cursor is None:
            break
    assert pages == 3
    assert seen == [("s1", k) for k in range(5)] + [("s2", 5), ("s2", 6)]
    first = client.get("/v1/keyframes", params={"robot": "r1", "limit": 1}).json()["keyframes"][0]
    assert first["stamp"] == pytest.approx(keyframe_scene.t0)
    assert first["pose_source"] == "rgb"
    assert first["payload_bytes"] > 0


def test_keyframes_unknown_robot_is_empty(keyframe_client: TestClient) -> None:
    r = keyframe_client.get("/v1/keyframes", params={"robot": "nobody"})
    assert r.status_code == 200
    assert r.json() == {"keyframes": [], "next_cursor": None}


@pytest.mark.parametrize(
    ("params", "status"),
    [
        ({}, 422),  # robot missing
        ({"robot": "r1", "limit": 0}, 422),
        ({"robot": "r1", "limit": 100000}, 422),
        ({"robot": "r1", "limit": "x"}, 422),
        ({"robot": "r1", "cursor": "!!not-base64!!"}, 400),
        ({"robot": "r1", "cursor": encode_cursor("s9", 42)}, 400),  # names no keyframe
    ],
)
def test_keyframes_bad_query(keyframe_client: TestClient, params: dict[str, str | int], status: int) -> None:
    """Bad parameters give 422 (validation) or 400 (bad cursor) with a JSON detail."""
    r = keyframe_client.get("/v1/keyframes", params=params)
    assert r.status_code == status, r.text
    assert "detail" in r.json()


def test_cursor_round_trip() -> None:
    assert decode_cursor(encode_cursor("s-1.x", 2**62)) == ("s-1.x", 2**62)
    for bad in ("", "e30", encode_cursor("s", 1) + "!!"):
        with pytest.raises(ValueError):
            decode_cursor(bad)


def test_keyframe_image_is_the_stored_jpeg(keyframe_client: TestClient) -> None:
    """``/v1/keyframes/{robot}/{session}/{seq}/image`` answers the colour JPEG the robot sent,
    byte for byte (the web page's thumbnail); an unknown keyframe or a bad seq does not."""
    expected = factories.keyframe(np.random.default_rng(0)).rgb_jpeg  # the scene's keyframes share it
    r = keyframe_client.get("/v1/keyframes/r1/s1/2/image")
    assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"
    assert r.content == expected and r.content[:2] == b"\xff\xd8"
    assert keyframe_client.get("/v1/keyframes/r1/s1/99/image").status_code == 404
    assert keyframe_client.get("/v1/keyframes/r9/s1/0/image").json() == {"detail": "no keyframe r9/s1/0"}
    assert keyframe_client.get("/v1/keyframes/r1/s1/-1/image").status_code == 422



def test_an_erased_image_is_gone(keyframe_scene: Any, keyframe_client: TestClient) -> None:
    """After retention or an erase order the image route answers 410 with the reason, while the
    keyframe stays listed with its pose."""
    t0 = keyframe_scene.t0
    with open_store(keyframe_scene.url) as store:
        assert store.erase_images(now_s=t0 + 1000, stamp_from=t0 + 2, stamp_to=t0 + 3, robot_id="r1") == 1
    r = keyframe_client.get("/v1/keyframes/r1/s1/2/image")
    assert r.status_code == 410 and "was erased" in r.json()["detail"]
    assert keyframe_client.get("/v1/keyframes/r1/s1/3/image").status_code == 200
    listed = keyframe_client.get("/v1/keyframes", params={"robot": "r1"}).json()["keyframes"]
    assert [k["seq"] for k in listed if k["session_id"] == "s1"] == list(range(5))

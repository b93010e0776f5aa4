"""Tests of the REST API (``wardmap.server.api``) against a temporary SQLite store.

The store is filled with real wire keyframes (a 64x48 JPEG, a 32x24 depth raster) through
``store.insert``, then the app is driven with FastAPI's TestClient (its lifespan opens the
same file). Every route is covered, including the 400/404/422 paths.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from wardmap.server.api import create_app, decode_cursor, encode_cursor
from wardmap.server.store import open_store
from wardmap.shared import wire
from wardmap.shared.se3 import make_transform, transform_to_tum
from wardmap.shared.wire import Intrinsics, KeyframeMsg, Keypoints, PackedRaster

W, H = 64, 48
T0 = 1_714_557_600.0


def _pose(k: int) -> np.ndarray:
    a = 0.1 * k
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return make_transform(R, [k * 0.5, -1.0, 0.25])


def _base() -> KeyframeMsg:
    rng = np.random.default_rng(0)
    ok, jpg = cv2.imencode(".jpg", rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
    assert ok
    n = 4
    return KeyframeMsg(
        robot_id="r1", session_id="s1", seq=0, stamp=T0, T_odom_camera=np.eye(4), pose_source="rgb",
        keypoints=Keypoints(
            uv=(rng.random((n, 2)) * [W - 1, H - 1]).astype(np.float32),
            octave=np.zeros(n, np.int8),
            angle_deg=(rng.random(n) * 360).astype(np.float32),
            depth_m=rng.uniform(0.5, 4.0, n).astype(np.float32),
            descriptors=rng.integers(0, 256, (n, 32), dtype=np.uint8),
        ),
        rgb_jpeg=bytes(jpg.tobytes()),
        depth=PackedRaster(*wire.encode_depth(rng.uniform(0.5, 4.0, (H // 2, W // 2)))),
        intrinsics=Intrinsics(W, H, 50.0, 50.0, 31.5, 23.5, (0.0, 0.0, 0.0, 0.0, 0.0), 5000.0),
    )


N_R1, N_R2 = 7, 3


@pytest.fixture
def db(tmp_path: Path) -> str:
    """A store with robot r1 (7 keyframes, sessions s1 and s2) and r2 (3 keyframes, one session)."""
    url = f"sqlite:///{tmp_path / 'map.db'}"
    base = _base()
    with open_store(url) as store:
        for k in range(N_R1):
            msg = replace(base, robot_id="r1", session_id="s1" if k < 5 else "s2", seq=k,
                          stamp=T0 + k, T_odom_camera=_pose(k))
            assert store.insert(msg, wire.encode(msg), T0 + 100 + k) == "stored"
        for k in range(N_R2):
            msg = replace(base, robot_id="r2", seq=k, stamp=T0 + k, T_odom_camera=_pose(k))
            assert store.insert(msg, wire.encode(msg), T0 + 200 + k) == "stored"
        store.count_rejection("wire: payload")
        store.count_rejection("wire: payload")
        store.count_rejection('odd "reason"')
    return url


@pytest.fixture
def client(db: str) -> Iterator[TestClient]:
    with TestClient(create_app(db)) as c:
        yield c


def test_healthz(client: TestClient) -> None:
    """The liveness probe answers ok."""
    r = client.get("/healthz")
    assert r.status_code == 200
    assert r.json() == {"status": "ok"}


def test_robots(client: TestClient) -> None:
    """Both robots are listed with their keyframe and session counts and seen times."""
    r = client.get("/v1/robots")
    assert r.status_code == 200
    robots = {x["robot_id"]: x for x in r.json()["robots"]}
    assert set(robots) == {"r1", "r2"}
    assert (robots["r1"]["keyframes"], robots["r1"]["sessions"]) == (N_R1, 2)
    assert (robots["r2"]["keyframes"], robots["r2"]["sessions"]) == (N_R2, 1)
    assert robots["r1"]["first_seen_s"] == pytest.approx(T0 + 100)
    assert robots["r1"]["last_seen_s"] == pytest.approx(T0 + 100 + N_R1 - 1)


def test_keyframes_pagination_visits_each_once(client: TestClient) -> None:
    """Pages of 3 walk r1's keyframes in stamp order, each exactly once, ending with a null cursor."""
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
    assert first["stamp"] == pytest.approx(T0)
    assert first["pose_source"] == "rgb"
    assert first["payload_bytes"] > 0


def test_keyframes_unknown_robot_is_empty(client: TestClient) -> None:
    r = client.get("/v1/keyframes", params={"robot": "nobody"})
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
def test_keyframes_bad_query(client: TestClient, params: dict[str, str | int], status: int) -> None:
    """Bad parameters give 422 (validation) or 400 (bad cursor) with a JSON detail."""
    r = client.get("/v1/keyframes", params=params)
    assert r.status_code == status, r.text
    assert "detail" in r.json()


def test_cursor_round_trip() -> None:
    assert decode_cursor(encode_cursor("s-1.x", 2**62)) == ("s-1.x", 2**62)
    for bad in ("", "e30", encode_cursor("s", 1) + "!!"):
        with pytest.raises(ValueError):
            decode_cursor(bad)


def test_trajectory_json(client: TestClient) -> None:
    """JSON poses equal the stored transforms as TUM rows, in stamp order."""
    r = client.get("/v1/robots/r2/trajectory")
    assert r.status_code == 200
    body = r.json()
    assert body["robot_id"] == "r2"
    assert [p["stamp"] for p in body["poses"]] == pytest.approx([T0 + k for k in range(N_R2)])
    for k, p in enumerate(body["poses"]):
        np.testing.assert_allclose(p["t"] + p["q_xyzw"], transform_to_tum(_pose(k)), atol=1e-12)


def test_trajectory_tum(client: TestClient) -> None:
    """TUM text has a comment header and one 8-column line per keyframe matching the poses."""
    r = client.get("/v1/robots/r1/trajectory", params={"format": "tum"})
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/plain")
    lines = r.text.strip().splitlines()
    assert lines[0].startswith("#")
    rows = np.array([[float(v) for v in ln.split()] for ln in lines[1:]])
    assert rows.shape == (N_R1, 8)
    np.testing.assert_allclose(rows[:, 0], [T0 + k for k in range(N_R1)], atol=1e-6)
    for k in range(N_R1):
        np.testing.assert_allclose(rows[k, 1:], transform_to_tum(_pose(k)), atol=1e-7)


def test_trajectory_unknown_robot_404(client: TestClient) -> None:
    r = client.get("/v1/robots/ghost/trajectory")
    assert r.status_code == 404
    assert "ghost" in r.json()["detail"]


def test_trajectory_bad_format_422(client: TestClient) -> None:
    r = client.get("/v1/robots/r1/trajectory", params={"format": "csv"})
    assert r.status_code == 422


def test_metrics(client: TestClient) -> None:
    """Prometheus text carries the ingest counters (0 without ingest), rejections by reason, robots."""
    r = client.get("/metrics")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/plain")
    samples = {}
    for line in r.text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            samples[name] = float(value)
    assert samples["wardmap_keyframes_received_total"] == 0
    assert samples["wardmap_keyframes_stored_total"] == 0
    assert samples["wardmap_keyframes_duplicates_total"] == 0
    assert samples["wardmap_ingest_queue_depth"] == 0
    assert samples["wardmap_robots"] == 2
    assert samples['wardmap_rejections_total{reason="wire: payload"}'] == 2
    assert samples['wardmap_rejections_total{reason="odd \\"reason\\""}'] == 1
    for name in ("wardmap_keyframes_received_total", "wardmap_rejections_total", "wardmap_robots"):
        assert f"# TYPE {name} " in r.text


def test_bad_store_url_fails_at_startup(tmp_path: Path) -> None:
    """create_app opens nothing; the lifespan raises the store's error."""
    app = create_app("mysql://nope")
    with pytest.raises(Exception, match="unknown store URL"), TestClient(app):
        pass


def test_wire_rejection_reasons_are_bounded() -> None:
    """Rejection reasons come from a fixed set of top-level fields, whatever field name a
    hostile payload carries (each reason becomes a DB row and a Prometheus label)."""
    from wardmap.server.ingest import wire_reason

    assert wire_reason("") == "wire: payload"
    assert wire_reason("keypoints.uv") == "wire: keypoints"
    assert wire_reason("T_odom_camera.q_xyzw") == "wire: T_odom_camera"
    reasons = {wire_reason(f"field{i}") for i in range(1000)} | {wire_reason("intrmnsics.fx")}
    assert reasons == {"wire: unknown field"}

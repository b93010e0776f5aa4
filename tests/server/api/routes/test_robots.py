"""``GET /v1/robots`` and ``/v1/robots/{id}/trajectory`` (``server/api/routes/robots.py``) over
the keyframe scene of ``conftest.py`` (r1: 7 keyframes in 2 sessions, r2: 3 in one)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from wardmap.shared.se3 import transform_to_tum


def test_robots(keyframe_client: TestClient, keyframe_scene: Any) -> None:
    """Both robots are listed with their keyframe and session counts and seen times."""
    s = keyframe_scene
    r = keyframe_client.get("/v1/robots")
    assert r.status_code == 200
    robots = {x["robot_id"]: x for x in r.json()["robots"]}
    assert set(robots) == {"r1", "r2"}
    assert (robots["r1"]["keyframes"], robots["r1"]["sessions"]) == (s.n_r1, 2)
    assert (robots["r2"]["keyframes"], robots["r2"]["sessions"]) == (s.n_r2, 1)
    assert robots["r1"]["first_seen_s"] == pytest.approx(s.t0 + 100)
    assert robots["r1"]["last_seen_s"] == pytest.approx(s.t0 + 100 + s.n_r1 - 1)


def test_trajectory_json(keyframe_client: TestClient, keyframe_scene: Any) -> None:
    """JSON poses equal the stored transforms as TUM rows, in stamp order."""
    s = keyframe_scene
    r = keyframe_client.get("/v1/robots/r2/trajectory")
    assert r.status_code == 200
    body = r.json()
    assert body["robot_id"] == "r2"
    assert [p["stamp"] for p in body["poses"]] == pytest.approx([s.t0 + k for k in range(s.n_r2)])
    for k, p in enumerate(body["poses"]):
        np.testing.assert_allclose(p["t"] + p["q_xyzw"], transform_to_tum(s.pose(k)), atol=1e-12)


def test_trajectory_tum(keyframe_client: TestClient, keyframe_scene: Any) -> None:
    """TUM text has a comment header and one 8-column line per keyframe matching the poses."""
    s = keyframe_scene
    r = keyframe_client.get("/v1/robots/r1/trajectory", params={"format": "tum"})
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/plain")
    lines = r.text.strip().splitlines()
    assert lines[0].startswith("#")
    rows = np.array([[float(v) for v in ln.split()] for ln in lines[1:]])
    assert rows.shape == (s.n_r1, 8)
    np.testing.assert_allclose(rows[:, 0], [s.t0 + k for k in range(s.n_r1)], atol=1e-6)
    for k in range(s.n_r1):
        np.testing.assert_allclose(rows[k, 1:], transform_to_tum(s.pose(k)), atol=1e-7)


def test_trajectory_unknown_robot_404(keyframe_client: TestClient) -> None:
    r = keyframe_client.get("/v1/robots/ghost/trajectory")
    assert r.status_code == 404
    assert "ghost" in r.json()["detail"]


def test_trajectory_bad_format_422(keyframe_client: TestClient) -> None:
    r = keyframe_client.get("/v1/robots/r1/trajectory", params={"format": "csv"})
    assert r.status_code == 422

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


def test_robots_show_their_anchoring_and_map_pose(keyframe_client: TestClient, keyframe_scene: Any) -> None:
    """r1's latest session (s2) is anchored through s1 with its T_map_odom and latest map pose;
    r2 floats: not anchored, no map pose."""
    s = keyframe_scene
    robots = {x["robot_id"]: x for x in keyframe_client.get("/v1/robots").json()["robots"]}
    r1, r2 = robots["r1"], robots["r2"]
    assert (r1["session_id"], r1["anchored"], r1["anchored_to"]) == ("s2", True, "r1/s1")
    assert r1["anchored_at_s"] == pytest.approx(s.t0 + 160)
    np.testing.assert_allclose(r1["T_map_odom"]["t"] + r1["T_map_odom"]["q_xyzw"],
                               transform_to_tum(s.T_map_odom_s2), atol=1e-12)
    last = s.n_r1 - 1
    assert r1["map_pose"]["stamp"] == pytest.approx(s.t0 + last)
    np.testing.assert_allclose(r1["map_pose"]["t"] + r1["map_pose"]["q_xyzw"],
                               transform_to_tum(s.T_map_odom_s2 @ s.pose(last)), atol=1e-12)
    assert r2["anchored"] is False and r2["map_pose"] is None and r2["T_map_odom"] is None
    assert r2["anchored_at_s"] is None


def test_map_trajectory_has_the_back_ends_poses(keyframe_client: TestClient, keyframe_scene: Any) -> None:
    """The default frame is the map: r1's keyframes at the graph's estimates (both sessions on one
    map); r2 floats, so its map trajectory is empty (200, not 404)."""
    s = keyframe_scene
    body = keyframe_client.get("/v1/robots/r1/trajectory").json()
    assert body["frame"] == "map" and len(body["poses"]) == s.n_r1
    for k, p in enumerate(body["poses"]):
        T = (np.eye(4) if k < 5 else s.T_map_odom_s2) @ s.pose(k)
        np.testing.assert_allclose(p["t"] + p["q_xyzw"], transform_to_tum(T), atol=1e-12)
    r2 = keyframe_client.get("/v1/robots/r2/trajectory")
    assert r2.status_code == 200 and r2.json()["poses"] == []


def test_trajectory_json(keyframe_client: TestClient, keyframe_scene: Any) -> None:
    """JSON poses (odom frame) equal the stored transforms as TUM rows, in stamp order."""
    s = keyframe_scene
    r = keyframe_client.get("/v1/robots/r2/trajectory", params={"frame": "odom"})
    assert r.status_code == 200
    body = r.json()
    assert body["robot_id"] == "r2" and body["frame"] == "odom"
    assert [p["stamp"] for p in body["poses"]] == pytest.approx([s.t0 + k for k in range(s.n_r2)])
    for k, p in enumerate(body["poses"]):
        np.testing.assert_allclose(p["t"] + p["q_xyzw"], transform_to_tum(s.pose(k)), atol=1e-12)


def test_trajectory_tum(keyframe_client: TestClient, keyframe_scene: Any) -> None:
    """TUM text has a comment header (naming the frame) and one 8-column line per keyframe matching
    the poses."""
    s = keyframe_scene
    r = keyframe_client.get("/v1/robots/r1/trajectory", params={"format": "tum", "frame": "odom"})
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/plain")
    lines = r.text.strip().splitlines()
    assert lines[0] == "# frame odom" and lines[1].startswith("#")
    rows = np.array([[float(v) for v in ln.split()] for ln in lines[2:]])
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


def test_trajectory_bad_frame_422(keyframe_client: TestClient) -> None:
    r = keyframe_client.get("/v1/robots/r1/trajectory", params={"frame": "world"})
    assert r.status_code == 422

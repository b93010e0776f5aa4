"""``GET /healthz`` (``server/api/routes/health.py``)."""

from __future__ import annotations

import sqlite3
from typing import Any

from fastapi.testclient import TestClient


def test_healthz(keyframe_client: TestClient) -> None:
    """The liveness probe answers ok."""
    r = keyframe_client.get("/healthz")
    assert r.status_code == 200
    assert r.json() == {"status": "ok"}


def test_readyz_ok_while_the_store_can_write(keyframe_client: TestClient) -> None:
    """An API-only server on a writable store is ready."""
    r = keyframe_client.get("/readyz")
    assert r.status_code == 200
    assert r.json() == {"status": "ok"}


def test_readyz_503_while_another_process_holds_the_write_lock(
    keyframe_scene: Any, keyframe_client: TestClient
) -> None:
    """Another connection holds the database's write lock: not ready (503, the reason says why),
    and ready again once it lets go."""
    path = keyframe_scene.url.removeprefix("sqlite:///")
    other = sqlite3.connect(path, isolation_level=None)
    try:
        other.execute("BEGIN EXCLUSIVE")
        r = keyframe_client.get("/readyz")
        assert r.status_code == 503
        assert r.json()["status"] != "ok"
    finally:
        other.execute("ROLLBACK")
        other.close()
    assert keyframe_client.get("/readyz").status_code == 200

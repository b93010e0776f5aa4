"""``GET /healthz`` (``server/api/routes/health.py``)."""

from __future__ import annotations

from fastapi.testclient import TestClient


def test_healthz(keyframe_client: TestClient) -> None:
    """The liveness probe answers ok."""
    r = keyframe_client.get("/healthz")
    assert r.status_code == 200
    assert r.json() == {"status": "ok"}

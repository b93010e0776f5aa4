"""``GET /v1/categories`` (``server/api/routes/categories.py``) over the object scene of
``conftest.py`` (three doors, a bed, a wheelchair)."""

from __future__ import annotations

from fastapi.testclient import TestClient

from wardmap.shared.knowledge import KnowledgeGraph


def test_categories(object_client: TestClient) -> None:
    """Every knowledge-graph class in class order, with its count and mobility, and the total."""
    body = object_client.get("/v1/categories").json()
    kg = KnowledgeGraph.load()
    assert [c["name"] for c in body["categories"]] == list(kg.names)
    counts = {c["name"]: c["count"] for c in body["categories"]}
    assert counts["door"] == 3 and counts["bed"] == 1 and counts["wheelchair"] == 1 and counts["sink"] == 0
    assert body["total"] == 5
    mobility = {c["name"]: c["mobility"] for c in body["categories"]}
    assert mobility["door"] == "static" and mobility["wheelchair"] == "movable"


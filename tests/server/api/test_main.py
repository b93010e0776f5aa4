"""The app itself (``server/api/main.py``): its lifespan starts and stops the composition root,
and a WardmapError becomes an HTTP status in one place."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from wardmap.server.api import Services, create_app
from wardmap.server.app import MapServer
from wardmap.server.objectmap import ObjectMap
from wardmap.server.store import StoreError, open_store
from wardmap.shared.errors import WardmapError


def test_bad_store_url_fails_at_startup() -> None:
    """Building the server and its app opens nothing; the lifespan raises the store's error."""
    app = MapServer("mysql://nope").app
    with pytest.raises(Exception, match="unknown store URL"), TestClient(app):
        pass


class _Root:
    """A composition root that records its life cycle and serves a real store."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.events: list[str] = []

    def start(self) -> Services:
        self.events.append("start")
        store = open_store(self.url)
        self.store = store
        return Services(store=store, objects=ObjectMap(store))

    def stop(self) -> None:
        self.events.append("stop")
        self.store.close()


def test_lifespan_starts_and_stops_the_root(tmp_path: Path) -> None:
    """The app starts its root once when it starts serving and stops it once at shutdown."""
    root = _Root(f"sqlite:///{tmp_path / 'a.db'}")
    app = create_app(root)
    assert root.events == []
    with TestClient(app) as c:
        assert c.get("/healthz").status_code == 200 and root.events == ["start"]
    assert root.events == ["start", "stop"]


def test_wardmap_errors_become_http_statuses(tmp_path: Path) -> None:
    """A StoreError escaping a route is a 400 with its message; another WardmapError a 500."""
    root = _Root(f"sqlite:///{tmp_path / 'a.db'}")
    app = create_app(root)

    @app.get("/boom/{kind}")
    def boom(kind: str) -> None:
        raise StoreError("bad page") if kind == "store" else WardmapError("broken")

    with TestClient(app, raise_server_exceptions=False) as c:
        store_error = c.get("/boom/store")
        assert (store_error.status_code, store_error.json()) == (400, {"detail": "bad page"})
        other = c.get("/boom/other")
        assert (other.status_code, other.json()) == (500, {"detail": "broken"})

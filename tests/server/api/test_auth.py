"""The REST API's bearer tokens (``server/api/auth.py`` over ``server/tokens.py``), through the
real app and a real store: every data route needs a token, a ``read`` token reads, a ``read``
token on a route that changes state is 403, bad and revoked tokens are 401, the probes and the
OpenAPI document stay public, no CORS headers are sent, and insecure mode checks nothing."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi import APIRouter, Depends
from fastapi.testclient import TestClient

from wardmap.server.api.auth import AdminOnly, require_token
from wardmap.server.app import MapServer
from wardmap.server.store import open_store
from wardmap.server.tokens import revoke_token

TokenMaker = Callable[..., dict[str, str]]
PUBLIC = {"/", "/healthz", "/readyz", "/openapi.json", "/docs", "/docs/oauth2-redirect", "/redoc"}
"""Routes that carry no map data: the probes, the API's documents, a web page's shell."""


def _app_with_admin_routes(url: str) -> MapServer:
    """The real app plus two test routes that change nothing: a POST on a router with the data
    router's dependency (method rule) and a GET that asks for admin explicitly."""
    server = MapServer(url)
    router = APIRouter(dependencies=[Depends(require_token)])

    @router.post("/v1/test-write")
    def write() -> dict[str, str]:
        return {"status": "written"}

    @router.get("/v1/test-admin", dependencies=[AdminOnly])
    def admin_read() -> dict[str, str]:
        return {"status": "read"}

    server.app.include_router(router)
    return server


@pytest.fixture
def client(keyframe_scene: Any) -> Iterator[TestClient]:
    """No default token: each test sends what it means to."""
    with TestClient(_app_with_admin_routes(keyframe_scene.url).app) as c:
        yield c


def _data_routes(client: TestClient) -> list[tuple[str, str]]:
    """``(method, path)`` of every documented route but the public ones, parameters filled."""
    paths = client.get("/openapi.json").json()["paths"]
    return [(method.upper(), p.replace("{object_id}", "1").replace("{robot_id}", "r1"))
            for p, ops in paths.items() if p not in PUBLIC for method in ops]


def test_every_data_route_needs_a_token(client: TestClient) -> None:
    """Without a token every route but the probes and the OpenAPI pages is 401 with
    ``WWW-Authenticate: Bearer`` (so a new route is protected unless it is put on the public router)."""
    routes = _data_routes(client)
    assert {"/v1/robots", "/v1/keyframes", "/v1/objects", "/v1/categories", "/metrics",
            "/v1/test-write"} <= {path for _, path in routes}
    for method, path in routes:
        r = client.request(method, path)
        assert r.status_code == 401, (method, path, r.status_code)
        assert r.headers["www-authenticate"].startswith("Bearer"), path
    for path in ("/healthz", "/readyz", "/openapi.json"):
        assert client.get(path).status_code == 200, path


def test_read_token_reads_and_is_forbidden_on_admin_routes(
    keyframe_scene: Any, client: TestClient
, token_headers: TokenMaker) -> None:
    """A ``read`` token: 200 on reads (robots, keyframes, metrics), 403 on a POST and on a GET that
    asks for admin; an ``admin`` token passes both."""
    read = token_headers(keyframe_scene.url, "read")
    assert client.get("/v1/robots", headers=read).status_code == 200
    assert client.get("/v1/keyframes", params={"robot": "r1"}, headers=read).status_code == 200
    assert client.get("/metrics", headers=read).status_code == 200
    for r in (client.post("/v1/test-write", headers=read), client.get("/v1/test-admin", headers=read)):
        assert r.status_code == 403 and "needs admin" in r.json()["detail"]
    admin = token_headers(keyframe_scene.url, "admin")
    assert client.post("/v1/test-write", headers=admin).json() == {"status": "written"}
    assert client.get("/v1/test-admin", headers=admin).json() == {"status": "read"}
    assert client.get("/v1/robots", headers=admin).status_code == 200


def test_bad_and_revoked_tokens_are_401(
    keyframe_scene: Any, client: TestClient, token_headers: TokenMaker
) -> None:
    """A malformed token, a right id with a wrong secret, an unknown id, another scheme and a
    revoked token are each 401; the revocation counts from the next request (no cache)."""
    good = token_headers(keyframe_scene.url, "read")["Authorization"]
    text = good.removeprefix("Bearer ")
    token_id = text.split("_")[1]
    wrong_secret = text[:-1] + ("A" if text[-1] != "A" else "B")
    unknown_id = "wm_000000000000_" + text.split("_", 2)[2]
    for auth in ("Bearer nonsense", f"Bearer {wrong_secret}", f"Bearer {unknown_id}", f"Basic {text}",
                 f"Bearer {text}x", "Bearer " + "x" * 10_000):
        assert client.get("/v1/robots", headers={"Authorization": auth}).status_code == 401, auth[:40]
    assert client.get("/v1/robots", headers={"Authorization": good}).status_code == 200
    with open_store(keyframe_scene.url) as store:
        revoke_token(store, token_id)
    assert client.get("/v1/robots", headers={"Authorization": good}).status_code == 401


def test_no_cors_headers(keyframe_scene: Any, client: TestClient, token_headers: TokenMaker) -> None:
    """CORS is closed: neither a cross-origin GET nor a preflight gets Access-Control headers, so a
    browser page from another origin cannot read the API even with a token."""
    headers = {**token_headers(keyframe_scene.url), "Origin": "https://evil.example"}
    r = client.get("/v1/robots", headers=headers)
    assert r.status_code == 200 and "access-control-allow-origin" not in r.headers
    pre = client.options("/v1/robots", headers={"Origin": "https://evil.example",
                                                "Access-Control-Request-Method": "GET"})
    assert not any(h.startswith("access-control-") for h in pre.headers)


def test_openapi_declares_the_bearer_scheme(client: TestClient) -> None:
    """The OpenAPI document says data routes take a bearer token and may answer 401/403."""
    doc = client.get("/openapi.json").json()
    assert doc["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"
    robots = doc["paths"]["/v1/robots"]["get"]
    assert robots["security"] == [{"HTTPBearer": []}] and {"401", "403"} <= set(robots["responses"])
    assert "security" not in doc["paths"]["/healthz"]["get"]


def test_insecure_mode_checks_nothing(tmp_path: Path) -> None:
    """``require_tokens=False`` (insecure-loopback) serves data routes without a token."""
    with TestClient(MapServer(f"sqlite:///{tmp_path / 'm.db'}", require_tokens=False).app) as c:
        assert c.get("/v1/robots").status_code == 200


def test_a_store_without_tokens_is_warned_about(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A server that requires tokens but has none says at start-up how to make one."""
    with TestClient(MapServer(f"sqlite:///{tmp_path / 'm.db'}").app):
        pass
    assert "wardmap token create" in caplog.text

"""``GET /`` (the web page) and ``/docs``, ``/redoc`` (``routes/web.py``, ``routes/docs.py``):
served from the package, with every asset they name on this server and none on a CDN. The
page's behaviour is tested in a real browser (``test_web_browser.py``)."""

from __future__ import annotations

import re

from fastapi.testclient import TestClient

ASSET = re.compile(r"""(?:src|href)=["']([^"']+)["']""")


def _assets(html: str) -> list[str]:
    return ASSET.findall(html)


def test_page_and_its_assets_are_served(object_client: TestClient) -> None:
    """``/`` is the HTML page; each script, style sheet and icon it names is under /static
    on this server and is served; no URL names another host."""
    r = object_client.get("/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assets = _assets(r.text)
    assert {"/static/wardmap.js", "/static/wardmap.css", "/static/favicon.svg"} <= set(assets)
    for url in assets:
        assert url.startswith("/"), url
        assert object_client.get(url).status_code == 200, url
    assert "http://" not in r.text and "https://" not in r.text


def test_api_docs_use_the_packaged_files(object_client: TestClient) -> None:
    """Swagger UI and ReDoc pages load their scripts, styles and icon from /static/vendor
    (served here, licences beside them), not a CDN; the spec validator badge is off."""
    for path in ("/docs", "/redoc"):
        html = object_client.get(path).text
        assets = _assets(html)
        assert assets and all(a.startswith("/static/vendor/") for a in assets), (path, assets)
        assert "https://" not in html and "http://" not in html, path
        for url in assets:
            assert object_client.get(url).status_code == 200, url
    assert '"validatorUrl": null' in object_client.get("/docs").text
    for licence in ("swagger-ui/LICENSE", "swagger-ui/NOTICE", "redoc/LICENSE"):
        assert object_client.get(f"/static/vendor/{licence}").status_code == 200, licence
    assert object_client.get("/docs/oauth2-redirect").status_code == 200
    assert object_client.get("/openapi.json").json()["info"]["title"] == "wardmap map server"


def test_page_routes_stay_out_of_the_api_schema(object_client: TestClient) -> None:
    """The page and docs routes are not API operations; the event stream and the keyframe
    image are."""
    paths = set(object_client.get("/openapi.json").json()["paths"])
    assert not paths & {"/", "/docs", "/redoc", "/docs/oauth2-redirect"}
    assert {"/v1/events", "/v1/keyframes/{robot_id}/{session_id}/{seq}/image"} <= paths


def test_unknown_static_file_is_404(object_client: TestClient) -> None:
    assert object_client.get("/static/nope.js").status_code == 404
    assert object_client.get("/static/%2e%2e/routes/web.py").status_code == 404  # nothing outside static/

"""The web page (``GET /``) and the API docs in a real Chromium, driven by Playwright.

The browser is Debian's ``chromium`` (``scripts/test.sh`` installs it in CI; Playwright
downloads nothing). The server is the real app on a loopback port over the ward of
``tests/webscene.py``. Every page is opened with all hosts but the server's blocked and every
request recorded: a test fails on a request that left the host or on a console error.
Screenshots go to pytest's tmp dir (``--basetemp`` to keep them).
"""

from __future__ import annotations

import os
import re
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import numpy as np
import pytest
import webscene

from wardmap.server.app import MapServer
from wardmap.server.objectmap import ObjectState
from wardmap.shared.se3 import yaw_transform

pytestmark = pytest.mark.slow

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        if os.environ.get("CI"):
            pytest.fail("playwright is not installed (the dev extra has it)")
        pytest.skip("playwright is not installed")
    if CHROMIUM is None:
        if os.environ.get("CI"):
            pytest.fail("no chromium on PATH: scripts/test.sh installs Debian's chromium")
        pytest.skip("no chromium on PATH (apt-get install chromium)")
    with sync_playwright() as p:
        # --no-sandbox: CI runs as root, where Chromium's sandbox refuses to start; a container's
        # small /dev/shm makes it crash unless it keeps shared memory in /tmp.
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-dev-shm-usage"])
        try:
            yield b
        finally:
            b.close()


@pytest.fixture(scope="module")
def ward(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, MapServer, str]]:
    """The ward served with tokens required, and a ``read`` token for it."""
    url = f"sqlite:///{tmp_path_factory.mktemp('ward') / 'map.db'}"
    webscene.fill_ward(url)
    token = webscene.read_token(url)
    with webscene.live_server(url) as (base, root):
        yield base, root, token


@dataclass
class Watch:
    """What a page did: console errors, uncaught errors, requests to other hosts (blocked)."""

    errors: list[str] = field(default_factory=list)
    outside: list[str] = field(default_factory=list)
    requests: list[Any] = field(default_factory=list)


def open_page(browser: Any, base: str, path: str = "/", **context: Any) -> tuple[Any, Any, Watch]:
    """A new context and page at ``base + path``: requests to any host but ``base``'s are
    aborted and recorded, console errors and page errors recorded."""
    watch = Watch()
    ctx = browser.new_context(**{"viewport": {"width": 1200, "height": 800}, **context})
    host = urlsplit(base).netloc

    def route(r: Any) -> None:
        if urlsplit(r.request.url).netloc == host or r.request.url.startswith(("data:", "blob:")):
            r.continue_()
        else:
            watch.outside.append(r.request.url)
            r.abort()

    ctx.route("**/*", route)
    page = ctx.new_page()
    page.on("console", lambda m: watch.errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: watch.errors.append(str(e)))
    page.on("request", lambda r: watch.requests.append(r))
    page.goto(base + path)
    return ctx, page, watch


def ready(page: Any) -> None:
    page.wait_for_selector("body[data-ready='1']", timeout=15_000)
    # robotsLoaded is set once every robot's trajectory is fetched (they arrive one by one)
    page.wait_for_function("wardmap.state.robotsLoaded && wardmap.state.trajectories.size > 0")


def screen(page: Any, x: float, y: float) -> dict[str, float]:
    """The canvas position (CSS pixels) of map point (x, y)."""
    sx, sy = page.evaluate("([x, y]) => wardmap.toScreen(x, y)", [x, y])
    return {"x": sx, "y": sy}


COLOURED_PIXELS = """([name, x, y, r]) => {
  // Pixels within r (CSS px) of (x, y) drawn in the category's colour (each channel +-40).
  const c = document.getElementById("map"), d = window.devicePixelRatio;
  const want = wardmap.colourOf(name).match(/[0-9a-f]{2}/gi).map((h) => parseInt(h, 16));
  const x0 = Math.round((x - r) * d), y0 = Math.round((y - r) * d), n = Math.round(2 * r * d);
  const px = c.getContext("2d").getImageData(x0, y0, n, n).data;
  let hits = 0;
  for (let i = 0; i < px.length; i += 4)
    if (px[i + 3] > 0 && [0, 1, 2].every((k) => Math.abs(px[i + k] - want[k]) <= 40)) hits++;
  return hits;
}"""


def coloured_pixels(page: Any, category: str, x: float, y: float, size_m: float) -> int:
    """How many canvas pixels around map point (x, y) (within the object's size) have the
    category's colour."""
    p = screen(page, x, y)
    scale = page.evaluate("wardmap.state.view.scale")
    return int(page.evaluate(COLOURED_PIXELS, [category, p["x"], p["y"], max(2.0, size_m * scale / 2)]))


def shot(page: Any, tmp_path: Path, name: str) -> None:
    page.screenshot(path=str(tmp_path / f"{name}.png"))


def test_page_draws_robots_objects_and_trajectories(
    browser: Any, ward: tuple[str, MapServer, str], tmp_path: Path
) -> None:
    """The page loads, lists both robots with their anchoring, draws every object where the
    map has it (the canvas pixel at each centre is the category's colour, not background),
    r1's trajectory of 6 keyframes, and nothing leaves the host."""
    base, _, token = ward
    ctx, page, watch = open_page(browser, base, f"/#token={token}")
    try:
        ready(page)
        assert page.evaluate("[...wardmap.state.objects.keys()].sort()") == [1, 2, 3, 4, 5]
        assert page.evaluate("wardmap.state.trajectories.get('r1').points.length") == webscene.R1_KEYFRAMES
        assert page.evaluate("wardmap.state.trajectories.get('r2').points.length") == 0  # not on the map
        robots = page.locator("#robots li")
        assert robots.count() == 2
        assert "anchored" in robots.nth(0).inner_text() and "not anchored" in robots.nth(1).inner_text()
        assert page.locator("#live").inner_text() == "live"
        for _, category, x, y, _, size in webscene.OBJECTS:
            assert coloured_pixels(page, category, x, y, max(size[:2])) > 10, (category, x, y)
        # The bed (2 m x 1 m) is turned by +0.5 rad: 0.9 m along its x axis is bed, the mirror
        # image of that point (turned by -0.5 rad) is floor.
        a = webscene.BED_YAW
        assert coloured_pixels(page, "bed", 5.0 + 0.9 * np.cos(a), 2.0 + 0.9 * np.sin(a), 0.0) > 0
        assert coloured_pixels(page, "bed", 5.0 + 0.9 * np.cos(a), 2.0 - 0.9 * np.sin(a), 0.0) == 0
        shot(page, tmp_path, "floor")
        assert watch.outside == [] and watch.errors == []
    finally:
        ctx.close()


def test_nearest_door_from_a_clicked_point(browser: Any, ward: tuple[str, MapServer, str],
                                           tmp_path: Path) -> None:
    """Clicking the floor at (4, 4) and searching doors lists door 2 (6, 5) first, about 2.2 m
    away, then door 1 (0, 5) and door 3; the bed (5, 2), nearer, is not a door. From robot
    r1's position instead, door 3 comes first."""
    base, _, token = ward
    ctx, page, watch = open_page(browser, base, f"/#token={token}")
    try:
        ready(page)
        page.locator("#map").click(position=screen(page, 4.0, 4.0))
        assert page.locator("#detail").is_hidden()  # the floor, not an object
        page.select_option("#category", "door")
        page.click("#search-form button[type=submit]")
        page.wait_for_selector("#results li[data-object-id]")
        items = page.locator("#results li[data-object-id]")
        assert [items.nth(i).get_attribute("data-object-id") for i in range(items.count())] == ["2", "1", "3"]
        first = items.nth(0).inner_text()
        found = re.search(r"([0-9.]+) m", first)
        assert found is not None, first
        distance_m = float(found.group(1))
        # On the floor sqrt(2^2 + 1^2); the search point sits at the objects' mean height (0.75 m).
        assert "door #2" in first and "last seen" in first and abs(distance_m - 2.25) <= 0.1
        shot(page, tmp_path, "search")
        # From robot r1's position, (10, 0) at 1.2 m: door 3 at (12, 5) is nearest.
        page.select_option("#origin", "robot:r1")
        page.click("#search-form button[type=submit]")
        page.wait_for_selector("#results li[data-object-id='3']:first-child")
        assert watch.outside == [] and watch.errors == []
    finally:
        ctx.close()


def test_object_detail_with_thumbnail(browser: Any, ward: tuple[str, MapServer, str], tmp_path: Path) -> None:
    """Clicking door 2 opens its detail: category, confidence, size, the robot that saw it and
    the thumbnail of r1's keyframe 3 (fetched with the page's headers)."""
    base, _, token = ward
    ctx, page, watch = open_page(browser, base, f"/#token={token}")
    try:
        ready(page)
        page.locator("#map").click(position=screen(page, 6.0, 5.0))
        page.wait_for_selector("#detail:not([hidden])")
        page.wait_for_selector("#detail-figure:not([hidden])")
        assert page.locator("#detail-title").inner_text() == "door #2"
        fields = {k: page.locator(f"dd[data-field='{k}']").inner_text()
                  for k in ("category", "confidence", "size", "seen by", "observations")}
        assert fields == {"category": "door", "confidence": "0.90", "size": "0.90 × 0.10 × 2.00 m",
                          "seen by": "r1", "observations": "1"}
        assert "keyframe s1/3" in page.locator("#thumb-caption").inner_text()
        assert any(r.url.endswith("/v1/keyframes/r1/s1/3/image") for r in watch.requests)
        shot(page, tmp_path, "detail")
        assert watch.outside == [] and watch.errors == []
    finally:
        ctx.close()


def test_new_object_appears_live(browser: Any, ward: tuple[str, MapServer, str]) -> None:
    """An object the map writer adds after the page loaded is drawn without a reload, within
    1 s of its commit (the update stream, GET /v1/events); deleting it removes it."""
    base, root, token = ward
    ctx, page, watch = open_page(browser, base, f"/#token={token}")
    try:
        ready(page)
        assert root.services is not None
        objects = root.services.objects
        committed_ms = time.time() * 1000.0
        sink = ObjectState(90, "sink", 0.8, yaw_transform(3.0, 6.0, 0.0, 0.9), np.array([0.6, 0.5, 0.3]))
        objects.upsert([sink])
        page.wait_for_function("wardmap.state.updatesDrawn.has(90)", timeout=5_000)
        latency_ms = page.evaluate("wardmap.state.updatesDrawn.get(90)") - committed_ms
        assert page.evaluate("wardmap.state.objects.get(90).category") == "sink"
        assert latency_ms < 1000.0, latency_ms
        objects.delete(90)
        page.wait_for_function("!wardmap.state.objects.has(90)", timeout=5_000)
        assert watch.outside == [] and watch.errors == []
    finally:
        ctx.close()


def test_token_is_sent_and_kept_out_of_the_address(browser: Any, ward: tuple[str, MapServer, str]) -> None:
    """Opened as ``/#token=TOKEN``, the page sends ``Authorization: Bearer TOKEN`` on every data
    request (the event stream too, read with fetch) and removes the token from the address."""
    base, _, token = ward
    ctx, page, watch = open_page(browser, base, f"/#token={token}")
    try:
        ready(page)
        assert "token" not in page.url
        data = [r for r in watch.requests if urlsplit(r.url).path.startswith("/v1/")]
        paths = {urlsplit(r.url).path for r in data}
        assert paths >= {"/v1/events", "/v1/objects", "/v1/robots", "/v1/categories"}
        assert all(r.headers.get("authorization") == f"Bearer {token}" for r in data), [
            (r.url, r.headers.get("authorization")) for r in data]
        assert watch.errors == []
    finally:
        ctx.close()


def test_tablet_portrait_layout(browser: Any, ward: tuple[str, MapServer, str], tmp_path: Path) -> None:
    """On a portrait tablet (768 x 1024, touch) the panel moves below the floor view, nothing
    is wider than the screen, and a tap on the floor sets the search point."""
    base, _, token = ward
    ctx, page, watch = open_page(browser, base, f"/#token={token}", viewport={"width": 768, "height": 1024},
                                 has_touch=True, is_mobile=True, device_scale_factor=2)
    try:
        ready(page)
        floor = page.locator("#floor").bounding_box()
        panel = page.locator("aside").bounding_box()
        assert floor is not None and panel is not None
        assert panel["y"] >= floor["y"] + floor["height"] - 1 and floor["height"] >= 400
        assert page.evaluate("document.documentElement.scrollWidth") <= 768
        page.locator("#map").tap(position=screen(page, 4.0, 4.0))
        assert page.locator("#origin-point").inner_text().startswith("Point (")
        shot(page, tmp_path, "tablet")
        assert watch.outside == [] and watch.errors == []
    finally:
        ctx.close()


def test_refused_token_is_explained(browser: Any, ward: tuple[str, MapServer, str]) -> None:
    """Opened without a token, the server's data routes answer 401: the page says how to give
    one and keeps running (no uncaught error)."""
    base, _, _ = ward
    ctx, page, watch = open_page(browser, base, "/")
    try:
        page.wait_for_selector("#banner:not([hidden])")
        assert "#token=YOUR_TOKEN" in page.locator("#banner").inner_text()
        assert page.locator("#live").inner_text() == "reconnecting"
        assert watch.outside == []
        # The browser logs each 401 response as a console error; nothing else may appear.
        assert all("401" in e for e in watch.errors), watch.errors
    finally:
        ctx.close()


@pytest.mark.parametrize(("path", "selector"), [("/docs", ".swagger-ui .info .title"), ("/redoc", "h1")])
def test_api_docs_work_offline(browser: Any, ward: tuple[str, MapServer, str], tmp_path: Path,
                               path: str, selector: str) -> None:
    """Swagger UI and ReDoc render the API from the packaged files, with every other host
    blocked: no request leaves the host, no console error."""
    base, _, _ = ward
    ctx, page, watch = open_page(browser, base, path)
    try:
        page.wait_for_selector(selector, timeout=15_000)
        assert "wardmap map server" in page.locator(selector).first.inner_text()
        page.wait_for_load_state("networkidle")
        shot(page, tmp_path, path.strip("/"))
        assert watch.outside == [] and watch.errors == []
    finally:
        ctx.close()

"""``GET /``: the web page (a floor view of the map, robots, search, live updates; docs/web.md).

The page is static (``static/index.html``, ``wardmap.js``, ``wardmap.css``: plain HTML, JS
and CSS, no library, nothing from the network) and reads the data routes like any client,
sending ``Authorization: Bearer <token>`` when it was opened with ``#token=...``. Its files
hold no data, so they are public.
"""

from __future__ import annotations

from importlib.resources import files

from fastapi import APIRouter
from fastapi.responses import HTMLResponse

__all__ = ["router"]

router = APIRouter(include_in_schema=False)


@router.get("/")
async def page() -> HTMLResponse:
    html = files("wardmap.server.api").joinpath("static", "index.html").read_text(encoding="utf-8")
    return HTMLResponse(html, headers={"Cache-Control": "no-cache"})

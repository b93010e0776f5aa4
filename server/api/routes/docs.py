"""``GET /docs`` (Swagger UI) and ``GET /redoc`` (ReDoc) from files packaged with the server.

FastAPI's own pages load their scripts, styles, fonts and favicon from CDNs, so on a hospital
network without internet they stay blank. These serve the same pages from the vendored copies
under ``static/vendor/`` (swagger-ui-dist and redoc from npm, with their licences; versions in
``static/vendor/README.md``), mounted at ``/static`` by the app, and turn off what still
reaches out: ReDoc's Google fonts and Swagger's online spec validator badge.
"""

from __future__ import annotations

from typing import Final

from fastapi import APIRouter
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse

__all__ = ["OPENAPI_URL", "router"]

OPENAPI_URL: Final = "/openapi.json"
_VENDOR: Final = "/static/vendor"
_OAUTH2_REDIRECT: Final = "/docs/oauth2-redirect"
_TITLE: Final = "wardmap map server"

router = APIRouter(include_in_schema=False)


@router.get("/docs")
async def swagger_ui() -> HTMLResponse:
    return get_swagger_ui_html(
        openapi_url=OPENAPI_URL,
        title=f"{_TITLE} - Swagger UI",
        swagger_js_url=f"{_VENDOR}/swagger-ui/swagger-ui-bundle.js",
        swagger_css_url=f"{_VENDOR}/swagger-ui/swagger-ui.css",
        swagger_favicon_url=f"{_VENDOR}/swagger-ui/favicon-32x32.png",
        oauth2_redirect_url=_OAUTH2_REDIRECT,
        swagger_ui_parameters={"validatorUrl": None},  # else a badge image from validator.swagger.io
    )


@router.get(_OAUTH2_REDIRECT)
async def swagger_ui_redirect() -> HTMLResponse:
    return get_swagger_ui_oauth2_redirect_html()


@router.get("/redoc")
async def redoc() -> HTMLResponse:
    return get_redoc_html(
        openapi_url=OPENAPI_URL,
        title=f"{_TITLE} - ReDoc",
        redoc_js_url=f"{_VENDOR}/redoc/redoc.standalone.js",
        redoc_favicon_url=f"{_VENDOR}/swagger-ui/favicon-32x32.png",
        with_google_fonts=False,
    )

"""The interactive API documentation (``/docs``: Swagger UI, ``/redoc``: ReDoc), served whole by
this server: their scripts and styles come from the installed ``fastapi-offline`` package, not a
CDN, so the pages work on a machine with no internet.

    install_docs(app)     # after FastAPI(docs_url=None, redoc_url=None)
"""

from __future__ import annotations

import functools
import re
from importlib.resources import files
from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

from app.web.security import page_csp

#: Where the pages' own scripts, styles and icon are served from.
ASSETS_PATH = "/docs-assets"
REDOC_REMOTE_LOGO = b"https://cdn.redoc.ly/redoc/logo-mini.svg"
EMPTY_SVG = b"data:image/svg+xml,%3Csvg xmlns='http://www.w3.org/2000/svg'/%3E"


def assets_directory() -> Path:
    """The folder of the installed Swagger UI and ReDoc files (``fastapi_offline/static``)."""
    return Path(str(files("fastapi_offline") / "static"))


@functools.cache
def redoc_script_offline() -> bytes:
    """ReDoc's bundle with its one remote resource (the "powered by" logo, from Redocly's CDN)
    replaced by an empty image, so that the page asks nothing of another host."""
    script = (assets_directory() / "redoc.standalone.js").read_bytes()
    return script.replace(REDOC_REMOTE_LOGO, EMPTY_SVG)


_INLINE_SCRIPT = re.compile(r"<script>(.*?)</script>", re.S)


def with_page_policy(page: HTMLResponse, *, workers: bool = False) -> HTMLResponse:
    """``page`` with the server's page policy (``app.web.security``), allowing exactly its own
    inline scripts."""
    scripts = _INLINE_SCRIPT.findall(bytes(page.body).decode())
    page.headers["Content-Security-Policy"] = page_csp(inline_scripts=scripts, workers=workers)
    return page


def install_docs(app: FastAPI) -> None:
    """Serve ``/docs`` and ``/redoc`` with their assets from this server (not in the schema)."""

    @app.get(f"{ASSETS_PATH}/redoc.standalone.js", include_in_schema=False)
    async def redoc_script() -> Response:
        return Response(redoc_script_offline(), media_type="text/javascript")

    app.mount(ASSETS_PATH, StaticFiles(directory=assets_directory()), name="docs-assets")
    openapi_url = app.openapi_url or "/openapi.json"

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui() -> HTMLResponse:
        return with_page_policy(
            get_swagger_ui_html(
                openapi_url=openapi_url,
                title=f"{app.title} — API",
                swagger_js_url=f"{ASSETS_PATH}/swagger-ui-bundle.js",
                swagger_css_url=f"{ASSETS_PATH}/swagger-ui.css",
                swagger_favicon_url=f"{ASSETS_PATH}/favicon.png",
            )
        )

    @app.get("/redoc", include_in_schema=False)
    async def redoc() -> HTMLResponse:
        return with_page_policy(
            get_redoc_html(
                openapi_url=openapi_url,
                title=f"{app.title} — API",
                redoc_js_url=f"{ASSETS_PATH}/redoc.standalone.js",
                redoc_favicon_url=f"{ASSETS_PATH}/favicon.png",
                with_google_fonts=False,
            ),
            workers=True,
        )

"""``/admin/static/NAME``: the dashboard's stylesheet and script, and plotly.js from the installed
``plotly`` package (nothing is loaded from another site: the server may have no internet)."""

from __future__ import annotations

from functools import lru_cache
from importlib.resources import files
from pathlib import Path

from fastapi.responses import FileResponse

from app.admin.routing import admin_router
from app.web.errors import not_found

router = admin_router()

STATIC_DIR = Path(__file__).resolve().parents[1] / "static"
#: Long enough to spare reloads; the pages add ``?v=<version>`` so an upgrade is fetched anew.
CACHE_CONTROL = "public, max-age=86400"
MEDIA_TYPES = {".css": "text/css", ".js": "text/javascript"}


@lru_cache
def static_files() -> dict[str, Path]:
    """The files served, by name (a fixed list: a name never reaches the file system)."""
    served = {path.name: path for path in STATIC_DIR.iterdir() if path.suffix in MEDIA_TYPES}
    served["plotly.min.js"] = Path(str(files("plotly") / "package_data" / "plotly.min.js"))
    return served


@router.get("/static/{name}")
def static_file(name: str) -> FileResponse:
    path = static_files().get(name)
    if path is None or not path.is_file():
        raise not_found(f"file {name}")
    return FileResponse(
        path,
        media_type=MEDIA_TYPES[path.suffix] + "; charset=utf-8",
        headers={"Cache-Control": CACHE_CONTROL},
    )

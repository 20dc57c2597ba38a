"""Any other ``/admin/…`` path: the 404 page (after the login check, so that the dashboard's
paths are not probed without one). Included last."""

from __future__ import annotations

from fastapi import Response
from fastapi.responses import RedirectResponse

from app.admin.auth import DashboardUserDep
from app.admin.routing import admin_router
from app.web.errors import not_found

router = admin_router()


@router.get("/{path:path}")
def unknown_page(_user: DashboardUserDep, path: str) -> Response:
    if not path:  # /admin/ is the overview
        return RedirectResponse("/admin", status_code=307)
    raise not_found(f"page /admin/{path}")

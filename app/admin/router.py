"""The admin dashboard's router: every page under ``/admin``, none in the OpenAPI document.

    app.include_router(router)        # in app.main.create_app

To add a page, add its module to ``PAGES`` (before ``not_found``) and an entry to
``app.admin.nav.NAV``.
"""

from __future__ import annotations

from fastapi import APIRouter

from app.admin.pages import (
    editor,
    jobs,
    keys,
    login,
    maps,
    not_found,
    overview,
    route_tester,
    sessions,
    static,
    sweeps,
)

PAGES = (static, login, overview, sessions, jobs, maps, sweeps, route_tester, editor, keys)

router = APIRouter(include_in_schema=False)
for page in PAGES:
    router.include_router(page.router)
router.include_router(not_found.router)  # last: it answers any other /admin path

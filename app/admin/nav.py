"""The dashboard's navigation: one entry per page, in menu order.

To add a page (e.g. Sweeps): write ``app/admin/pages/sweeps.py`` with ``router = admin_router()``
and its routes, add the module to ``PAGES`` in ``app/admin/router.py``, and add a
:class:`NavItem` here; its ``section`` is what the page's template sets as ``section`` to be marked
as the current page.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True, kw_only=True)
class NavItem:
    label: str
    url: str
    section: str


NAV = (
    NavItem(label="Overview", url="/admin", section="overview"),
    NavItem(label="Sessions", url="/admin/sessions", section="sessions"),
    NavItem(label="Jobs", url="/admin/jobs", section="jobs"),
    NavItem(label="Maps", url="/admin/maps", section="maps"),
    NavItem(label="Sweeps", url="/admin/sweeps", section="sweeps"),
    NavItem(label="Route tester", url="/admin/routes", section="routes"),
    NavItem(label="Corridor editor", url="/admin/editor", section="editor"),
    NavItem(label="API keys", url="/admin/keys", section="keys"),
)

"""Rendering pages: Jinja2 templates (autoescaped) with what every page shows, flash messages,
and the security headers of every dashboard response.

    return render(request, "map.html", section="maps", title="Map 3", map=info)
    return redirect(request, "/admin/jobs/5", flash="Job 5 canceled.")
    return redirect(request, "/admin/sweeps/4", flash="Rebuild queued as job 9.",
                    flash_link=("/admin/jobs/9", "Follow job 9"))
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from fastapi import Request, Response
from fastapi.responses import HTMLResponse, RedirectResponse
from fastapi.templating import Jinja2Templates

from app.admin.auth import DashboardUser, admin_state, set_cookie
from app.admin.nav import NAV
from app.services.system import package_version
from app.web.security import COMMON_HEADERS, PAGE_CSP

TEMPLATES_DIR = Path(__file__).resolve().parent / "templates"
FLASH_COOKIE = "im_admin_flash"
FLASH_TTL_S = 60

#: On every dashboard response. Nothing is loaded from another origin; no page may frame these.
#: Scripts only from our files (no inline script). Styles allow 'unsafe-inline' because plotly.js
#: styles its plots with inline style rules (its own stylesheet is not in the plotly package).
#: The dashboard's answers: the server's one policy (``app.web.security``) for its own pages.
SECURITY_HEADERS = {**COMMON_HEADERS, "Content-Security-Policy": PAGE_CSP}


def _when(value: datetime | None) -> str:
    return "—" if value is None else value.strftime("%Y-%m-%d %H:%M:%S UTC")


def _number(value: Any, digits: int = 3) -> str:
    """A number for people: ``digits`` significant digits, "—" when unknown or not finite."""
    if value is None or isinstance(value, bool) or not isinstance(value, int | float):
        return "—"
    if not math.isfinite(value):
        return "—"
    return f"{value:.{digits}g}" if isinstance(value, float) else str(value)


def _duration(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "—"
    minutes, rest_s = divmod(round(seconds), 60)
    return f"{minutes} min {rest_s} s" if minutes else f"{seconds:.1f} s"


def _percent(fraction: float) -> str:
    return f"{round(100 * fraction)}%"


templates = Jinja2Templates(directory=TEMPLATES_DIR)
templates.env.filters.update(when=_when, number=_number, duration=_duration, percent=_percent)
templates.env.globals.update(nav=NAV, server_version=package_version())


def render(
    request: Request, template: str, *, status_code: int = 200, **context: Any
) -> HTMLResponse:
    """The page ``template`` with ``context``, the logged-in user and any flash message."""
    user: DashboardUser | None = getattr(request.state, "admin_user", None)
    flash = _take_flash(request)
    response = templates.TemplateResponse(
        request,
        template,
        {"user": user, "csrf_token": user.csrf_token if user else "", "flash": flash, **context},
        status_code=status_code,
    )
    if flash is not None:
        response.delete_cookie(FLASH_COOKIE, path="/admin", httponly=True, samesite="strict")
    return response


@dataclass(frozen=True, slots=True, kw_only=True)
class Flash:
    """A message shown once, on the page a form redirects to; optionally with a link (a
    dashboard path) after it."""

    message: str
    link_url: str | None = None
    link_text: str | None = None

    def __str__(self) -> str:
        return self.message


def redirect(
    request: Request,
    url: str,
    *,
    flash: str | None = None,
    flash_link: tuple[str, str] | None = None,
) -> RedirectResponse:
    """303 to ``url`` (after a form), with a message to show there and, after it, a link
    ``(url, text)``."""
    response = RedirectResponse(url, status_code=303)
    if flash is not None:
        payload = {"message": flash}
        if flash_link is not None:
            payload["link_url"], payload["link_text"] = flash_link
        token = admin_state(request).signer.sign("flash", payload, ttl_s=FLASH_TTL_S)
        set_cookie(response, request, FLASH_COOKIE, token, max_age_s=FLASH_TTL_S)
    return response


def _take_flash(request: Request) -> Flash | None:
    cookie = request.cookies.get(FLASH_COOKIE)
    if cookie is None:
        return None
    payload = admin_state(request).signer.unsign("flash", cookie)
    if not payload or "message" not in payload:
        return None
    link_url, link_text = payload.get("link_url"), payload.get("link_text")
    if not (isinstance(link_url, str) and link_url.startswith("/admin/")):
        link_url = link_text = None
    return Flash(
        message=str(payload["message"]),
        link_url=link_url,
        link_text=str(link_text) if link_url else None,
    )


def add_security_headers(response: Response) -> None:
    for name, value in SECURITY_HEADERS.items():
        response.headers.setdefault(name, value)
    response.headers.setdefault("Cache-Control", "no-store")

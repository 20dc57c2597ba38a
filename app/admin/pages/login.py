"""``/admin/login``, ``/admin/logout`` and ``/admin/logins/end-all``.

A login takes an admin API key. The answers: a device key 403 ("a device key cannot log in"), an
unknown, revoked or expired key 401, a form without its CSRF token 403. Success stores
the login and sets its cookie and goes (303) to ``next`` (a dashboard path) or the overview.
After repeated failures from one address (or from all) an attempt is held a while before its
key is checked (:class:`~app.admin.auth.LoginThrottle`); no key is ever refused for that.
Logging out ends the login on the server; ``/admin/logins/end-all`` (on the API keys page) ends
every login.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Query, Request, Response

from app.admin.auth import (
    AdminStateDep,
    CheckedFormDep,
    LoginHoldDep,
    PostedFormDep,
    end_login,
    login_form_token,
    login_form_token_ok,
    login_source,
    safe_next,
    set_login_form_cookie,
    start_login,
)
from app.admin.routing import admin_router
from app.admin.templating import redirect, render
from app.storage import admin_logins, keys
from app.web.deps import DbDep, KeyUsage, SettingsDep

router = admin_router()


def _login_page(
    request: Request,
    state: AdminStateDep,
    *,
    next_url: str,
    error: str | None = None,
    status_code: int = 200,
) -> Response:
    token = login_form_token(request, state)
    response = render(
        request,
        "login.html",
        status_code=status_code,
        section="login",
        title="Log in",
        next_url=safe_next(next_url),
        form_token=token,
        error=error,
    )
    set_login_form_cookie(response, request, state, token)
    return response


@router.get("/login")
def login_form(
    request: Request,
    state: AdminStateDep,
    next_url: Annotated[str, Query(alias="next", max_length=2000)] = "/admin",
) -> Response:
    return _login_page(request, state, next_url=next_url)


@router.post("/login")
def log_in(
    request: Request,
    state: AdminStateDep,
    settings: SettingsDep,
    db: DbDep,
    form: PostedFormDep,
    _held: LoginHoldDep,
) -> Response:
    next_url = str(form.get("next") or "/admin")
    if not login_form_token_ok(request, state, form.get("form_token")):
        return _login_page(
            request,
            state,
            next_url=next_url,
            error="The login form expired or its security token is missing. Try again.",
            status_code=403,
        )
    key = str(form.get("key") or "").strip()
    if not key:
        return _login_page(
            request, state, next_url=next_url, error="Enter an admin API key.", status_code=422
        )
    with db.read() as db_session:
        principal = keys.authenticate(db_session, key, admin_key=settings.admin_key)
    if principal is None or not principal.is_admin:
        state.throttle.failed(login_source(request))
    if principal is None:
        return _login_page(
            request,
            state,
            next_url=next_url,
            error="That key is unknown, revoked or expired.",
            status_code=401,
        )
    if not principal.is_admin:
        return _login_page(
            request,
            state,
            next_url=next_url,
            error="That is a device key: a device key cannot log in. Use an admin key.",
            status_code=403,
        )
    if principal.key_id is not None:
        usage: KeyUsage = request.app.state.key_usage
        if usage.due(principal.key_id):
            with db.transaction() as db_session:
                keys.touch(db_session, principal.key_id)
    response = redirect(request, safe_next(next_url), flash="You are logged in.")
    start_login(response, request, state, db, principal, key)
    return response


@router.post("/logout")
def log_out(request: Request, state: AdminStateDep, db: DbDep, _form: CheckedFormDep) -> Response:
    response = redirect(request, "/admin/login", flash="You are logged out.")
    end_login(response, request, state, db)
    return response


@router.post("/logins/end-all")
def end_all_logins(request: Request, db: DbDep, _form: CheckedFormDep) -> Response:
    """End every dashboard login, this one included (a cookie someone copied, a shared
    computer, …)."""
    with db.transaction() as db_session:
        ended = admin_logins.end_all_logins(db_session)
    return redirect(
        request,
        "/admin/login",
        flash=f"Every dashboard session is ended ({ended}), yours too. Log in again.",
    )

"""``/admin/keys``: API keys — create (the secret shown once, on the answer to the form), list,
revoke; end every dashboard login. Revoking a key ends the dashboard logins it opened."""

from __future__ import annotations

from datetime import UTC, datetime, time

from fastapi import Request, Response

from app.admin.auth import CheckedFormDep, DashboardUserDep
from app.admin.routing import admin_router
from app.admin.templating import redirect, render
from app.services.errors import InvalidInput, ServiceError
from app.services.keys import create_checked_key
from app.storage import admin_logins, keys
from app.storage.orm import Role
from app.web.deps import DbDep, valid_id

router = admin_router()


def _keys_page(
    request: Request,
    db: DbDep,
    *,
    created: tuple[keys.KeyInfo, str] | None = None,
    error: str | None = None,
    submitted: dict[str, str] | None = None,
    status_code: int = 200,
) -> Response:
    with db.read() as db_session:
        infos = keys.list_keys(db_session)
        open_logins = admin_logins.count_logins(db_session)
    now = datetime.now(UTC)
    return render(
        request,
        "keys.html",
        status_code=status_code,
        section="keys",
        title="API keys",
        keys=infos,
        open_logins=open_logins,
        now=now,
        roles=list(Role),
        created=created,
        error=error,
        submitted=submitted or {},
    )


@router.get("/keys")
def key_list(request: Request, _user: DashboardUserDep, db: DbDep) -> Response:
    return _keys_page(request, db)


def _key_request(form: dict[str, str]) -> tuple[str, Role, datetime | None]:
    """The form's name, role and expiry (midnight UTC of the day given); InvalidInput with a
    readable reason. The name's rules are the API's (``create_checked_key``)."""
    expires = form.get("expires_on", "")
    try:
        expires_at = (
            datetime.combine(datetime.fromisoformat(expires).date(), time(0), tzinfo=UTC)
            if expires
            else None
        )
    except ValueError as err:
        raise InvalidInput(
            "validation_error", "Expires on: not a date", field="expires_on"
        ) from err
    try:
        role = Role(form.get("role", ""))
    except ValueError as err:
        roles = " or ".join(repr(r.value) for r in Role)
        raise InvalidInput(
            "validation_error", f"role: Input should be {roles}", field="role"
        ) from err
    return form.get("name", ""), role, expires_at


@router.post("/keys")
def create_key(request: Request, form: CheckedFormDep, db: DbDep) -> Response:
    submitted = {name: str(value).strip() for name, value in form.items() if isinstance(value, str)}
    try:
        name, role, expires_at = _key_request(submitted)
        with db.transaction() as db_session:
            created = create_checked_key(db_session, name=name, role=role, expires_at=expires_at)
    except ServiceError as err:
        return _keys_page(
            request, db, error=err.detail, submitted=submitted, status_code=err.status_code
        )
    return _keys_page(request, db, created=created, status_code=201)


@router.post("/keys/{key_id}/revoke")
def revoke_key(request: Request, _form: CheckedFormDep, db: DbDep, key_id: int) -> Response:
    with db.transaction() as db_session:
        info = keys.revoke_key(db_session, valid_id(key_id, "API key"))
    return redirect(request, "/admin/keys", flash=f"Key {info.id} ({info.name}) is revoked.")

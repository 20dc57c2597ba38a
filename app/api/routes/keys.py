"""``/v1/keys``: API keys (admin). A new key's secret is in the 201 answer and nowhere else: only
its SHA-256 is stored. Revoking (DELETE) keeps the key's record, with ``revoked_at``."""

from __future__ import annotations

from datetime import UTC, datetime

from fastapi import APIRouter, Response
from sqlalchemy.orm import Session

from app.api.deps import AdminPrincipal, ReadSessionDep, WriteSessionDep, valid_id
from app.api.errors import ApiError, error_responses
from app.api.route_class import SessionEndingRoute
from app.api.schemas import KeyCreate, KeyCreated, KeyPublic, KeysPublic
from app.storage import keys

router = APIRouter(prefix="/keys", tags=["keys"], route_class=SessionEndingRoute)


@router.post(
    "",
    status_code=201,
    summary="Create an API key",
    description="A device key (upload, read maps) or an admin key. The key is in this answer "
    "only: store it now.",
    responses=error_responses(401, 403, 422),
)
def create_key(
    new: KeyCreate, _admin: AdminPrincipal, session: WriteSessionDep, response: Response
) -> KeyCreated:
    info, secret = create_checked_key(session, new)
    response.headers["Location"] = f"/v1/keys/{info.id}"
    return KeyCreated(**KeyPublic.from_domain(info).model_dump(), key=secret)


def create_checked_key(session: Session, new: KeyCreate) -> tuple[keys.KeyInfo, str]:
    """Store the key ``new`` describes (422 if it would already have expired); returns it and its
    secret."""
    if new.expires_at is not None and new.expires_at <= datetime.now(UTC):
        raise ApiError(422, "validation_error", "expires_at is in the past", field="expires_at")
    return keys.create_key(session, name=new.name, role=new.role, expires_at=new.expires_at)


@router.get(
    "",
    summary="List API keys",
    description="Every key, oldest first, revoked and expired ones included; never secrets.",
    responses=error_responses(401, 403),
)
def list_keys(_admin: AdminPrincipal, session: ReadSessionDep) -> KeysPublic:
    infos = keys.list_keys(session)
    return KeysPublic(data=[KeyPublic.from_domain(info) for info in infos], count=len(infos))


@router.get(
    "/{key_id}",
    summary="Get an API key",
    description="One key's record (never its secret).",
    responses=error_responses(401, 403, 404, 422),
)
def get_key(key_id: int, _admin: AdminPrincipal, session: ReadSessionDep) -> KeyPublic:
    return KeyPublic.from_domain(keys.get_key(session, valid_id(key_id, "API key")))


@router.delete(
    "/{key_id}",
    summary="Revoke an API key",
    description="The key stops working at once; its record stays, with revoked_at. Revoking "
    "a revoked key changes nothing.",
    responses=error_responses(401, 403, 404, 422),
)
def revoke_key(key_id: int, _admin: AdminPrincipal, session: WriteSessionDep) -> KeyPublic:
    return KeyPublic.from_domain(keys.revoke_key(session, valid_id(key_id, "API key")))

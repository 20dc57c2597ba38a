"""``/v1/keys``: API keys (admin). A new key's secret is in the 201 answer and nowhere else: only
its SHA-256 is stored. Revoking (DELETE) keeps the key's record, with ``revoked_at``."""

from __future__ import annotations

from fastapi import APIRouter, Response

from app.api.schemas.keys import KeyCreate, KeyCreated, KeyPublic, KeysPublic
from app.services.keys import create_checked_key
from app.storage import keys
from app.web.deps import AdminPrincipal, KeyId, ReadDbSessionDep, WriteDbSessionDep, valid_id
from app.web.errors import error_responses
from app.web.route_class import SessionEndingRoute

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
    new: KeyCreate, _admin: AdminPrincipal, db_session: WriteDbSessionDep, response: Response
) -> KeyCreated:
    info, secret = create_checked_key(
        db_session, name=new.name, role=new.role, expires_at=new.expires_at
    )
    response.headers["Location"] = f"/v1/keys/{info.id}"
    response.headers["Cache-Control"] = "no-store"  # the answer carries the secret
    return KeyCreated(**KeyPublic.model_validate(info).model_dump(), key=secret)


@router.get(
    "",
    summary="List API keys",
    description="Every key, oldest first, revoked and expired ones included; never secrets.",
    responses=error_responses(401, 403),
)
def list_keys(_admin: AdminPrincipal, db_session: ReadDbSessionDep) -> KeysPublic:
    infos = keys.list_keys(db_session)
    return KeysPublic(data=[KeyPublic.model_validate(info) for info in infos], count=len(infos))


@router.get(
    "/{key_id}",
    summary="Get an API key",
    description="One key's record (never its secret).",
    responses=error_responses(401, 403, 404, 422),
)
def get_key(key_id: KeyId, _admin: AdminPrincipal, db_session: ReadDbSessionDep) -> KeyPublic:
    return KeyPublic.model_validate(keys.get_key(db_session, valid_id(key_id, "API key")))


@router.delete(
    "/{key_id}",
    summary="Revoke an API key",
    description="The key stops working at once; its record stays, with revoked_at. Revoking "
    "a revoked key changes nothing.",
    responses=error_responses(401, 403, 404, 422),
)
def revoke_key(key_id: KeyId, _admin: AdminPrincipal, db_session: WriteDbSessionDep) -> KeyPublic:
    return KeyPublic.model_validate(keys.revoke_key(db_session, valid_id(key_id, "API key")))

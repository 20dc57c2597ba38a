"""``/v1/sessions``: upload a mapping session, list and read sessions, download the raw upload.

An upload is validated completely before anything is stored (architecture §2); then the session, its
raw bytes, its map and its build job are written in one transaction, and the answer is 202 with
the ids and ``Location: /v1/jobs/{job_id}``.

Idempotency: with ``Idempotency-Key: <up to 200 visible ASCII characters>``, a second upload by
the same key holder with the same key and the same bytes answers **202 again with the first
upload's body** (same ``session_id``, ``map_id``, ``job_id``) and ``Idempotent-Replayed: true``,
storing nothing; the same key with different bytes is a 409 ``idempotency_conflict``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from typing import Annotated, Any

from fastapi import APIRouter, Header, Query, Response

from app.api.schemas.sessions import ImageStored, SessionCreated, SessionPublic, SessionsPublic
from app.domain.upload.session import Session as ParsedSession
from app.services.maps import image_url, merge_maps, store_session_image, tuning_refused
from app.services.uploads import parse_upload
from app.storage import keys, maps, sessions
from app.storage.db import Database
from app.storage.keys import Principal
from app.storage.sessions import MAX_IDEMPOTENCY_KEY_LENGTH, MAX_MAP_NAME_LENGTH, UploadResult
from app.web.deps import (
    ID_RULE,
    CurrentPrincipal,
    DbDep,
    ImageBodyDep,
    ReadDbSessionDep,
    SessionDep,
    SettingsDep,
    UploadBodyDep,
    admin_principal,
    is_id,
)
from app.web.errors import ApiError, error_responses, unauthorized
from app.web.http import raw_upload_response
from app.web.route_class import SessionEndingRoute
from app.web.upload import decode_body

router = APIRouter(prefix="/sessions", tags=["sessions"], route_class=SessionEndingRoute)

IdempotencyKey = Annotated[
    str | None,
    Header(
        alias="Idempotency-Key",
        min_length=1,
        max_length=MAX_IDEMPOTENCY_KEY_LENGTH,
        pattern=r"^[\x21-\x7e]+$",
        description="Makes a retried upload return the first result instead of a second "
        "session (1–200 visible ASCII characters, unique per upload and key holder).",
        examples=["3f1c2a9e-occam-1"],
    ),
]
ContentEncoding = Annotated[
    str | None,
    Header(
        alias="Content-Encoding",
        description="gzip to send the JSON compressed (the limit on the decompressed size "
        "applies); otherwise leave it out",
        examples=["gzip"],
    ),
]
Limit = Annotated[int, Query(ge=1, le=200, description="page size")]
Offset = Annotated[int, Query(ge=0, le=2**31, description="items to skip")]

_IDENTITY = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
UPLOAD_EXAMPLE: dict[str, Any] = {
    "map_id": "lobby",
    "pose_data": [
        {"id": 0, "timestamp": 0.0, "pose": _IDENTITY, "planes": []},
        {"id": 1, "timestamp": 0.1, "pose": [*_IDENTITY[:12], 0.05, 0, 0, 1], "planes": []},
    ],
    "tag_data": [
        [
            {
                "tag_id": 3,
                "pose_id": 1,
                "timestamp": 0.1,
                "tag_pose": [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 1.5, 0, 0, 0, 1],
                "camera_intrinsics": [1590.0, 1590.0, 950.0, 720.0],
                "tag_corners_pixel_coordinates": [
                    *(858.31, 811.69, 1041.69, 811.69, 1041.69, 628.31, 858.31, 628.31)
                ],
                "tag_position_variance": [1e-6, 1e-6, 1e-5],
                "tag_orientation_variance": [1e-4, 1e-4, 1e-4, 1e-4],
            }
        ]
    ],
    "location_data": [],
    "plane_data": [],
}
UPLOAD_REQUEST_BODY: dict[str, Any] = {
    "required": True,
    "description": "The app's mapping session (docs/architecture.md §2), as JSON; may be sent with "
    "Content-Encoding: gzip. Unknown keys are accepted and kept in the raw upload.",
    "content": {
        "application/json": {
            "schema": {
                "type": "object",
                "required": ["map_id", "pose_data"],
                "additionalProperties": True,
                "properties": {
                    "map_id": {"type": "string", "maxLength": MAX_MAP_NAME_LENGTH},
                    "pose_data": {
                        "type": "array",
                        "minItems": 1,
                        "description": "{id, timestamp (s), pose: 16 numbers, column-major "
                        "world_T_phone}",
                        "items": {"type": "object"},
                    },
                    "tag_data": {
                        "type": "array",
                        "description": "frames of detections {tag_id, pose_id, tag_pose (16, "
                        "row-major, OpenCV camera_T_tag), camera_intrinsics, "
                        "tag_corners_pixel_coordinates, …}",
                        "items": {"type": "array", "items": {"type": "object"}},
                    },
                    "location_data": {
                        "type": "array",
                        "description": "points of interest {name, pose_id, transform}",
                        "items": {"type": "object"},
                    },
                    "plane_data": {"type": "array", "description": "ignored"},
                },
            },
            "examples": {"two poses, one tag": {"value": UPLOAD_EXAMPLE}},
        }
    },
}


@router.post(
    "",
    status_code=202,
    summary="Upload a mapping session",
    description="Validate the session, store it (raw bytes kept, gzip-compressed, never "
    "changed), create its map and queue the job that builds it. Answers 202 with the ids and "
    "`Location: /v1/jobs/{job_id}`. A retry with the same `Idempotency-Key` answers 202 with the "
    "first upload's body and `Idempotent-Replayed: true`. The answer's `shares_tags_with` names "
    "other maps with some of its tags (nothing merges by itself). `?into_map=N` (admin) puts the "
    "session into existing map N instead, which is rebuilt from all its sessions "
    "(docs/multi-session.md); 404 if there is no map N, and nothing is stored.",
    response_description="Accepted: the map is being built; follow job_url.",
    openapi_extra={"requestBody": UPLOAD_REQUEST_BODY},
    responses=error_responses(
        400,
        401,
        403,
        404,
        409,
        413,
        415,
        422,
        429,
        examples={
            409: (
                "idempotency_conflict",
                "Idempotency-Key '3f1c2a9e-occam-1' was used for session 17: the body differs "
                "from that upload; use a new key for a new upload",
            )
        },
    ),
)
def upload_session(
    principal: CurrentPrincipal,
    body: UploadBodyDep,
    db: DbDep,
    settings: SettingsDep,
    response: Response,
    idempotency_key: IdempotencyKey = None,
    content_encoding: ContentEncoding = None,  # noqa: ARG001 (read with the body; here for the docs)
    auto_tune_trials: Annotated[
        int,
        Query(
            ge=0,
            le=1000,
            description="tune the noise variances by the shift metric with this many sampler "
            "trials before building (0: the default parameters); a map of one session only, so "
            "with into_map a 422",
        ),
    ] = 0,
    into_map: Annotated[
        int | None,
        Query(
            description="admin: upload into this existing map (a building's map of several "
            "sessions): the session joins its sessions and the map is rebuilt; without it the "
            f"upload makes a map of its own. The map's id: {ID_RULE} (404 not_found)",
        ),
    ] = None,
) -> SessionCreated:
    if into_map is not None:
        admin_principal(principal)  # 403 for a device key
        if auto_tune_trials:  # refused at the door, never a build that drops or fails it
            raise tuning_refused(into_map)
    if not principal.is_admin and auto_tune_trials > settings.device_max_auto_tune_trials:
        raise ApiError(
            422,
            "validation_error",
            f"auto_tune_trials: a device key may ask for at most "
            f"{settings.device_max_auto_tune_trials} trials (an admin key up to 1000), got "
            f"{auto_tune_trials}",
            field="auto_tune_trials",
        )
    upload = decode_body(body, max_session_bytes=settings.max_session_bytes)
    result = _replayed(db, principal, idempotency_key, upload.stored.sha256)
    if result is None:
        parsed = _parse(upload.json_chunks(), max_poses=settings.max_poses)
        # The write transaction starts only now: parsing never holds SQLite's write lock.
        with db.transaction() as db_session:
            # the key may have been revoked while the body arrived: check it again, in the
            # transaction that stores
            if principal.key_id is not None and not keys.active_principal(
                db_session, principal.key_id
            ):
                raise unauthorized("API key revoked or expired while uploading")
            result = sessions.create_session(
                db_session,
                parsed=parsed,
                upload=upload.stored,
                uploaded_by=principal.subject,
                idempotency_key=idempotency_key,
                max_attempts=settings.max_attempts,
                auto_tune_trials=auto_tune_trials,
            )
            if into_map is not None and not result.replayed:
                if not is_id(into_map):  # as a map that does not exist: the upload rolled back
                    raise maps.MapNotFound(into_map)
                # its own map merged into the one named (404 there rolls the upload back)
                build = merge_maps(
                    db_session, into_map, result.map_id, max_attempts=settings.max_attempts
                )
                result = dataclasses.replace(
                    result,
                    map_id=build.info.id,
                    job_id=build.job_id,
                    shares_tags_with=tuple(
                        t for t in result.shares_tags_with if t[0] != build.info.id
                    ),
                )
    response.headers["Location"] = f"/v1/jobs/{result.job_id}"
    if result.replayed:
        response.headers["Idempotent-Replayed"] = "true"
    return SessionCreated.from_domain(result)


def _replayed(
    db: Database, principal: Principal, idempotency_key: str | None, sha256: str
) -> UploadResult | None:
    """The earlier upload's result if this is a retry (checked before the costly parse;
    ``create_session`` checks again in its transaction, for retries that race)."""
    if idempotency_key is None:
        return None
    with db.read() as db_session:
        earlier = sessions.find_by_idempotency_key(db_session, principal.subject, idempotency_key)
        return None if earlier is None else sessions.replay_upload(db_session, earlier, sha256)


def _parse(json_chunks: Iterable[bytes], *, max_poses: int) -> ParsedSession:
    """The validated session; SessionFormatError (422, naming the field) otherwise."""
    return parse_upload(json_chunks, max_poses=max_poses)


@router.get(
    "",
    summary="List sessions",
    description="Newest first. A device key sees the sessions it uploaded; an admin all.",
    responses=error_responses(401, 422),
)
def list_sessions(
    db_session: ReadDbSessionDep, principal: CurrentPrincipal, limit: Limit = 50, offset: Offset = 0
) -> SessionsPublic:
    infos, total = sessions.list_sessions(
        db_session,
        limit=limit,
        offset=offset,
        uploaded_by=None if principal.is_admin else principal.subject,
    )
    return SessionsPublic(
        data=[SessionPublic.model_validate(info) for info in infos],
        count=total,
        limit=limit,
        offset=offset,
    )


@router.get(
    "/{session_id}",  # noqa: FAST003 (session_id is read by SessionDep)
    summary="Get a session",
    description="Metadata, statistics, its map and its jobs.",
    responses=error_responses(401, 404, 422),
)
def get_session(info: SessionDep) -> SessionPublic:
    return SessionPublic.model_validate(info)


@router.get(
    "/{session_id}/raw",  # noqa: FAST003 (session_id is read by SessionDep)
    summary="Download the raw upload",
    description="The JSON exactly as uploaded, byte for byte (after undoing the upload's "
    "Content-Encoding). Sent gzip-compressed (`Content-Encoding: gzip`) to clients that accept "
    "it; any HTTP client decodes that to the same bytes. Streamed from the database in 1 MiB "
    "pieces.",
    response_class=Response,
    responses={
        200: {
            "description": "the upload's JSON bytes",
            "content": {"application/json": {"example": UPLOAD_EXAMPLE}},
        },
        **error_responses(401, 404, 422),
    },
)
def get_raw_session(
    info: SessionDep,
    db: DbDep,
    accept_encoding: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> Response:
    return raw_upload_response(db, info.id, accept_encoding)


@router.put(
    "/{session_id}/image",  # noqa: FAST003 (session_id is read by SessionDep)
    summary="Upload the session's picture",
    description="The JPEG the app takes of the mapped place (`Content-Type: image/jpeg`, at most "
    "4 MiB), shown with the session's map (`GET /v1/maps/{id}/image`, `image_url` in the maps "
    "list). Idempotent: the same bytes again change nothing (`changed: false`); other bytes "
    "replace the picture.",
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {
                "image/jpeg": {
                    "schema": {"type": "string", "format": "binary"},
                    "example": "(JPEG bytes)",
                }
            },
        }
    },
    responses=error_responses(401, 404, 413, 415, 422),
)
def put_session_image(info: SessionDep, body: ImageBodyDep, db: DbDep) -> ImageStored:
    with db.transaction() as db_session:
        stored = store_session_image(db_session, info.id, body)
        map_info = maps.get_map(db_session, info.map_id) if info.map_id is not None else None
    return ImageStored(
        session_id=info.id,
        map_id=info.map_id,
        sha256=stored.sha256,
        size_bytes=stored.size_bytes,
        changed=stored.changed,
        image_url=image_url(map_info) if map_info is not None else None,
    )

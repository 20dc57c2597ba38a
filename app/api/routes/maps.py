"""``/v1/maps``: maps, their versions, the app's download format, plots; rebuild and delete.

A map is made from one session; every successful build adds a version (1, 2, …) and the newest is
the map's current version. Until the first build succeeds the map exists with
``current_version: null``; its ``latest_job`` tells "still building" from "build failed".

Choices:
- ``GET /v1/maps/{id}`` carries a strong ``ETag`` derived from the current version's number and
  content hash and the newest job's id and state; ``If-None-Match`` with it answers 304.
  ``app-map`` and ``plot.png`` carry an ETag of the version they come from.
- ``app-map`` and ``plot.png`` of a map with no version yet are a **409 ``map_not_ready``** (the map
  exists, it has nothing to download yet), not a 404, which means "no such map (or version)".
- A rebuild queues a new ``build_map`` job for the map's session with the given parameter
  overrides; the raw session is never modified. It answers 202 with ``Location`` of the job.
- A map may be made of several sessions (docs/multi-session.md): ``/{id}/sessions`` lists them,
  ``POST`` adds one, ``DELETE /{id}/sessions/{session_id}`` takes one out, ``POST /{id}/merge``
  merges another map in. Each change queues the rebuild that makes the version of the new set
  (202, like a rebuild); the version records exactly which sessions it used.
- Versions always match their walks (docs/multi-session.md, "Versions and membership"): each
  change bumps the map's ``generation``; a build stores its version only if it was built for the
  map's generation; changes in quick succession fold into the one build that has not started.
"""

from __future__ import annotations

import gzip
from typing import Annotated, Any

from fastapi import APIRouter, Body, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from sqlalchemy.orm import Session

from app.api.schemas.maps import (
    AddSessionRequest,
    AppMap,
    MapPublic,
    MapSessionsPublic,
    MapsPublic,
    MapSummary,
    MapUpdate,
    MergeRequest,
    RebuildAccepted,
    RebuildRequest,
    VersionDetail,
    VersionsPublic,
    VersionSummary,
)
from app.services.corridor_edits import app_map_with_edits_gzip
from app.services.maps import (
    APP_MAP_EXPORT,
    BuildQueued,
    MapPages,
    MapState,
    add_session_to_map,
    checked_ground_truth,
    checked_overrides,
    checked_session_ids,
    chosen_version,
    current_version,
    delete_map_and_jobs,
    merge_maps,
    picture_of_map,
    remove_session_from_map,
    rename_map,
    request_build,
    tag_poses_of,
)
from app.services.version_cache import VersionCache
from app.storage import maps
from app.storage.db import Database
from app.storage.maps import MapInfo, VersionInfo
from app.storage.sessions import AUTO_TUNE_TRIALS, GROUND_TRUTH
from app.web.deps import (
    AdminPrincipal,
    DbDep,
    MapDep,
    MapId,
    MapStateDep,
    ReadDbSessionDep,
    SessionId,
    SettingsDep,
    VersionNumber,
    VersionQuery,
    WriteDbSessionDep,
    valid_id,
    valid_version,
)
from app.web.errors import ApiError, error_responses
from app.web.http import (
    JSON_MEDIA_TYPE,
    AcceptEncoding,
    IfNoneMatch,
    ReadyDocument,
    if_none_match_hits,
    strong_etag,
)
from app.web.route_class import SessionEndingRoute

router = APIRouter(prefix="/maps", tags=["maps"], route_class=SessionEndingRoute)

Limit = Annotated[int, Query(ge=1, le=200, description="page size")]
Offset = Annotated[int, Query(ge=0, le=2**31, description="items to skip")]

NOT_MODIFIED: dict[int | str, dict[str, Any]] = {
    304: {"description": "Not modified: the copy with this ETag is current"}
}
NOT_READY_EXAMPLE = (
    "map_not_ready",
    "map 12 has no version yet: its build job 31 is queued; follow /v1/jobs/31",
)


@router.get(
    "",
    summary="List maps",
    description="Newest first; with tag_id, only maps whose current version has that tag.",
    response_model=MapsPublic,
    responses=error_responses(401, 422),
)
async def list_maps(
    request: Request,
    db: DbDep,
    limit: Limit = 50,
    offset: Offset = 0,
    tag_id: Annotated[
        int | None, Query(ge=0, le=2**53, description="only maps containing this tag")
    ] = None,
) -> Response:
    pages: MapPages = request.app.state.map_pages
    query = (limit, offset, tag_id)
    content = pages.fresh(query)
    if content is None:
        content = await run_in_threadpool(
            pages.make, query, lambda: _maps_page(db, limit=limit, offset=offset, tag_id=tag_id)
        )
    return Response(content=content, media_type=JSON_MEDIA_TYPE)


def _maps_page(db: Database, *, limit: int, offset: int, tag_id: int | None) -> bytes:
    with db.read() as db_session:
        infos, total = maps.list_maps(db_session, limit=limit, offset=offset, tag_id=tag_id)
    page = MapsPublic(
        data=[MapSummary.from_domain(info) for info in infos],
        count=total,
        limit=limit,
        offset=offset,
    )
    return page.__pydantic_serializer__.to_json(page)


@router.get(
    "/{map_id}",  # noqa: FAST003 (map_id is read by MapStateDep)
    summary="Get a map",
    description="The current version (parameters, statistics, metrics with the shift metric, "
    "tag poses) and the newest job. Strong ETag; If-None-Match answers 304; gzip-compressed for "
    "clients that accept it.",
    response_model=MapPublic,
    responses={**NOT_MODIFIED, **error_responses(401, 404, 422)},
)
async def get_map(
    state: MapStateDep,
    request: Request,
    db: DbDep,
    if_none_match: IfNoneMatch = None,
    accept_encoding: AcceptEncoding = None,
) -> Response:
    document: ReadyDocument | None = state.documents.get(MAP_DOCUMENT)
    if document is None:
        document = await run_in_threadpool(
            _map_document, request.app.state.version_cache, db, state
        )
        request.app.state.map_states.attach(state, MAP_DOCUMENT, document)
    return document.response(if_none_match, accept_encoding)


#: The map document's key in a :class:`MapState`'s ``documents``.
MAP_DOCUMENT = "map"


def _map_document(cache: VersionCache, db: Database, state: MapState) -> ReadyDocument:
    """``GET /v1/maps/{id}``'s answer for ``state``, made once per state."""
    current = state.info.current
    with db.read() as db_session:
        tags = tag_poses_of(cache, db_session, current.id) if current else []
    public = MapPublic.from_domain(state.info, tags=tags, latest_job=state.latest_job)
    return ReadyDocument.of(
        public.__pydantic_serializer__.to_json(public), media_type=JSON_MEDIA_TYPE
    )


@router.get(
    "/{map_id}/versions",  # noqa: FAST003 (map_id is read by MapDep)
    summary="List a map's versions",
    description="Every version, oldest first: parameters, statistics and metrics of each.",
    responses=error_responses(401, 404, 422),
)
def list_versions(info: MapDep, db_session: ReadDbSessionDep) -> VersionsPublic:
    versions = maps.list_versions(db_session, info.id)
    return VersionsPublic(
        data=[VersionSummary.model_validate(version) for version in versions], count=len(versions)
    )


@router.get(
    "/{map_id}/versions/{number}",  # noqa: FAST003 (map_id is read by MapDep)
    summary="Get a map version",
    description="One version with its tag poses and the detections it left out (and why).",
    responses=error_responses(401, 404, 422),
)
def get_version(info: MapDep, number: VersionNumber, db_session: ReadDbSessionDep) -> VersionDetail:
    version = maps.get_version(db_session, info.id, valid_version(info.id, number))
    return VersionDetail.with_details(version, maps.tag_poses(db_session, version.id))


@router.post(
    "/{map_id}/rebuild",
    status_code=202,
    summary="Rebuild a map",
    description="Queue a new build of the map's sessions, optionally with other SLAM "
    "parameters (any SlamParams field; unknown names and out-of-range values are a 422 naming "
    "the parameter), other sessions (which become the map's) and ground truth (the version then "
    "carries the ground-truth metric; a bad one is a 422 invalid_ground_truth naming the field). "
    "A build of the map queued before and not started yet takes the request instead "
    "(`coalesced`); a running one is asked to stop (`superseded_job_ids`): only a build of the "
    "map's current sessions and parameters stores a version. `auto_tune_trials` on a map of "
    "several sessions is a 422. The raw sessions are never modified (admin).",
    responses=error_responses(401, 403, 404, 422),
)
def rebuild_map(
    map_id: MapId,
    _admin: AdminPrincipal,
    db_session: WriteDbSessionDep,
    settings: SettingsDep,
    response: Response,
    body: Annotated[RebuildRequest | None, Body()] = None,
) -> RebuildAccepted:
    overrides = checked_overrides(body.params if body else {})
    if body and body.auto_tune_trials:
        overrides[AUTO_TUNE_TRIALS] = body.auto_tune_trials
    answered = dict(overrides)  # the answer does not echo the ground truth
    if body and body.ground_truth is not None:
        overrides[GROUND_TRUTH] = checked_ground_truth(body.ground_truth)
    session_ids = body.session_ids if body else None
    if session_ids is not None:
        checked_session_ids(db_session, session_ids)
    build = request_build(
        db_session,
        valid_id(map_id, "map"),
        overrides,
        max_attempts=settings.max_attempts,
        change="rebuild requested",
        session_ids=session_ids,
    )
    accepted = RebuildAccepted.from_build(build, answered)
    response.headers["Location"] = accepted.job_url
    return accepted


@router.get(
    "/{map_id}/sessions",  # noqa: FAST003 (map_id is read by MapDep)
    summary="The sessions of a map",
    description="In order (the first is the map frame), each with what it contributed to the "
    "current version.",
    responses=error_responses(401, 404, 422),
)
def list_map_sessions(info: MapDep) -> MapSessionsPublic:
    return MapSessionsPublic.from_domain(info)


@router.post(
    "/{map_id}/sessions",
    status_code=202,
    summary="Add a session to a map",
    description="Add an uploaded session (it stays in its own map too) and queue the rebuild "
    "of the map from all its sessions. 409 already_in_map. A session whose tags cannot place it "
    "in the map fails that build with the reason (no_shared_tags, too_few_shared_tags, "
    "inconsistent_shared_tags); the map keeps its current version (admin).",
    responses=error_responses(401, 403, 404, 409, 422),
)
def add_map_session(
    map_id: MapId,
    body: AddSessionRequest,
    _admin: AdminPrincipal,
    db_session: WriteDbSessionDep,
    settings: SettingsDep,
    response: Response,
) -> RebuildAccepted:
    build = add_session_to_map(
        db_session,
        valid_id(map_id, "map"),
        valid_id(body.session_id, "session"),
        max_attempts=settings.max_attempts,
    )
    return _accepted(response, build)


@router.delete(
    "/{map_id}/sessions/{session_id}",
    status_code=202,
    summary="Take a session out of a map",
    description="The session and its upload stay; queues the rebuild without it. 404 not_in_map; "
    "409 last_session (a map needs one: delete the map instead) (admin).",
    responses=error_responses(401, 403, 404, 409, 422),
)
def remove_map_session(
    map_id: MapId,
    session_id: SessionId,
    _admin: AdminPrincipal,
    db_session: WriteDbSessionDep,
    settings: SettingsDep,
    response: Response,
) -> RebuildAccepted:
    build = remove_session_from_map(
        db_session,
        valid_id(map_id, "map"),
        session_id,  # compared with the map's sessions: one out of range is not in the map
        max_attempts=settings.max_attempts,
    )
    return _accepted(response, build)


@router.post(
    "/{map_id}/merge",
    status_code=202,
    summary="Merge another map into this one",
    description="The other map's sessions join this map's (after them) and the other map is "
    "deleted (its uploads stay); queues the rebuild. The upload's answer names the maps a new "
    "session shares tags with. 409 same_map (admin).",
    responses=error_responses(401, 403, 404, 409, 422),
)
def merge_map(
    map_id: MapId,
    body: MergeRequest,
    _admin: AdminPrincipal,
    db_session: WriteDbSessionDep,
    settings: SettingsDep,
    response: Response,
) -> RebuildAccepted:
    build = merge_maps(
        db_session,
        valid_id(map_id, "map"),
        valid_id(body.map_id, "map"),
        max_attempts=settings.max_attempts,
    )
    return _accepted(response, build)


def _accepted(response: Response, build: BuildQueued) -> RebuildAccepted:
    accepted = RebuildAccepted.from_build(build, build.params)
    response.headers["Location"] = accepted.job_url
    return accepted


@router.get(
    "/{map_id}/app-map",  # noqa: FAST003 (map_id is read by MapDep)
    summary="Download the map in the app's format",
    description="`{tag_vertices, odometry_vertices, waypoints_vertices}` (architecture §7) of the "
    "current version, or of `?version=N`, made so the app's route planner can use it: every "
    "`neighbors` link listed at both ends, one connected graph (graph nodes that are no pose are "
    "extra odometry vertices numbered after the last pose), unique waypoint names; `notes` says "
    "what was adjusted. Gzip-compressed for clients that accept it. 409 map_not_ready while the "
    "map has no version.",
    response_model=AppMap,
    responses={
        **NOT_MODIFIED,
        **error_responses(401, 404, 409, 422, examples={409: NOT_READY_EXAMPLE}),
    },
)
async def get_app_map(
    state: MapStateDep,
    request: Request,
    db: DbDep,
    version: VersionQuery = None,
    if_none_match: IfNoneMatch = None,
    accept_encoding: AcceptEncoding = None,
) -> Response:
    cache: VersionCache = request.app.state.version_cache
    revision = state.info.corridor_edits_revision
    document: ReadyDocument | None = None
    if version is None:
        document = cache.peek(
            (APP_MAP_DOCUMENT, APP_MAP_EXPORT, current_version(state).id, revision)
        )
    if document is None:
        if version is not None:
            valid_version(state.info.id, version)
        document = await run_in_threadpool(_app_map_document, cache, db, state.info, version)
    return document.response(if_none_match, accept_encoding)


#: The app-map's key in the VersionCache (with the export's version and the version's id).
APP_MAP_DOCUMENT = "app_map_document"


def _app_map_document(
    cache: VersionCache, db: Database, info: MapInfo, number: int | None
) -> ReadyDocument:
    with db.read() as db_session:
        chosen = chosen_version(db_session, info, number)
        revision = info.corridor_edits_revision
        return cache.get(
            (APP_MAP_DOCUMENT, APP_MAP_EXPORT, chosen.id, revision),
            lambda: _ready_app_map(cache, db_session, chosen, revision),
        )


def _ready_app_map(
    cache: VersionCache, db_session: Session, version: VersionInfo, revision: int
) -> ReadyDocument:
    """The app-map of ``version`` with its map's corridor edits as of ``revision``; its ETag
    names the version, the export's own version (a rebuild that changes nothing still gets a
    new ETag, so a phone learns of the version) and the edits."""
    zipped, digest = app_map_with_edits_gzip(cache, db_session, version, revision)
    return ReadyDocument.of(
        gzip.decompress(zipped),
        media_type=JSON_MEDIA_TYPE,
        gzipped=zipped,
        etag=strong_etag(
            "app-map",
            APP_MAP_EXPORT,
            version.map_id,
            version.number,
            version.content_sha256,
            *((digest,) if digest else ()),
        ),
    )


@router.patch(
    "/{map_id}",
    summary="Change a map",
    description="Set the map's display name, the name people see in the app's list (admin). "
    "The upload's map_id (`name`) never changes.",
    responses=error_responses(401, 403, 404, 422),
)
def update_map(
    map_id: MapId, change: MapUpdate, _admin: AdminPrincipal, db_session: WriteDbSessionDep
) -> MapSummary:
    return MapSummary.from_domain(
        rename_map(db_session, valid_id(map_id, "map"), change.display_name)
    )


@router.get(
    "/{map_id}/image",  # noqa: FAST003 (map_id is read by MapDep)
    summary="The map's picture",
    description="The JPEG the app sent with the map's session. Use `image_url` from the maps "
    "list: it carries the picture's version (`?v=`), and that answer may be cached for a year "
    "(a new picture gets a new URL); without it, revalidate with the ETag. 404 no_image when the "
    "map has no picture.",
    response_class=Response,
    responses={
        200: {
            "description": "the picture",
            "content": {
                "image/jpeg": {
                    "schema": {"type": "string", "format": "binary"},
                    "example": "(JPEG bytes)",
                }
            },
        },
        **NOT_MODIFIED,
        **error_responses(401, 404, 422),
    },
)
def get_image(
    info: MapDep,
    db_session: ReadDbSessionDep,
    v: Annotated[
        str | None, Query(max_length=64, description="the picture's version, from image_url")
    ] = None,
    if_none_match: IfNoneMatch = None,
) -> Response:
    picture = picture_of_map(db_session, info.id)
    etag = strong_etag("image", picture.sha256)
    cache = (
        "private, max-age=31536000, immutable"
        if v is not None and picture.sha256.startswith(v) and len(v) >= 8
        else "private, no-cache"
    )
    headers = {"ETag": etag, "Cache-Control": cache}
    if if_none_match_hits(if_none_match, etag):
        return Response(status_code=304, headers=headers)
    return Response(content=picture.jpeg, media_type="image/jpeg", headers=headers)


@router.get(
    "/{map_id}/plot.png",  # noqa: FAST003 (map_id is read by MapDep)
    summary="Plot of the map",
    description="Top-down PNG of the current version (or `?version=N`): raw and optimized "
    "trajectory and tags, one panel per floor. 409 map_not_ready while the map has no version.",
    response_class=Response,
    responses={
        200: {
            "description": "the plot",
            "content": {"image/png": {"schema": {"type": "string", "format": "binary"},
                                      "example": "(PNG bytes)"}},
        },
        **NOT_MODIFIED,
        **error_responses(401, 404, 409, 422, examples={409: NOT_READY_EXAMPLE}),
    },
)  # fmt: skip
def get_plot(
    info: MapDep,
    db_session: ReadDbSessionDep,
    version: VersionQuery = None,
    if_none_match: IfNoneMatch = None,
) -> Response:
    if version is not None:
        valid_version(info.id, version)
    chosen = chosen_version(db_session, info, version)
    etag = strong_etag("plot", chosen.map_id, chosen.number, chosen.content_sha256)
    if if_none_match_hits(if_none_match, etag):
        return Response(status_code=304, headers={"ETag": etag})
    png = maps.plot_png(db_session, info.id, chosen.number)
    if png is None:
        raise ApiError(404, "not_found", f"version {chosen.number} of map {info.id} has no plot")
    return Response(content=png, media_type="image/png", headers={"ETag": etag})


@router.delete(
    "/{map_id}",
    status_code=204,
    summary="Delete a map",
    description="Cancel its unfinished jobs and delete the map with its versions (its jobs go "
    "with it; the session and its raw upload stay) (admin).",
    response_class=Response,
    responses=error_responses(401, 403, 404, 422),
)
def delete_map(map_id: MapId, _admin: AdminPrincipal, db_session: WriteDbSessionDep) -> None:
    delete_map_and_jobs(db_session, valid_id(map_id, "map"))

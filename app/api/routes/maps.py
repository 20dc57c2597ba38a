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
"""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import APIRouter, Body, Header, Query, Response
from sqlalchemy.orm import Session

from app.api.deps import (
    AdminPrincipal,
    MapDep,
    ReadSessionDep,
    SettingsDep,
    WriteSessionDep,
    valid_id,
)
from app.api.errors import ApiError, error_responses
from app.api.http import if_none_match_hits, strong_etag
from app.api.route_class import SessionEndingRoute
from app.api.schemas import (
    AppMap,
    MapPublic,
    MapsPublic,
    MapSummary,
    RebuildAccepted,
    RebuildRequest,
    VersionDetail,
    VersionsPublic,
    VersionSummary,
)
from app.domain.errors import ParameterError
from app.domain.map_io import map_from_json, map_to_app_format
from app.domain.params import SlamParams
from app.domain.path_graph import path_graph_from_json
from app.storage import maps, queue
from app.storage.maps import MapInfo, VersionInfo
from app.storage.navigation import path_graph_document
from app.storage.sessions import AUTO_TUNE_TRIALS, BUILD_MAP

router = APIRouter(prefix="/maps", tags=["maps"], route_class=SessionEndingRoute)

Limit = Annotated[int, Query(ge=1, le=200, description="page size")]
Offset = Annotated[int, Query(ge=0, le=2**31, description="items to skip")]
IfNoneMatch = Annotated[
    str | None,
    Header(
        alias="If-None-Match",
        description="the ETag of the copy you hold: 304 if it is still current",
    ),
]
VersionQuery = Annotated[
    int | None,
    Query(ge=1, le=2**31, description="a version number; the current version when left out"),
]

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
    responses=error_responses(401, 422),
)
def list_maps(
    session: ReadSessionDep,
    limit: Limit = 50,
    offset: Offset = 0,
    tag_id: Annotated[
        int | None, Query(ge=0, le=2**53, description="only maps containing this tag")
    ] = None,
) -> MapsPublic:
    infos, total = maps.list_maps(session, limit=limit, offset=offset, tag_id=tag_id)
    return MapsPublic(
        data=[MapSummary.from_domain(info) for info in infos],
        count=total,
        limit=limit,
        offset=offset,
    )


@router.get(
    "/{map_id}",  # noqa: FAST003 (map_id is read by MapDep)
    summary="Get a map",
    description="The current version (parameters, statistics, metrics with the shift metric, "
    "tag poses) and the newest job. Strong ETag; If-None-Match answers 304.",
    response_model=MapPublic,
    responses={**NOT_MODIFIED, **error_responses(401, 404, 422)},
)
def get_map(
    info: MapDep,
    session: ReadSessionDep,
    response: Response,
    if_none_match: IfNoneMatch = None,
) -> MapPublic | Response:
    jobs, _ = queue.list_jobs(session, map_id=info.id, limit=1)
    latest_job = jobs[0] if jobs else None
    current = info.current
    etag = strong_etag(
        info.id,
        current.number if current else None,
        current.content_sha256 if current else None,
        latest_job.id if latest_job else None,
        latest_job.state if latest_job else None,
    )
    if if_none_match_hits(if_none_match, etag):
        return Response(status_code=304, headers={"ETag": etag})
    tags = maps.tag_poses(session, current.id) if current else []
    response.headers["ETag"] = etag
    return MapPublic.from_domain(info, tags=tags, latest_job=latest_job)


@router.get(
    "/{map_id}/versions",  # noqa: FAST003 (map_id is read by MapDep)
    summary="List a map's versions",
    description="Every version, oldest first: parameters, statistics and metrics of each.",
    responses=error_responses(401, 404, 422),
)
def list_versions(info: MapDep, session: ReadSessionDep) -> VersionsPublic:
    versions = maps.list_versions(session, info.id)
    return VersionsPublic(
        data=[VersionSummary.from_domain(version) for version in versions], count=len(versions)
    )


@router.get(
    "/{map_id}/versions/{number}",  # noqa: FAST003 (map_id is read by MapDep)
    summary="Get a map version",
    description="One version with its tag poses and the detections it left out (and why).",
    responses=error_responses(401, 404, 422),
)
def get_version(info: MapDep, number: int, session: ReadSessionDep) -> VersionDetail:
    version = maps.get_version(session, info.id, valid_id(number, f"version of map {info.id}"))
    return VersionDetail.with_details(version, maps.tag_poses(session, version.id))


@router.post(
    "/{map_id}/rebuild",
    status_code=202,
    summary="Rebuild a map",
    description="Queue a new build of the map's session, optionally with other SLAM "
    "parameters (any SlamParams field; unknown names and out-of-range values are a 422 naming "
    "the parameter). The new version becomes current when the job succeeds; the raw session is "
    "never modified (admin).",
    responses=error_responses(401, 403, 404, 422),
)
def rebuild_map(
    map_id: int,
    _admin: AdminPrincipal,
    session: WriteSessionDep,
    settings: SettingsDep,
    response: Response,
    body: Annotated[RebuildRequest | None, Body()] = None,
) -> RebuildAccepted:
    overrides = checked_overrides(body.params if body else {})
    if body and body.auto_tune_trials:
        overrides[AUTO_TUNE_TRIALS] = body.auto_tune_trials
    info, job_id = enqueue_rebuild(
        session, valid_id(map_id, "map"), overrides, max_attempts=settings.max_attempts
    )
    accepted = RebuildAccepted.queued(info, job_id, overrides)
    response.headers["Location"] = accepted.job_url
    return accepted


def enqueue_rebuild(
    session: Session, map_id: int, overrides: dict[str, Any], *, max_attempts: int
) -> tuple[MapInfo, int]:
    """Queue a build of map ``map_id``'s session with ``overrides`` (already checked, see
    :func:`checked_overrides`); returns the map and the job's id. Raises MapNotFound."""
    info = maps.get_map(session, map_id)
    job_id = queue.enqueue(
        session,
        kind=BUILD_MAP,
        map_id=info.id,
        session_id=info.session_id,
        params=overrides,
        max_attempts=max_attempts,
    )
    return info, job_id


def checked_overrides(overrides: dict[str, Any]) -> dict[str, Any]:
    """The overrides as the worker will read them (values coerced, e.g. "1e-3" → 0.001), or a 422
    naming the first bad parameter."""
    defaults = SlamParams()
    for name, value in overrides.items():
        try:
            defaults.with_overrides({name: value})
        except ParameterError as err:
            raise ApiError(422, "invalid_parameter", str(err), field=f"params.{name}") from err
    try:
        params = defaults.with_overrides(overrides).to_dict()
    except ParameterError as err:
        raise ApiError(422, "invalid_parameter", str(err), field="params") from err
    return {name: params[name] for name in overrides}


@router.get(
    "/{map_id}/app-map",  # noqa: FAST003 (map_id is read by MapDep)
    summary="Download the map in the app's format",
    description="`{tag_vertices, odometry_vertices, waypoints_vertices}` (DESIGN §7) of the "
    "current version, or of `?version=N`; `neighbors` are the path graph's links (junctions are "
    "extra odometry vertices numbered after the last pose). 409 map_not_ready while the map has "
    "no version.",
    response_model=AppMap,
    responses={
        **NOT_MODIFIED,
        **error_responses(401, 404, 409, 422, examples={409: NOT_READY_EXAMPLE}),
    },
)
def get_app_map(
    info: MapDep,
    session: ReadSessionDep,
    version: VersionQuery = None,
    if_none_match: IfNoneMatch = None,
) -> Response:
    chosen = chosen_version(session, info, version)
    etag = strong_etag("app-map", chosen.map_id, chosen.number, chosen.content_sha256)
    if if_none_match_hits(if_none_match, etag):
        return Response(status_code=304, headers={"ETag": etag})
    content = app_map_content(session, chosen)
    return Response(content=content, media_type="application/json", headers={"ETag": etag})


def app_map_content(session: Session, version: VersionInfo) -> bytes:
    """The app's map file (DESIGN §7) of ``version``, as compact JSON bytes."""
    graph_document = path_graph_document(session, version.id)
    app_map = map_to_app_format(
        map_from_json(maps.map_document(session, version.map_id, version.number)),
        path_graph=None if graph_document is None else path_graph_from_json(graph_document),
    )
    return json.dumps(app_map, separators=(",", ":"), allow_nan=False).encode()


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
    session: ReadSessionDep,
    version: VersionQuery = None,
    if_none_match: IfNoneMatch = None,
) -> Response:
    chosen = chosen_version(session, info, version)
    etag = strong_etag("plot", chosen.map_id, chosen.number, chosen.content_sha256)
    if if_none_match_hits(if_none_match, etag):
        return Response(status_code=304, headers={"ETag": etag})
    png = maps.plot_png(session, info.id, chosen.number)
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
def delete_map(map_id: int, _admin: AdminPrincipal, session: WriteSessionDep) -> None:
    delete_map_and_jobs(session, valid_id(map_id, "map"))


def delete_map_and_jobs(session: Session, map_id: int) -> None:
    """Cancel the map's unfinished jobs and delete it with its versions and jobs, in the caller's
    transaction. Raises MapNotFound (and the caller's rollback undoes the cancel)."""
    queue.cancel_unfinished_for_map(session, map_id)
    maps.delete_map(session, map_id)


def chosen_version(session: Session, info: MapInfo, number: int | None) -> VersionInfo:
    """The asked-for version (404 if there is none with that number), or the current one
    (409 while there is none)."""
    if number is not None:
        return maps.get_version(session, info.id, number)
    if info.current is not None:
        return info.current
    jobs, _ = queue.list_jobs(session, map_id=info.id, limit=1)
    building = (
        f": its build job {jobs[0].id} is {jobs[0].state}; follow /v1/jobs/{jobs[0].id}"
        if jobs
        else ": rebuild it to make one"
    )
    raise ApiError(409, "map_not_ready", f"map {info.id} has no version yet{building}")

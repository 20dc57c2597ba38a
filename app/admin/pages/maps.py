"""``/admin/maps``: maps with their quality at a glance; a map's top-down plot per floor (raw and
optimized trajectory, tags with their uncertainty, the path graph, points of interest), its
versions with parameters and metrics, its sessions with what each contributed (add, remove, merge
another map in; maps sharing its tags are offered), a rebuild form, delete, and downloads (the
app's map file and the path graph as GeoJSON).

The plot's data is the version's overview, built once by the worker that stored the version
(``app.domain.formats.derived_documents``) and read from its blob (tens of kB, not the whole map
document); versions stored before have none, and their figure is built from the map document.
Either way it is kept in the process's version cache (versions never change). A map with corridor
edits is drawn with its path graph, nodes and points of interest taken from the edited graph
(:func:`edited_figure`), the one routes use; the route tester draws the same.
"""

from __future__ import annotations

import dataclasses
import gzip
import json
from typing import Annotated, Any

from fastapi import Query, Request, Response
from sqlalchemy.orm import Session

from app.admin.auth import CheckedFormDep, DashboardUserDep
from app.admin.forms import changed_params, rebuild_fields, rebuild_overrides
from app.admin.paging import PAGE_SIZE, Page, PageNumber
from app.admin.routing import admin_router
from app.admin.templating import redirect, render
from app.domain.formats.derived_documents import figure_of_overview, overview_document
from app.domain.formats.map_figure import with_path_graph
from app.domain.formats.map_io import map_from_json
from app.domain.navigation.path_graph import PathGraph
from app.domain.upload.session import Session as ParsedSession
from app.services.corridor_edits import app_map_with_edits_gzip, edits_report
from app.services.errors import ServiceError
from app.services.maps import (
    MapSessionUse,
    add_session_to_map,
    chosen_version,
    delete_map_and_jobs,
    enqueue_rebuild,
    map_session_uses,
    merge_maps,
    picture_of_map,
    remove_session_from_map,
    rename_map,
)
from app.services.navigation import edited_version, geojson_bytes, version_path_graph
from app.services.uploads import stored_session
from app.services.version_cache import VersionCache
from app.storage import maps, queue
from app.storage.maps import MapInfo, VersionInfo
from app.web.deps import MAX_ID, DbDep, ReadDbSessionDep, SettingsDep, valid_id, valid_version

router = admin_router()

#: ``?version=N``: any number is taken; one that can be no version's (:data:`MAX_ID`) names
#: nothing and gets the page of a version the map does not have (:func:`asked_version`), as on
#: ``/v1``: it never reaches the database, where PostgreSQL's 32-bit column refuses it.
VersionNumber = Annotated[
    int | None, Query(description="a version number; the current one if left out")
]


def asked_version(map_id: int, number: int | None) -> int | None:
    """``number`` (None: the current version) if it can be a version's, else the 404 of a
    version map ``map_id`` does not have."""
    return None if number is None else valid_version(map_id, number)


@router.get("/maps")
def map_list(
    request: Request, _user: DashboardUserDep, db_session: ReadDbSessionDep, page: PageNumber = 1
) -> Response:
    infos, total = maps.list_maps(db_session, limit=PAGE_SIZE, offset=(page - 1) * PAGE_SIZE)
    latest_jobs = {}
    for info in infos:
        jobs, _ = queue.list_jobs(db_session, map_id=info.id, limit=1)
        latest_jobs[info.id] = jobs[0] if jobs else None
    return render(
        request,
        "maps.html",
        section="maps",
        title="Maps",
        maps=infos,
        latest_jobs=latest_jobs,
        page=Page.of(number=page, size=PAGE_SIZE, total=total, url="/admin/maps"),
    )


def raw_session(db_session: Session, session_id: int) -> ParsedSession:
    """The parsed raw upload of a session (for its raw trajectory)."""
    return stored_session(db_session, session_id)


def path_graph_or_none(
    request: Request, db_session: Session, version: VersionInfo
) -> PathGraph | None:
    """The version's path graph, or None for a version built before path graphs existed."""
    try:
        return version_path_graph(request.app.state.version_cache, db_session, version)
    except ServiceError:
        return None


def version_figure(
    request: Request, db_session: Session, info: MapInfo, version: VersionInfo
) -> dict[str, Any]:
    """The plot data of a map version: its stored overview's figure, else built from its map
    document (cached per process: versions never change)."""

    def build() -> dict[str, Any]:
        stored = maps.derived_bytes(db_session, version.overview_sha256)
        if stored is not None:
            figure = figure_of_overview(json.loads(gzip.decompress(stored)))
            if figure is not None:
                return figure
        result = map_from_json(maps.map_document(db_session, info.id, version.number))
        contributions = version.statistics.get("sessions") or []
        # several sessions: their raw odometry is each in its own frame, so none is drawn
        overview = overview_document(
            result,
            raw_session(db_session, info.session_id) if len(contributions) < 2 else None,
            path_graph_or_none(request, db_session, version),
            sessions=contributions,
        )
        figure_built: dict[str, Any] = overview["figure"]
        return figure_built

    cache: VersionCache = request.app.state.version_cache
    return cache.get(("admin_figure", version.id), build)


def edited_figure(
    request: Request, db_session: Session, info: MapInfo, version: VersionInfo
) -> dict[str, Any]:
    """:func:`version_figure` with the map's corridor edits applied to its path graph, nodes and
    points of interest (the stored figure is the version's graph as built): what routes use,
    so that a point of interest added in the corridor editor is drawn and listed too."""
    figure = version_figure(request, db_session, info, version)
    if info.corridor_edits_revision == 0:
        return figure
    try:
        edited = edited_version(
            request.app.state.version_cache, db_session, version, info.corridor_edits_revision
        )
    except ServiceError:  # no path graph: no edit applies
        return figure
    return with_path_graph(figure, edited.path_graph)


def session_uses(
    db_session: Session, info: MapInfo, uses: list[MapSessionUse]
) -> list[MapSessionUse]:
    """The map's sessions, with what a one-walk map's session contributed taken from its current
    version (a version of one session has no ``statistics["sessions"]``: its session is the
    whole map)."""
    version = info.current
    if version is None or len(uses) != 1 or uses[0].contribution or not uses[0].in_current_version:
        return uses
    stats = version.statistics
    contribution = {
        "session_id": uses[0].session_id,
        "poses": stats.get("poses"),
        "tags": [tag.tag_id for tag in maps.tag_poses(db_session, version.id)],
        "detections_used": version.detections_used,
        "detections_rejected": version.detections_rejected,
        "tag_chi2_mean": None,
        "shared_tags": [],
        "placed_by_tags": [],
        "own_landmark_tags": [],
        "odometry_variance_scale": 1.0,
    }
    return [dataclasses.replace(uses[0], contribution=contribution)]


def map_page(
    request: Request,
    db_session: Session,
    map_id: int,
    number: int | None,
    *,
    submitted: dict[str, str] | None = None,
    rebuild_error: ServiceError | None = None,
    rename_error: ServiceError | None = None,
    submitted_name: str | None = None,
) -> Response:
    """The map page (with the rebuild or rename form's error and values after a refusal)."""
    info = maps.get_map(db_session, valid_id(map_id, "map"))
    number = asked_version(info.id, number)
    version = chosen_version(db_session, info, number) if info.current or number else None
    jobs, _ = queue.list_jobs(db_session, map_id=info.id, limit=10)
    refusal = rebuild_error or rename_error
    error_field = None
    if rebuild_error is not None and rebuild_error.field:
        error_field = rebuild_error.field.removeprefix("params.")
    return render(
        request,
        "map.html",
        status_code=refusal.status_code if refusal else 200,
        section="maps",
        title=f"Map {info.id}: {info.display_name}",
        info=info,
        version=version,
        versions=maps.list_versions(db_session, info.id),
        jobs=jobs,
        figure=edited_figure(request, db_session, info, version) if version else None,
        has_path_graph=version is not None
        and path_graph_or_none(request, db_session, version) is not None,
        fields=rebuild_fields(info.current.params if info.current else None, submitted),
        rebuild_error=rebuild_error.detail if rebuild_error else None,
        error_field=error_field,
        changed_params=changed_params,
        shown_current=info.current.number if info.current else 0,
        rename_error=rename_error.detail if rename_error else None,
        submitted_name=submitted_name,
        map_sessions=session_uses(db_session, info, map_session_uses(info)),
        sharing=_maps_sharing_tags(db_session, info),
        edits=_edits_on(request, db_session, info, version),
    )


def _edits_on(
    request: Request, db_session: Session, info: MapInfo, version: VersionInfo | None
) -> dict[str, Any] | None:
    """How many of the map's corridor edits apply to ``version``, and why the others do not
    (None: never edited, or no version with a path graph)."""
    if version is None or info.corridor_edits_revision == 0:
        return None
    try:
        report = edits_report(request.app.state.version_cache, db_session, info, version.number)
    except ServiceError:
        return None
    return {
        "count": len(report.edits),
        "applied": report.applied_count,
        "not_applied": [
            (stored.id, stored.edit.op, outcome.reason)
            for stored, outcome in zip(report.edits, report.outcomes, strict=True)
            if not outcome.applied
        ],
    }


def _maps_sharing_tags(db_session: Session, info: MapInfo) -> list[tuple[int, str, list[int]]]:
    """Other maps whose current version has some of this map's current tags (merge candidates)."""
    if info.current is None:
        return []
    tag_ids = [tag.tag_id for tag in maps.tag_poses(db_session, info.current.id)]
    return maps.maps_sharing_tags(db_session, tag_ids, exclude_map_id=info.id)


@router.post("/maps/{map_id}/sessions/add")
def add_session(
    request: Request, form: CheckedFormDep, db: DbDep, settings: SettingsDep, map_id: int
) -> Response:
    map_id = valid_id(map_id, "map")
    try:
        session_id = valid_id(int(str(form.get("session_id") or "0")), "session")
        with db.transaction() as db_session:
            job_id = add_session_to_map(
                db_session, map_id, session_id, max_attempts=settings.max_attempts
            ).job_id
    except (ServiceError, ValueError, LookupError) as err:
        return redirect(request, f"/admin/maps/{map_id}", flash=f"Not added: {err}")
    return redirect(
        request,
        f"/admin/maps/{map_id}",
        flash=f"Session {session_id} added to map {map_id}; rebuild queued as job {job_id}.",
    )


@router.post("/maps/{map_id}/sessions/{session_id}/remove")
def remove_session(
    request: Request,
    _form: CheckedFormDep,
    db: DbDep,
    settings: SettingsDep,
    map_id: int,
    session_id: int,
) -> Response:
    map_id = valid_id(map_id, "map")
    try:
        with db.transaction() as db_session:
            job_id = remove_session_from_map(
                db_session,
                map_id,
                valid_id(session_id, "session"),
                max_attempts=settings.max_attempts,
            ).job_id
    except (ServiceError, LookupError) as err:
        return redirect(request, f"/admin/maps/{map_id}", flash=f"Not removed: {err}")
    return redirect(
        request,
        f"/admin/maps/{map_id}",
        flash=f"Session {session_id} taken out of map {map_id}; rebuild queued as job {job_id}.",
    )


@router.post("/maps/{map_id}/merge")
def merge(
    request: Request, form: CheckedFormDep, db: DbDep, settings: SettingsDep, map_id: int
) -> Response:
    map_id = valid_id(map_id, "map")
    try:
        other = valid_id(int(str(form.get("map_id") or "0")), "map")
        with db.transaction() as db_session:
            job_id = merge_maps(
                db_session, map_id, other, max_attempts=settings.max_attempts
            ).job_id
    except (ServiceError, ValueError, LookupError) as err:
        return redirect(request, f"/admin/maps/{map_id}", flash=f"Not merged: {err}")
    return redirect(
        request,
        f"/admin/maps/{map_id}",
        flash=f"Map {other} merged into map {map_id}; rebuild queued as job {job_id}.",
    )


@router.get("/maps/{map_id}")
def map_detail(
    request: Request,
    _user: DashboardUserDep,
    db_session: ReadDbSessionDep,
    map_id: int,
    version: VersionNumber = None,
) -> Response:
    return map_page(request, db_session, map_id, version)


@router.post("/maps/{map_id}/rebuild")
def rebuild(
    request: Request, form: CheckedFormDep, db: DbDep, settings: SettingsDep, map_id: int
) -> Response:
    map_id = valid_id(map_id, "map")
    try:
        overrides, _ = rebuild_overrides(form)
    except ServiceError as err:
        with db.read() as db_session:
            return map_page(
                request,
                db_session,
                map_id,
                None,
                submitted={k: str(v) for k, v in form.items() if isinstance(v, str)},
                rebuild_error=err,
            )
    with db.transaction() as db_session:
        info, job_id = enqueue_rebuild(
            db_session, map_id, overrides, max_attempts=settings.max_attempts
        )
    changed = ", ".join(f"{name} = {value}" for name, value in overrides.items()) or "defaults"
    return redirect(
        request,
        f"/admin/maps/{info.id}",
        flash=f"Rebuild of map {info.id} queued as job {job_id} ({changed}).",
    )


@router.post("/maps/{map_id}/rename")
def rename(request: Request, form: CheckedFormDep, db: DbDep, map_id: int) -> Response:
    map_id = valid_id(map_id, "map")
    name = form.get("display_name")
    name = name if isinstance(name, str) else ""
    try:
        with db.transaction() as db_session:
            info = rename_map(db_session, map_id, name)
    except ServiceError as err:
        with db.read() as db_session:
            return map_page(
                request, db_session, map_id, None, rename_error=err, submitted_name=name
            )
    return redirect(
        request,
        f"/admin/maps/{info.id}",
        flash=f"Map {info.id} is now named {info.display_name!r}.",
    )


@router.get("/maps/{map_id}/image")
def map_picture(
    _user: DashboardUserDep,
    db_session: ReadDbSessionDep,
    map_id: int,
    v: Annotated[str | None, Query(max_length=64)] = None,
) -> Response:
    picture = picture_of_map(db_session, valid_id(map_id, "map"))
    immutable = v is not None and len(v) >= 8 and picture.sha256.startswith(v)
    return Response(
        content=picture.jpeg,
        media_type="image/jpeg",
        headers={
            "Cache-Control": "private, max-age=31536000, immutable"
            if immutable
            else "private, no-cache"
        },
    )


@router.post("/maps/{map_id}/delete")
def delete(request: Request, _form: CheckedFormDep, db: DbDep, map_id: int) -> Response:
    map_id = valid_id(map_id, "map")
    with db.transaction() as db_session:
        delete_map_and_jobs(db_session, map_id)
    return redirect(request, "/admin/maps", flash=f"Map {map_id} deleted (its session stays).")


@router.get("/maps/{map_id}/app-map")
def download_app_map(
    request: Request,
    _user: DashboardUserDep,
    db_session: ReadDbSessionDep,
    map_id: int,
    version: VersionNumber = None,
) -> Response:
    info = maps.get_map(db_session, valid_id(map_id, "map"))
    chosen = chosen_version(db_session, info, asked_version(info.id, version))
    return Response(
        content=gzip.decompress(
            app_map_with_edits_gzip(
                request.app.state.version_cache, db_session, chosen, info.corridor_edits_revision
            )[0]
        ),
        media_type="application/json",
        headers={
            "Content-Disposition": f'attachment; filename="map-{info.id}-v{chosen.number}.json"'
        },
    )


@router.get("/maps/{map_id}/geojson")
def download_geojson(
    request: Request,
    _user: DashboardUserDep,
    db_session: ReadDbSessionDep,
    map_id: int,
    version: VersionNumber = None,
) -> Response:
    info = maps.get_map(db_session, valid_id(map_id, "map"))
    chosen = chosen_version(db_session, info, asked_version(info.id, version))
    return Response(
        content=geojson_bytes(
            request.app.state.version_cache, db_session, chosen, info.corridor_edits_revision
        ),
        media_type="application/geo+json",
        headers={
            "Content-Disposition": (
                f'attachment; filename="map-{info.id}-v{chosen.number}.geojson"'
            )
        },
    )


@router.get("/live/maps/{map_id}")
def map_live(
    request: Request,
    _user: DashboardUserDep,
    db_session: ReadDbSessionDep,
    map_id: int,
    version: VersionNumber = None,
    current: Annotated[int, Query(ge=0, le=MAX_ID, description="the page's current version")] = 0,
) -> Response:
    """The map page's live part: versions (with a notice when one newer than the page's
    ``current`` is ready) and jobs."""
    info = maps.get_map(db_session, valid_id(map_id, "map"))
    version = asked_version(info.id, version)
    jobs, _ = queue.list_jobs(db_session, map_id=info.id, limit=10)
    return render(
        request,
        "_map_live.html",
        shown_current=current,
        info=info,
        version=chosen_version(db_session, info, version) if info.current or version else None,
        versions=maps.list_versions(db_session, info.id),
        jobs=jobs,
        changed_params=changed_params,
    )

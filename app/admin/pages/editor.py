"""``/admin/editor``: pick a map; ``/admin/maps/{id}/editor``: the corridor editor (issue 27).

The page draws the current version's corridor graph, with the map's corridor edits applied, one
floor at a time (tags, points of interest, the walks faint), and lets an operator quiet a node,
add or remove an edge, move a node and place, rename or remove points of interest, with the mouse
and with the keyboard (``app/admin/static/editor.js``), undo, see every edit with whether it
applies, and plan a route beside it. Its script talks to the JSON endpoints below (the dashboard's
login cookie, and the page's CSRF token in ``X-CSRF-Token`` for changes); they do what the API's
``/v1/maps/{id}/corridor-edits`` does, through the same service.

    GET    /admin/maps/{id}/editor/data            the graph, the edits and their state
    POST   /admin/maps/{id}/editor/edits           add an edit (its JSON), 201
    DELETE /admin/maps/{id}/editor/edits/{edit_id} delete one (undo)
    GET    /admin/maps/{id}/editor/route?from=…&to=…   a route, as the route tester plans it
"""

from __future__ import annotations

import hmac
from typing import Annotated, Any

from fastapi import Body, Depends, Header, Query, Request, Response
from fastapi.responses import JSONResponse
from sqlalchemy.orm import Session

from app.admin.auth import CsrfRefused, DashboardUser, DashboardUserDep
from app.admin.forms import parse_endpoint
from app.admin.pages.maps import version_figure
from app.admin.paging import PAGE_SIZE, Page, PageNumber
from app.admin.routing import admin_router
from app.admin.templating import render
from app.domain.navigation.corridor_edits import ADD_EDGE_KINDS, DOOR, quiet_nodes
from app.domain.navigation.path_graph import PathGraph
from app.services import corridor_edits
from app.services.errors import ServiceError
from app.services.maps import chosen_version
from app.services.navigation import current_path_graph, edited_version, planned_route
from app.storage import maps
from app.storage.maps import MapInfo
from app.web.deps import ReadDbSessionDep, WriteDbSessionDep, valid_id
from app.web.errors import error_response

router = admin_router()


def checked_json_user(
    user: DashboardUserDep,
    csrf: Annotated[str | None, Header(alias="X-CSRF-Token")] = None,
) -> DashboardUser:
    """The logged-in admin of a change made by the editor's script, if it sends the login's CSRF
    token in ``X-CSRF-Token``; CsrfRefused (403) otherwise."""
    if csrf is None or not hmac.compare_digest(csrf, user.csrf_token):
        raise CsrfRefused("the request's security token is missing or wrong")
    return user


CheckedJsonUserDep = Annotated[DashboardUser, Depends(checked_json_user)]


@router.get("/editor")
def editor_maps(
    request: Request, _user: DashboardUserDep, db_session: ReadDbSessionDep, page: PageNumber = 1
) -> Response:
    infos, total = maps.list_maps(db_session, limit=PAGE_SIZE, offset=(page - 1) * PAGE_SIZE)
    return render(
        request,
        "editors.html",
        section="editor",
        title="Corridor editor",
        maps=infos,
        page=Page.of(number=page, size=PAGE_SIZE, total=total, url="/admin/editor"),
    )


@router.get("/maps/{map_id}/editor")
def editor(
    request: Request, _user: DashboardUserDep, db_session: ReadDbSessionDep, map_id: int
) -> Response:
    info = maps.get_map(db_session, valid_id(map_id, "map"))
    version, graph = current_path_graph(
        request.app.state.version_cache, db_session, info
    )  # 409 without a version or a path graph
    return render(
        request,
        "editor.html",
        section="editor",
        title=f"Corridor editor: map {info.id}",
        info=info,
        version=version,
        kinds=ADD_EDGE_KINDS,
        floors=_floors(graph),
    )


@router.get("/maps/{map_id}/editor/data")
def editor_data(
    request: Request, _user: DashboardUserDep, db_session: ReadDbSessionDep, map_id: int
) -> Response:
    try:
        info = maps.get_map(db_session, valid_id(map_id, "map"))
        return JSONResponse(_data(request, db_session, info))
    except ServiceError as err:
        return _error(err)


@router.post("/maps/{map_id}/editor/edits")
def add_edit(
    request: Request,
    user: CheckedJsonUserDep,
    db_session: WriteDbSessionDep,
    map_id: int,
    document: Annotated[Any, Body()] = None,
) -> Response:
    try:
        stored, report = corridor_edits.add_edit(
            request.app.state.version_cache,
            db_session,
            valid_id(map_id, "map"),
            document,
            principal=user.principal,
            max_edits=request.app.state.settings.max_corridor_edits,
        )
    except ServiceError as err:
        db_session.rollback()  # the map's edit revision was raised: nothing is kept
        return _error(err)
    outcome = report.outcomes[-1]
    return JSONResponse(
        {"id": stored.id, "edit": stored.edit.to_json(), "applied": outcome.applied},
        status_code=201,
    )


@router.delete("/maps/{map_id}/editor/edits/{edit_id}")
def delete_edit(
    _user: CheckedJsonUserDep, db_session: WriteDbSessionDep, map_id: int, edit_id: int
) -> Response:
    try:
        stored = corridor_edits.delete_edit(
            db_session, valid_id(map_id, "map"), valid_id(edit_id, "corridor edit")
        )
    except ServiceError as err:
        db_session.rollback()
        return _error(err)
    return JSONResponse({"id": stored.id, "edit": stored.edit.to_json()})


@router.get("/maps/{map_id}/editor/route")
def editor_route(
    request: Request,
    _user: DashboardUserDep,
    db_session: ReadDbSessionDep,
    map_id: int,
    from_: Annotated[str, Query(alias="from", max_length=300)] = "",
    to: Annotated[str, Query(max_length=300)] = "",
) -> Response:
    try:
        info = maps.get_map(db_session, valid_id(map_id, "map"))
        _, graph = current_path_graph(request.app.state.version_cache, db_session, info)
        route = planned_route(
            graph, parse_endpoint(from_, "From"), parse_endpoint(to, "To"), avoid=frozenset()
        )
    except ServiceError as err:
        return _error(err)
    return JSONResponse(
        {
            "length_m": route.length_m,
            "polyline": [list(p) for p in route.polyline_m],
            "steps": [
                {"instruction": s.instruction, "kind": s.kind, "position": list(s.position_m)}
                for s in route.steps
            ],
        }
    )


def _error(err: ServiceError) -> JSONResponse:
    """``err`` as the API answers it (``app.web.errors.error_response``): its long numbers shown
    compactly (an edit at 1e308 is not echoed as 309 digits) and its text cut to a bound."""
    return error_response(err.status_code, err.code, err.detail, field=err.field)


def _floors(pg: PathGraph) -> list[dict[str, Any]]:
    levels = pg.floor_levels_m or (0.0,)
    return [
        {"index": k, "name": f"Floor {k + 1}", "level_m": round(level, 3)}
        for k, level in enumerate(levels)
    ]


def _data(request: Request, db_session: Session, info: MapInfo) -> dict[str, Any]:
    """What the editor draws: the edited graph of the current version, its tags and points of
    interest, the walks of each floor (from the version's figure), and the edits with their
    state."""
    cache = request.app.state.version_cache
    version = chosen_version(db_session, info, None)
    edited = edited_version(cache, db_session, version)  # the edits as of now
    pg = edited.path_graph
    graph = pg.graph
    quiet = quiet_nodes(pg)
    figure = version_figure(request, db_session, info, version)
    walks = {
        int(floor["index"]): floor.get("optimized") or {"x": [], "z": []}
        for floor in figure.get("floors", [])
    }
    return {
        "map_id": info.id,
        "map_name": info.display_name,
        "map_version": version.number,
        "revision": edited.revision,
        "floors": [{**floor, "walk": walks.get(floor["index"])} for floor in _floors(pg)],
        "nodes": [
            {
                "id": int(n),
                "x": d["position_m"][0],
                "y": d["position_m"][1],
                "z": d["position_m"][2],
                "floor": int(d["floor"]),
                "kind": d["kind"],
                "quiet": n in quiet,
            }
            for n, d in graph.nodes(data=True)
        ],
        "edges": [
            {
                "from": int(u),
                "to": int(v),
                "kind": DOOR if d.get("door") else d["kind"],
                "length_m": d["length_m"],
            }
            for u, v, d in graph.edges(data=True)
        ],
        "tags": [
            {
                "id": tag_id,
                "x": a.position_m[0],
                "y": a.position_m[1],
                "z": a.position_m[2],
                "floor": a.floor,
            }
            for tag_id, a in sorted(pg.tags.items())
        ],
        "pois": [
            {
                "name": a.name,
                "x": a.position_m[0],
                "y": a.position_m[1],
                "z": a.position_m[2],
                "floor": a.floor,
            }
            for a in pg.pois
        ],
        "edits": [
            {
                "id": stored.id,
                "edit": stored.edit.to_json(),
                "who": corridor_edits.who(stored),
                "created_at": stored.created_at.strftime("%Y-%m-%d %H:%M:%S UTC"),
                "applied": outcome.applied,
                "reason": outcome.reason,
            }
            for stored, outcome in zip(edited.edits, edited.edited.outcomes, strict=True)
        ],
    }

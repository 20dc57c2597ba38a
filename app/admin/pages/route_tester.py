"""``/admin/routes``: pick a map; ``/admin/maps/{id}/route``: choose where from and where to (from
lists of tags and points of interest, or by clicking the map), plan the route on the map's current
version as the API does, and see it drawn with its turn-by-turn steps.

The form is a GET (planning changes nothing): ``?from=tag:0&to=poi:Kitchen&avoid=stairs``.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Query, Request, Response

from app.admin.auth import DashboardUserDep
from app.admin.forms import parse_endpoint
from app.admin.pages.maps import edited_figure
from app.admin.paging import PAGE_SIZE, Page, PageNumber
from app.admin.routing import admin_router
from app.admin.templating import render
from app.domain.formats.map_figure import with_route
from app.domain.navigation.routing import AVOIDABLE, Route
from app.services.errors import ServiceError
from app.services.navigation import current_path_graph, planned_route
from app.storage import maps
from app.web.deps import ReadDbSessionDep, valid_id

router = admin_router()

EndText = Annotated[str, Query(max_length=300)]


@router.get("/routes")
def route_maps(
    request: Request, _user: DashboardUserDep, db_session: ReadDbSessionDep, page: PageNumber = 1
) -> Response:
    infos, total = maps.list_maps(db_session, limit=PAGE_SIZE, offset=(page - 1) * PAGE_SIZE)
    return render(
        request,
        "routes.html",
        section="routes",
        title="Route tester",
        maps=infos,
        page=Page.of(number=page, size=PAGE_SIZE, total=total, url="/admin/routes"),
    )


@router.get("/maps/{map_id}/route")
def route_tester(
    request: Request,
    _user: DashboardUserDep,
    db_session: ReadDbSessionDep,
    map_id: int,
    from_: Annotated[str, Query(alias="from", max_length=300)] = "",
    to: EndText = "",
    avoid: Annotated[list[str] | None, Query(max_length=2)] = None,
) -> Response:
    info = maps.get_map(db_session, valid_id(map_id, "map"))
    version, graph = current_path_graph(
        request.app.state.version_cache, db_session, info
    )  # 409 without one
    avoided = frozenset(avoid or ()) & AVOIDABLE
    figure = edited_figure(request, db_session, info, version)
    route: Route | None = None
    error: ServiceError | None = None
    if from_ and to:
        try:
            route = planned_route(
                graph,
                parse_endpoint(from_, "From"),
                parse_endpoint(to, "To"),
                avoid=avoided,
            )
            figure = with_route(figure, route)
        except ServiceError as err:
            error = err
    tags = sorted(graph.tags)
    pois = sorted(poi.name for poi in graph.pois)
    return render(
        request,
        "route.html",
        status_code=error.status_code if error else 200,
        section="routes",
        title=f"Route tester: map {info.id}",
        info=info,
        version=version,
        figure=figure,
        tags=tags,
        pois=pois,
        chosen_from=from_,
        chosen_to=to,
        avoid=avoided,
        route=route,
        error=error.detail if error else None,
    )

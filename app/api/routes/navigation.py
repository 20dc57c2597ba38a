"""``/v1/maps/{id}/pois``, ``/routes`` and ``/geojson``: the path graph of a map's current version.

Map versions never change, so each API process keeps the path graphs it has read in a small LRU
(``app.api.version_cache``); a route query then costs a Dijkstra search, not a database read and a
JSON parse. A map with no version yet is a 409 ``map_not_ready``; a
version built before path graphs existed is a 409 ``no_path_graph`` (rebuild the map).
"""

from __future__ import annotations

import gzip
from typing import Annotated

from fastapi import APIRouter, Header, Query, Request, Response

from app.api.deps import MapDep, ReadDbSessionDep
from app.api.errors import error_responses
from app.api.http import IfNoneMatch, accepts_gzip, if_none_match_hits, strong_etag
from app.api.route_class import SessionEndingRoute
from app.api.schemas.navigation import PoiPublic, PoisPublic, RoutePublic, RouteRequest
from app.domain.routing import (
    search_pois,
)
from app.services.maps import chosen_version
from app.services.navigation import current_path_graph, geojson_bytes, planned_route

#: GeoJSON smaller than this is sent as it is (gzip would save too little to pay its time).
GZIP_MIN_BYTES = 4096

router = APIRouter(prefix="/maps", tags=["navigation"], route_class=SessionEndingRoute)


NOT_READY = (
    "map_not_ready",
    "map 12 has no version yet: its build job 31 is running",
)


@router.get(
    "/{map_id}/pois",  # noqa: FAST003 (map_id is read by MapDep)
    summary="Search points of interest",
    description="Points of interest of the map's current version whose name contains `q` "
    "(case-insensitive): exact names first, then names starting with it, then the rest. Without "
    "`q`, all of them.",
    responses=error_responses(401, 404, 409, 422, examples={409: NOT_READY}),
)
def list_pois(
    info: MapDep,
    db_session: ReadDbSessionDep,
    request: Request,
    q: Annotated[str, Query(max_length=200, description="part of a name")] = "",
) -> PoisPublic:
    version, graph = current_path_graph(request.app.state.version_cache, db_session, info)
    found = search_pois(graph, q)
    return PoisPublic(
        data=[PoiPublic.from_domain(anchor) for anchor in found],
        count=len(found),
        map_version=version.number,
    )


@router.post(
    "/{map_id}/routes",  # noqa: FAST003 (map_id is read by MapDep)
    summary="Plan a route",
    description="The shortest walk on the map's current version from `from` to `to` (each one of "
    "a tag, a point of interest, a path-graph node or a position `[x, y, z]` in the map frame), "
    "avoiding stairs and/or elevators if asked: polyline, length, floors and turn-by-turn "
    "steps on the map's corridor skeleton, given at decision points only (turns of 45° or more, "
    "bears at junctions, 'in 5 m' announcements). With `heading_deg` (the phone's walking "
    "direction, e.g. from a localization) the first step says which way to face; `style` "
    "chooses units (m, ft, steps) and clock-face directions. An unknown tag, point of interest "
    "or node is a 404; a goal that cannot be reached "
    "(at all, or without what is avoided) a 409 saying why; an ambiguous name a 422.",
    responses=error_responses(
        401,
        404,
        409,
        422,
        examples={
            409: (
                "unreachable",
                "no route from tag 300 to 'Room 209' without stairs: the goal is on floor 2 and "
                "every way there uses stairs",
            ),
            404: ("not_found", "no point of interest named 'Room 999' in this map"),
        },
    ),
)
def plan(
    info: MapDep,
    body: RouteRequest,
    db_session: ReadDbSessionDep,
    request: Request,
) -> RoutePublic:
    version, graph = current_path_graph(request.app.state.version_cache, db_session, info)
    route = planned_route(
        graph,
        body.from_.to_domain(),
        body.to.to_domain(),
        avoid=frozenset(body.avoid),
        heading_rad=body.heading_rad(),
        style=body.guidance_style(),
    )
    return RoutePublic.from_domain(route, map_id=info.id, map_version=version.number)


@router.get(
    "/{map_id}/geojson",  # noqa: FAST003 (map_id is read by MapDep)
    summary="The path graph as GeoJSON",
    description="A FeatureCollection of the current version's path graph: points with "
    "`properties.kind` node, junction, tag or poi; lines (edges) with `properties.kind` walk, "
    "stairs or elevator, `floor` and `length_m`. Coordinates are metres in the map frame "
    "(see the document's `coordinate_system`), not longitude and latitude. With `If-None-Match` "
    "of the ETag you hold: 304 while the map's current version is the same; gzip-compressed for "
    "clients that accept it.",
    response_class=Response,
    responses={
        200: {
            "description": "the path graph",
            "content": {
                "application/geo+json": {
                    "example": {
                        "type": "FeatureCollection",
                        "features": [
                            {
                                "type": "Feature",
                                "geometry": {"type": "Point", "coordinates": [0.0, 0.0, 0.0]},
                                "properties": {"kind": "node", "id": 0, "floor": 0},
                            }
                        ],
                    }
                }
            },
        },
        304: {"description": "Not modified: the copy with this ETag is current"},
        **error_responses(401, 404, 409, 422, examples={409: NOT_READY}),
    },
)
def geojson(
    info: MapDep,
    db_session: ReadDbSessionDep,
    request: Request,
    if_none_match: IfNoneMatch = None,
    accept_encoding: Annotated[str | None, Header(include_in_schema=False)] = None,
) -> Response:
    version = chosen_version(db_session, info, None)
    headers = {
        "ETag": strong_etag("geojson", info.id, version.number, version.content_sha256),
        "Vary": "Accept-Encoding",
    }
    if if_none_match_hits(if_none_match, headers["ETag"]):
        return Response(status_code=304, headers=headers)
    content = geojson_bytes(request.app.state.version_cache, db_session, version)
    if accepts_gzip(accept_encoding) and len(content) > GZIP_MIN_BYTES:
        content = gzip.compress(content, compresslevel=1, mtime=0)
        headers["Content-Encoding"] = "gzip"
    return Response(content=content, media_type="application/geo+json", headers=headers)

"""``/v1/maps/{id}/pois``, ``/routes`` and ``/geojson``: the path graph of a map's current version.

Map versions never change, so each API process keeps the path graphs it has read in a small LRU
(``app.services.version_cache``) and the GeoJSON as ready bytes; a route query then costs a
Dijkstra search on the event loop, not a database read and a JSON parse (a thread reads the
graph only the first time). A map with no version yet is a 409 ``map_not_ready``; a
version built before path graphs existed is a 409 ``no_path_graph`` (rebuild the map).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Query, Request, Response
from fastapi.concurrency import run_in_threadpool

from app.api.schemas.navigation import PoiPublic, PoisPublic, RoutePublic, RouteRequest
from app.domain.navigation.path_graph import PathGraph
from app.domain.navigation.routing import (
    search_pois,
)
from app.services.maps import current_version
from app.services.navigation import (
    current_path_graph,
    edited_version,
    geojson_content,
    kept_path_graph,
    planned_route,
)
from app.services.version_cache import VersionCache
from app.storage.db import Database
from app.storage.maps import VersionInfo
from app.web.deps import DbDep, MapDep, MapStateDep, ReadDbSessionDep
from app.web.errors import ApiError, ErrorBody, error_responses
from app.web.http import (
    JSON_MEDIA_TYPE,
    AcceptEncoding,
    IfNoneMatch,
    ReadyDocument,
    strong_etag,
    weighted_items,
)
from app.web.route_class import SessionEndingRoute

#: The GeoJSON's key in the VersionCache (with the version's id).
GEOJSON_DOCUMENT = "geojson_document"
GEOJSON_MEDIA_TYPE = "application/geo+json"

router = APIRouter(prefix="/maps", tags=["navigation"], route_class=SessionEndingRoute)


NOT_READY = (
    "map_not_ready",
    "map 12 has no version yet: its build job 31 is running",
)

#: What a route answer can be: JSON (the default) or its text form.
TEXT_MEDIA_TYPE = "text/plain; charset=utf-8"
_ROUTE_MEDIA_TYPES = ("application/json", "text/plain")

#: The ``Accept`` request header of a route: JSON, or ``text/plain`` for its text form.
RouteAccept = Annotated[
    str | None,
    Header(
        alias="Accept",
        description="`application/json` (the default) or `text/plain` for the route's text form "
        "alone; anything else is a 406",
    ),
]


def route_media_type(accept: str | None) -> str:
    """The answer's media type for an ``Accept`` header (RFC 9110 §12.5.1): of
    ``application/json`` and ``text/plain``, the one with the higher q-value (each takes the q of
    the most specific range that matches it; JSON on a tie); none or empty means JSON. Raises a
    406 naming the header when neither is acceptable."""
    if accept is None or not accept.strip():
        return _ROUTE_MEDIA_TYPES[0]
    quality = dict.fromkeys(_ROUTE_MEDIA_TYPES, 0.0)
    specificity = dict.fromkeys(_ROUTE_MEDIA_TYPES, -1)
    for media_range, q in weighted_items(accept):
        kind, _, subtype = media_range.lower().partition("/")
        for media_type in _ROUTE_MEDIA_TYPES:
            want_kind, want_subtype = media_type.split("/")
            if kind == "*" and subtype == "*":
                rank = 0
            elif kind == want_kind and subtype == "*":
                rank = 1
            elif kind == want_kind and subtype == want_subtype:
                rank = 2
            else:
                continue
            if rank > specificity[media_type]:
                specificity[media_type], quality[media_type] = rank, q
    best = max(_ROUTE_MEDIA_TYPES, key=lambda m: quality[m])  # the first (JSON) on a tie
    if quality[best] <= 0.0:
        raise ApiError(
            406,
            "not_acceptable",
            f"a route is application/json or text/plain, not {accept!r}",
            field="Accept",
        )
    return best


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
    "/{map_id}/routes",  # noqa: FAST003 (map_id is read by MapStateDep)
    summary="Plan a route",
    description="The shortest walk on the map's current version from `from` to `to` (each one of "
    "a tag, a point of interest, a path-graph node or a position `[x, y, z]` in the map frame), "
    "avoiding stairs and/or elevators if asked: polyline, length, floors and turn-by-turn "
    "steps on the map's corridor skeleton, given at decision points only (turns of 45° or more, "
    "bears at junctions, 'in 5 m' announcements, 'keep left' at a fork the route goes through "
    "while another way goes on within 45° of straight ahead). With `heading_deg` (the phone's "
    "walking direction, e.g. from a localization) the first step says which way to face; `style` "
    "chooses units (m, ft, steps) and clock-face directions of `instruction`. Every step also "
    "has its structure (`turn`: the turn's class by its angle alone, `clock`, `steps_count` in "
    "steps of `stride_m`, `landmark`, `side`) and a `text` for a screen reader; the answer's "
    "`text` is the whole route as numbered sentences, and `Accept: text/plain` answers with it "
    "alone. An unknown tag, point of interest "
    "or node is a 404; a goal that cannot be reached "
    "(at all, or without what is avoided) a 409 saying why; an ambiguous name or a `stride_m` "
    "outside 0.3–1.5 m a 422; an `Accept` that allows neither JSON nor text a 406.",
    response_model=RoutePublic,
    responses={
        200: {
            "description": "the route (JSON), or its text form (`Accept: text/plain`)",
            "content": {
                "text/plain": {
                    "schema": {"type": "string"},
                    "example": "1. Go straight 12 metres (17 steps).\n"
                    "2. At tag 305, turn left, to 9 o'clock.\n"
                    "3. Go straight 9 metres (13 steps) to Room 209, on your right.\n"
                    "4. Arrive at Room 209, on your right.\n",
                }
            },
        },
        406: {
            "model": ErrorBody,
            "description": "Accept allows neither application/json nor text/plain",
            "content": {
                "application/json": {
                    "example": {
                        "detail": "a route is application/json or text/plain, not 'image/png'",
                        "code": "not_acceptable",
                        "field": "Accept",
                    }
                }
            },
        },
        **error_responses(
            401,
            404,
            409,
            422,
            examples={
                409: (
                    "unreachable",
                    "no route from tag 300 to 'Room 209' without stairs: the goal is on floor 2 "
                    "and every way there uses stairs",
                ),
                404: ("not_found", "no point of interest named 'Room 999' in this map"),
            },
        ),
    },
)
async def plan(
    state: MapStateDep, body: RouteRequest, request: Request, accept: RouteAccept = None
) -> Response:
    media_type = route_media_type(accept)
    version = current_version(state)
    cache: VersionCache = request.app.state.version_cache
    revision = state.info.corridor_edits_revision
    graph = kept_path_graph(cache, version, revision)
    if graph is None:
        db: Database = request.app.state.db
        graph = await run_in_threadpool(_read_path_graph, cache, db, version, revision)
    route = planned_route(
        graph,
        body.from_.to_domain(),
        body.to.to_domain(),
        avoid=frozenset(body.avoid),
        heading_rad=body.heading_rad(),
        style=body.guidance_style(),
    )
    public = RoutePublic.from_domain(
        route, map_id=state.info.id, map_version=version.number, stride_m=body.stride_m
    )
    vary = {"Vary": "Accept"}
    if media_type == "text/plain":
        return Response(content=public.text + "\n", media_type=TEXT_MEDIA_TYPE, headers=vary)
    answer = public.__pydantic_serializer__.to_json(public)
    return Response(content=answer, media_type=JSON_MEDIA_TYPE, headers=vary)


def _read_path_graph(
    cache: VersionCache, db: Database, version: VersionInfo, revision: int
) -> PathGraph:
    with db.read() as db_session:
        return edited_version(cache, db_session, version, revision).path_graph


@router.get(
    "/{map_id}/geojson",  # noqa: FAST003 (map_id is read by MapStateDep)
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
async def geojson(
    state: MapStateDep,
    request: Request,
    db: DbDep,
    if_none_match: IfNoneMatch = None,
    accept_encoding: AcceptEncoding = None,
) -> Response:
    version = current_version(state)
    cache: VersionCache = request.app.state.version_cache
    revision = state.info.corridor_edits_revision
    document: ReadyDocument | None = cache.peek((GEOJSON_DOCUMENT, version.id, revision))
    if document is None:
        document = await run_in_threadpool(_geojson_document, cache, db, version, revision)
    return document.response(if_none_match, accept_encoding)


def _geojson_document(
    cache: VersionCache, db: Database, version: VersionInfo, revision: int
) -> ReadyDocument:
    """The GeoJSON of ``version`` with its map's corridor edits; its ETag names the edits (none:
    the ETag of the version alone)."""
    with db.read() as db_session:
        edited = edited_version(cache, db_session, version, revision)
        return cache.get(
            (GEOJSON_DOCUMENT, version.id, edited.revision),
            lambda: ReadyDocument.of(
                geojson_content(edited.path_graph).encode(),
                media_type=GEOJSON_MEDIA_TYPE,
                etag=strong_etag(
                    "geojson",
                    version.map_id,
                    version.number,
                    version.content_sha256,
                    *((edited.digest,) if edited.digest else ()),
                ),
            ),
        )

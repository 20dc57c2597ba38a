"""Navigation: a version's path graph (cached), routes, GeoJSON.

What the API routers and the dashboard pages both do; errors are :mod:`app.services.errors`.
"""

from __future__ import annotations

import json

from sqlalchemy.orm import Session

from app.domain.navigation.instructions import DEFAULT_STYLE, GuidanceStyle, plan_guided_route
from app.domain.navigation.path_graph import PathGraph, path_graph_from_json, path_graph_to_geojson
from app.domain.navigation.routing import (
    AmbiguousEndpoint,
    Endpoint,
    Route,
    RouteError,
    UnknownEndpoint,
    Unreachable,
)
from app.services.errors import Conflict, InvalidInput, NotFound
from app.services.maps import chosen_version
from app.services.version_cache import VersionCache
from app.storage.maps import MapInfo, VersionInfo
from app.storage.navigation import path_graph_document


def current_path_graph(
    cache: VersionCache, db_session: Session, info: MapInfo
) -> tuple[VersionInfo, PathGraph]:
    """The map's current version and its path graph (409 if either does not exist yet)."""
    version = chosen_version(db_session, info, None)
    return version, version_path_graph(cache, db_session, version)


def version_path_graph(cache: VersionCache, db_session: Session, version: VersionInfo) -> PathGraph:
    """The path graph of ``version`` (cached per process; 409 if the version has none)."""

    def load() -> PathGraph:
        document = path_graph_document(db_session, version.id)
        if document is None:
            raise Conflict(
                "no_path_graph",
                f"version {version.number} of map {version.map_id} has no path graph (it was "
                "built before path graphs existed): rebuild the map",
            )
        return path_graph_from_json(document)

    return cache.get((PATH_GRAPH, version.id), load)


#: A path graph's key in the VersionCache (with the version's id).
PATH_GRAPH = "path_graph"


def kept_path_graph(cache: VersionCache, version: VersionInfo) -> PathGraph | None:
    """The path graph of ``version`` if this process has it already (no database), else None."""
    graph: PathGraph | None = cache.peek((PATH_GRAPH, version.id))
    return graph


def planned_route(
    graph: PathGraph,
    start: Endpoint,
    goal: Endpoint,
    *,
    avoid: frozenset[str],
    heading_rad: float | None = None,
    style: GuidanceStyle = DEFAULT_STYLE,
) -> Route:
    """:func:`app.domain.navigation.instructions.plan_guided_route` (instructions at decision
    points, the first facing ``heading_rad`` when given), its refusals as API errors: an unknown end
    404, an unreachable goal 409, an ambiguous name or another bad request 422."""
    try:
        return plan_guided_route(
            graph, start, goal, avoid=avoid, heading_rad=heading_rad, style=style
        )
    except UnknownEndpoint as err:
        raise NotFound("not_found", str(err), field=None) from err
    except Unreachable as err:
        raise Conflict("unreachable", str(err)) from err
    except AmbiguousEndpoint as err:
        raise InvalidInput("ambiguous_endpoint", str(err)) from err
    except RouteError as err:
        raise InvalidInput("invalid_route", str(err)) from err


def geojson_content(graph: PathGraph) -> str:
    """The path graph as a GeoJSON FeatureCollection, compact JSON."""
    return json.dumps(path_graph_to_geojson(graph), separators=(",", ":"), allow_nan=False)


def geojson_bytes(cache: VersionCache, db_session: Session, version: VersionInfo) -> bytes:
    """:func:`geojson_content` of ``version``'s path graph as UTF-8, made once per API process
    (a version never changes)."""
    return cache.get(
        ("geojson", version.id),
        lambda: geojson_content(version_path_graph(cache, db_session, version)).encode(),
    )

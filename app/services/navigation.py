"""Navigation: a version's path graph (cached), with its map's corridor edits applied, routes,
GeoJSON.

What the API routers and the dashboard pages both do; errors are :mod:`app.services.errors`.

A map's corridor edits (issue 27, :mod:`app.domain.navigation.corridor_edits`) apply to every
version of it: what routes, points of interest, GeoJSON and the app-map serve is the stored
graph with the edits applied (:func:`edited_version`), kept per process by version and the
map's ``corridor_edits_revision``, which every edit raises. So an edit is served at the next
request in this process (its commit drops the map's kept state, ``MAP_CHANGES``), and within
``INVISIBLE_MAP_MAP_CACHE_S`` in the others, like a new version.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass

from sqlalchemy.orm import Session

from app.domain.navigation.corridor_edits import EditedGraph, apply_edits
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
from app.storage.corridor_edits import StoredEdit, list_edits
from app.storage.maps import MapInfo, VersionInfo
from app.storage.navigation import path_graph_document


def current_path_graph(
    cache: VersionCache, db_session: Session, info: MapInfo
) -> tuple[VersionInfo, PathGraph]:
    """The map's current version and its path graph with the map's corridor edits (409 if
    either does not exist yet)."""
    version = chosen_version(db_session, info, None)
    edited = edited_version(cache, db_session, version, info.corridor_edits_revision)
    return version, edited.path_graph


def version_path_graph(cache: VersionCache, db_session: Session, version: VersionInfo) -> PathGraph:
    """The path graph of ``version`` as stored, without corridor edits (cached per process; 409
    if the version has none)."""

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


@dataclass(frozen=True, slots=True, kw_only=True)
class EditedVersion:
    """A version's path graph with its map's corridor edits as of ``revision`` applied:
    ``edits`` (oldest first), what became of each (``edited.outcomes``), and ``digest``, the
    SHA-256 of the edits (empty without edits), which the ETags of documents made from the
    edited graph name."""

    version_id: int
    revision: int
    edits: tuple[StoredEdit, ...]
    edited: EditedGraph
    digest: str

    @property
    def path_graph(self) -> PathGraph:
        return self.edited.path_graph


#: An edited path graph's key in the VersionCache (with the version's id and the revision).
EDITED_PATH_GRAPH = "edited_path_graph"


def edited_version(
    cache: VersionCache, db_session: Session, version: VersionInfo, revision: int | None = None
) -> EditedVersion:
    """``version``'s path graph with its map's corridor edits applied, as of ``revision`` (the
    map's ``corridor_edits_revision`` read with the map; None: read it now). Kept per process by
    version and revision; revision 0 (never edited) reads no edits. 409 ``no_path_graph``."""
    if revision is not None:
        kept: EditedVersion | None = cache.peek((EDITED_PATH_GRAPH, version.id, revision))
        if kept is not None:
            return kept
    edits: list[StoredEdit] = []
    if revision != 0:
        revision, edits = list_edits(db_session, version.map_id)  # the revision read with them
        again: EditedVersion | None = cache.peek((EDITED_PATH_GRAPH, version.id, revision))
        if again is not None:
            return again
    value = edited_of(cache, db_session, version, revision or 0, edits)
    cache.put((EDITED_PATH_GRAPH, version.id, value.revision), value)
    return value


def edited_of(
    cache: VersionCache,
    db_session: Session,
    version: VersionInfo,
    revision: int,
    edits: Sequence[StoredEdit],
) -> EditedVersion:
    """``version``'s path graph with ``edits`` applied, not kept: :func:`edited_version` keeps
    what is committed; a transaction that changes the edits uses this one."""
    base = version_path_graph(cache, db_session, version)
    digest = (
        hashlib.sha256(
            json.dumps([stored.edit.to_json() for stored in edits], sort_keys=True).encode()
        ).hexdigest()
        if edits
        else ""
    )
    return EditedVersion(
        version_id=version.id,
        revision=revision,
        edits=tuple(edits),
        edited=apply_edits(base, [stored.edit for stored in edits]),
        digest=digest,
    )


def kept_path_graph(cache: VersionCache, version: VersionInfo, revision: int) -> PathGraph | None:
    """The path graph of ``version`` with its map's corridor edits as of ``revision`` if this
    process has it already (no database), else None."""
    kept: EditedVersion | None = cache.peek((EDITED_PATH_GRAPH, version.id, revision))
    return None if kept is None else kept.path_graph


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


def geojson_bytes(
    cache: VersionCache, db_session: Session, version: VersionInfo, revision: int
) -> bytes:
    """:func:`geojson_content` of ``version``'s path graph with its map's corridor edits as of
    ``revision``, as UTF-8, made once per API process and revision."""
    edited = edited_version(cache, db_session, version, revision)
    return cache.get(
        ("geojson", version.id, edited.revision),
        lambda: geojson_content(edited.path_graph).encode(),
    )

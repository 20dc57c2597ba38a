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
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy.orm import Session

from app.domain.navigation.corridor_edits import (
    CorridorEdit,
    EditedGraph,
    apply_edits,
    apply_more_edits,
)
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
    edited graph name. :meth:`extended` adds edits made since at their own cost."""

    version_id: int
    revision: int
    edits: tuple[StoredEdit, ...]
    edited: EditedGraph
    digest: str
    #: The SHA-256 of the edits' JSON list so far, without its closing "]" (to extend it).
    hashed: Any = field(default=None, repr=False, compare=False)

    @property
    def path_graph(self) -> PathGraph:
        return self.edited.path_graph

    def extended(
        self, revision: int, more: Sequence[StoredEdit], edited: EditedGraph | None = None
    ) -> EditedVersion:
        """This with the edits ``more`` (made after its own) applied, as of ``revision``;
        ``edited``: what :func:`apply_more_edits` makes of them, when the caller has it."""
        if edited is None:
            edited = apply_more_edits(self.edited, [stored.edit for stored in more])
        edits = (*self.edits, *more)
        hashed = _hashed(self.hashed, self.edits, more)
        return EditedVersion(
            version_id=self.version_id,
            revision=revision,
            edits=edits,
            edited=edited,
            digest=_digest(hashed, edits),
            hashed=hashed,
        )


#: An edited path graph's key in the VersionCache (with the version's id and the revision).
EDITED_PATH_GRAPH = "edited_path_graph"
#: The newest edited path graph this process made of a version (with the version's id): the
#: edits added since are applied to it alone.
NEWEST_EDITED_PATH_GRAPH = "newest_edited_path_graph"


def _hashed(hashed: Any, before: Sequence[StoredEdit], more: Sequence[StoredEdit]) -> Any:
    """``hashed`` (the SHA-256 of ``before``'s JSON list, open) continued with ``more``."""
    if hashed is None or not before:
        hasher, items, first = hashlib.sha256(b"["), [*before, *more], True
    else:
        hasher, items, first = hashed.copy(), list(more), False
    for stored in items:
        if not first:
            hasher.update(b", ")
        first = False
        hasher.update(json.dumps(stored.edit.to_json(), sort_keys=True).encode())
    return hasher


def _digest(hashed: Any, edits: Sequence[StoredEdit]) -> str:
    """The SHA-256 of ``json.dumps([edit, …], sort_keys=True)`` ("" without edits)."""
    if not edits:
        return ""
    hasher = hashed.copy()
    hasher.update(b"]")
    return str(hasher.hexdigest())


def keep_edited(cache: VersionCache, value: EditedVersion) -> None:
    """Keep ``value`` (committed edits) for its version and revision, and as the version's
    newest."""
    cache.put((EDITED_PATH_GRAPH, value.version_id, value.revision), value)
    newest: EditedVersion | None = cache.peek((NEWEST_EDITED_PATH_GRAPH, value.version_id))
    if newest is None or newest.revision <= value.revision:
        cache.put((NEWEST_EDITED_PATH_GRAPH, value.version_id), value)


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
    keep_edited(cache, value)
    return value


def edited_of(
    cache: VersionCache,
    db_session: Session,
    version: VersionInfo,
    revision: int,
    edits: Sequence[StoredEdit],
) -> EditedVersion:
    """``version``'s path graph with ``edits`` applied, not kept: :func:`edited_version` keeps
    what is committed; a transaction that changes the edits uses this one. When this process
    has made the graph of the first of ``edits`` already (the newest it made of the version,
    and only edits added since), only the others are applied."""
    newest: EditedVersion | None = cache.peek((NEWEST_EDITED_PATH_GRAPH, version.id))
    if (
        newest is not None
        and len(newest.edits) <= len(edits)
        and all(a.id == b.id for a, b in zip(newest.edits, edits, strict=False))
    ):
        return newest.extended(revision, edits[len(newest.edits) :])
    base = version_path_graph(cache, db_session, version)
    unedited = EditedVersion(
        version_id=version.id,
        revision=0,
        edits=(),
        edited=EditedGraph(path_graph=base, outcomes=()),
        digest="",
    )
    return unedited.extended(revision, edits, apply_edits(base, _edits_of(edits)))


def _edits_of(edits: Sequence[StoredEdit]) -> list[CorridorEdit]:
    return [stored.edit for stored in edits]


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

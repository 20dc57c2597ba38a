"""``/v1/maps/{id}/corridor-edits``: an operator's corrections of a map's corridor graph (issue
27; admin keys). Devices see their effect only through routes, points of interest, GeoJSON and
the app-map, which serve the current version's graph with the edits applied from the next
request on (no rebuild).

``GET`` lists the edits with what became of each on the current version (``?version=N``: on
that one) and an ETag of the edits' revision, a page at a time (``?limit=``, ``?cursor=`` from
``next_cursor``); ``POST`` adds one (201, ``Location``; a map holds at most
``INVISIBLE_MAP_MAX_CORRIDOR_EDITS``), ``DELETE`` removes one (undo). ``POST`` and ``DELETE``
take ``If-Match`` with that ETag: 412 ``edits_changed`` when another operator changed the edits
meanwhile, 400 ``invalid_if_match`` when the header is no ETag of the edits.
"""

from __future__ import annotations

import re
from typing import Annotated, Any

from fastapi import APIRouter, Body, Header, Query, Request, Response

from app.api.schemas.corridor_edits import (
    EDIT_EXAMPLES,
    CorridorEditCreated,
    CorridorEditPublic,
    CorridorEditsPublic,
    cursor_after_id,
    edits_cursor,
)
from app.services import corridor_edits
from app.services.errors import BadRequest, InvalidInput, NotFound
from app.storage import maps
from app.web.deps import (
    AdminPrincipal,
    EditId,
    MapId,
    ReadDbSessionDep,
    VersionQuery,
    WriteDbSessionDep,
    valid_id,
    valid_version,
)
from app.web.errors import error_responses
from app.web.route_class import SessionEndingRoute

router = APIRouter(prefix="/maps", tags=["corridor edits"], route_class=SessionEndingRoute)

IfMatch = Annotated[
    str | None,
    Header(
        alias="If-Match",
        description='the ETag of the edits you read ("edits-4"): 412 edits_changed if they '
        "changed since; 400 invalid_if_match if it is no ETag of the edits",
    ),
]

#: Edits per page of the list, by default and at most.
DEFAULT_LIMIT = 100
MAX_LIMIT = 1_000
#: The longest cursor accepted, characters (one of ours is at most 35).
MAX_CURSOR_LENGTH = 64

Limit = Annotated[
    int,
    Query(
        ge=1,
        le=MAX_LIMIT,
        description=f"edits per page, 1 to {MAX_LIMIT} (a number outside: 422 naming limit)",
        openapi_examples={"a page of 100": {"value": DEFAULT_LIMIT}},
    ),
]
Cursor = Annotated[
    str | None,
    Query(
        max_length=MAX_CURSOR_LENGTH,
        description="the next_cursor of the page before; left out: the first page. Opaque: a "
        "cursor this API did not give is a 422 invalid_cursor naming cursor",
        openapi_examples={
            "the first page": {"value": None},
            "the page after edit 100": {"value": edits_cursor(100)},
        },
    ),
]

NO_PATH_GRAPH = (
    "no_path_graph",
    "version 1 of map 5 has no path graph (it was built before path graphs existed): rebuild "
    "the map",
)


def _etag(revision: int) -> str:
    return f'"edits-{revision}"'


#: An ``If-Match`` the edits' ETag can be: ``"edits-N"`` (or weak, or unquoted), N in ASCII
#: digits. At most 18 of them: a revision is a 32-bit counter, and ``int()`` must never meet
#: thousands of digits (past 4,300 it raises) nor digits of other scripts (it reads "١٢" as 12).
_ETAG = re.compile(r'(?:W/)?"?edits-([0-9]{1,18})"?', re.ASCII)
#: How much of a refused header its error echoes, characters.
_ECHOED = 40
#: The documented example of a refused If-Match.
IF_MATCH_REFUSED = (
    "invalid_if_match",
    "If-Match must be the ETag of the edits (\"edits-4\"), got '12'",
)


def _expected(if_match: str | None) -> int | None:
    """The revision an ``If-Match`` names; None without one (or ``*``). A header that is no ETag
    of the edits is a 400 ``invalid_if_match`` naming the header, never a 500."""
    if if_match is None or if_match.strip() == "*":
        return None
    match = _ETAG.fullmatch(if_match.strip())
    if match is None:
        shown = if_match if len(if_match) <= _ECHOED else if_match[:_ECHOED] + "…"
        raise BadRequest(
            "invalid_if_match",
            f'If-Match must be the ETag of the edits ("edits-4"), got {shown!r}',
            field="If-Match",
        )
    return int(match.group(1))


@router.get(
    "/{map_id}/corridor-edits",
    summary="List a map's corridor edits",
    description="The map's corridor edits, oldest first (the order they apply in), each with who "
    "made it and when, and whether it applies to the current version (or `?version=N`): an edit "
    "whose place the version no longer has is kept and reported as not applied, with the reason. "
    f"A page at a time: `limit` edits (default {DEFAULT_LIMIT}, at most {MAX_LIMIT}), then "
    "`?cursor=` the answer's `next_cursor` for the next page, until `next_cursor` is null; "
    "`count` and `applied_count` are of all the map's edits. A page goes on after the last edit "
    "of the page before, also when edits are added or deleted meanwhile (the ETag tells). "
    "The ETag is the edits' revision, for `If-Match` on POST and DELETE. Admin keys only.",
    responses=error_responses(
        401,
        403,
        404,
        409,
        422,
        examples={
            409: NO_PATH_GRAPH,
            422: ("invalid_cursor", "cursor: 'abc' is no cursor of this list: use next_cursor"),
        },
    ),
)
def list_corridor_edits(
    map_id: MapId,
    request: Request,
    response: Response,
    _admin: AdminPrincipal,
    db_session: ReadDbSessionDep,
    version: VersionQuery = None,
    limit: Limit = DEFAULT_LIMIT,
    cursor: Cursor = None,
) -> CorridorEditsPublic:
    after_id = None if cursor is None else cursor_after_id(cursor)
    if cursor is not None and after_id is None:
        shown = cursor if len(cursor) <= _ECHOED else cursor[:_ECHOED] + "…"
        raise InvalidInput(
            "invalid_cursor",
            f"cursor: {shown!r} is no cursor of this list: use next_cursor",
            field="cursor",
        )
    info = maps.get_map(db_session, valid_id(map_id, "map"))
    if version is not None:
        valid_version(info.id, version)
    report = corridor_edits.edits_report(request.app.state.version_cache, db_session, info, version)
    response.headers["ETag"] = _etag(report.revision)
    response.headers["Cache-Control"] = "no-store"
    return CorridorEditsPublic.from_domain(report, after_id=after_id, limit=limit)


@router.post(
    "/{map_id}/corridor-edits",
    status_code=201,
    summary="Add a corridor edit",
    description="An edit of the map's corridor graph, in the map's frame (points `[x, y, z]`, m, "
    "y up): `quiet` (at), `add_edge` (from, to, kind walk|door|stairs|elevator), `remove_edge` "
    "(from, to), `move_node` (from, to), `add_poi` (name, at), `rename_poi` (name, new_name, "
    "optional at), `remove_poi` (name, optional at). It must apply to the current version: a "
    "malformed edit, an unknown op, a point far outside the map or on no floor, a self-loop, a "
    "place with no node near it is a 422 naming the field; a duplicate edge, a removal that "
    "would cut a tag or point of interest off from the rest of the map, a name taken a 409; a "
    "map that holds INVISIBLE_MAP_MAX_CORRIDOR_EDITS edits already (5,000 by default) the 409 "
    "too_many_corridor_edits; a map without a path graph the 409 no_path_graph. Kept per map "
    "and applied to every version (rebuilds, new walks), found again by position. Routes and "
    "downloads use it from the next request on. Admin keys only.",
    responses=error_responses(
        400,
        401,
        403,
        404,
        409,
        412,
        422,
        examples={
            400: IF_MATCH_REFUSED,
            409: (
                "edit_conflict",
                "to: removing the edge 12–13 would cut tag 305 off from the rest of the map (the "
                "app cannot route to a place it cannot reach)",
            ),
            422: ("invalid_edit", "op: unknown op 'straighten': one of quiet, add_edge, …"),
        },
    ),
)
def add_corridor_edit(
    map_id: MapId,
    request: Request,
    response: Response,
    admin: AdminPrincipal,
    db_session: WriteDbSessionDep,
    edit: Annotated[dict[str, Any], Body(openapi_examples=EDIT_EXAMPLES)],
    if_match: IfMatch = None,
) -> CorridorEditCreated:
    stored, report = corridor_edits.add_edit(
        request.app.state.version_cache,
        db_session,
        valid_id(map_id, "map"),
        edit,
        principal=admin,
        expected_revision=_expected(if_match),
        max_edits=request.app.state.settings.max_corridor_edits,
    )
    response.headers["Location"] = f"/v1/maps/{map_id}/corridor-edits/{stored.id}"
    response.headers["ETag"] = _etag(report.revision)
    public = CorridorEditPublic.from_domain(stored, report.outcomes[-1])
    return CorridorEditCreated(
        **public.model_dump(), map_version=report.version.number, revision=report.revision
    )


@router.get(
    "/{map_id}/corridor-edits/{edit_id}",
    summary="Get a corridor edit",
    description="One edit, and whether it applies to the current version. Admin keys only.",
    responses=error_responses(401, 403, 404, 409, 422, examples={409: NO_PATH_GRAPH}),
)
def get_corridor_edit(
    map_id: MapId,
    edit_id: EditId,
    request: Request,
    _admin: AdminPrincipal,
    db_session: ReadDbSessionDep,
) -> CorridorEditPublic:
    info = maps.get_map(db_session, valid_id(map_id, "map"))
    report = corridor_edits.edits_report(request.app.state.version_cache, db_session, info)
    for stored, outcome in zip(report.edits, report.outcomes, strict=True):
        if stored.id == edit_id:
            return CorridorEditPublic.from_domain(stored, outcome)
    raise NotFound("not_found", f"map {info.id} has no corridor edit {edit_id}")


@router.delete(
    "/{map_id}/corridor-edits/{edit_id}",
    status_code=204,
    summary="Delete a corridor edit",
    description="Remove an edit (undo). The edits after it stay and apply without it from the "
    "next request on; one that needed it is then reported as not applied. Admin keys only.",
    responses=error_responses(400, 401, 403, 404, 409, 412, 422, examples={400: IF_MATCH_REFUSED}),
)
def delete_corridor_edit(
    map_id: MapId,
    edit_id: EditId,
    _admin: AdminPrincipal,
    db_session: WriteDbSessionDep,
    if_match: IfMatch = None,
) -> Response:
    corridor_edits.delete_edit(
        db_session,
        valid_id(map_id, "map"),
        valid_id(edit_id, "corridor edit"),
        expected_revision=_expected(if_match),
    )
    return Response(status_code=204)

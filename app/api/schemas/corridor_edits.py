"""Pydantic models of ``/v1/maps/{id}/corridor-edits`` (issue 27).

An edit is posted as the domain's JSON (``app.domain.navigation.corridor_edits``), which the
domain checks, so that the refusals name the edit's own fields; :data:`EDIT_EXAMPLES` documents
each operation.
"""

from __future__ import annotations

import base64
import re
from bisect import bisect_right
from datetime import datetime
from typing import Any

from pydantic import BaseModel, Field

from app.api.schemas.common import AT_EXAMPLE, examples
from app.domain.navigation.corridor_edits import EditOutcome
from app.services.corridor_edits import EditsReport, who
from app.storage.corridor_edits import StoredEdit

#: One example body per operation (points [x, y, z] in the map frame, m, y up).
EDIT_EXAMPLES: dict[str, dict[str, Any]] = {
    "quiet": {
        "summary": "quiet: no decision is announced at the node at 'at' (a lobby, a gentle bend)",
        "value": {"op": "quiet", "at": [12.4, 0.9, -3.1]},
    },
    "add_edge": {
        "summary": "add_edge: a corridor the walks did not close; kind walk, door, stairs or "
        "elevator",
        "value": {
            "op": "add_edge",
            "from": [12.4, 0.9, -3.1],
            "to": [12.4, 0.9, 9.0],
            "kind": "door",
        },
    },
    "remove_edge": {
        "summary": "remove_edge: a false link or a corridor to avoid",
        "value": {"op": "remove_edge", "from": [12.4, 0.9, -3.1], "to": [20.0, 0.9, -3.1]},
    },
    "move_node": {
        "summary": "move_node: straighten a centreline, put a junction where corridors meet",
        "value": {"op": "move_node", "from": [12.4, 0.9, -3.1], "to": [12.0, 0.9, -3.0]},
    },
    "add_poi": {
        "summary": "add_poi: a point of interest placed by clicking",
        "value": {"op": "add_poi", "name": "Room 212", "at": [15.0, 0.9, -4.5]},
    },
    "rename_poi": {
        "summary": "rename_poi ('at' optional: which of several of one name)",
        "value": {"op": "rename_poi", "name": "Room 21", "new_name": "Room 212"},
    },
    "remove_poi": {
        "summary": "remove_poi ('at' optional)",
        "value": {"op": "remove_poi", "name": "Room 212", "at": [15.0, 0.9, -4.5]},
    },
}

EDIT_EXAMPLE = {
    "id": 7,
    "edit": {"op": "quiet", "at": [12.4, 0.9, -3.1]},
    "created_by": "key:3",
    "created_by_name": "lab laptop",
    "who": "lab laptop (key:3)",
    "created_at": AT_EXAMPLE,
    "applied": True,
    "reason": None,
    "field": None,
}


class CorridorEditPublic(BaseModel):
    """An edit, who made it and when, and whether it applies to the version the answer names
    (``applied``; else ``reason`` and the ``field`` whose place was not found)."""

    model_config = examples(EDIT_EXAMPLE)

    id: int
    edit: dict[str, Any] = Field(description="the edit as posted: op and its fields")
    created_by: str = Field(description="key:<id> of the admin key, or env-admin")
    created_by_name: str | None = Field(description="that key's name")
    who: str = Field(description="who, for people")
    created_at: datetime
    applied: bool = Field(description="whether it applies to the version of the answer")
    reason: str | None = Field(description="why not, when it does not")
    field: str | None = Field(description="the edit's field whose place was not found")

    @classmethod
    def from_domain(cls, stored: StoredEdit, outcome: EditOutcome) -> CorridorEditPublic:
        return cls(
            id=stored.id,
            edit=stored.edit.to_json(),
            created_by=stored.created_by,
            created_by_name=stored.created_by_name,
            who=who(stored),
            created_at=stored.created_at,
            applied=outcome.applied,
            reason=outcome.reason,
            field=outcome.field,
        )


class CorridorEditsPublic(BaseModel):
    """A page of a map's corridor edits, oldest first (the order they apply in), each with what
    became of it on version ``map_version``; ``count`` and ``applied_count`` are of all the
    map's edits; ``next_cursor`` asks for the next page (null on the last); ``revision`` grows
    with every edit added or deleted."""

    model_config = examples(
        {
            "data": [EDIT_EXAMPLE],
            "count": 1,
            "applied_count": 1,
            "map_id": 5,
            "map_version": 3,
            "revision": 4,
            "next_cursor": None,
        }
    )

    data: list[CorridorEditPublic]
    count: int = Field(description="the map's edits, on every page")
    applied_count: int = Field(description="of those, the edits that apply to map_version")
    map_id: int
    map_version: int
    revision: int
    next_cursor: str | None = Field(description="?cursor= of the next page; null on the last page")

    @classmethod
    def from_domain(
        cls, report: EditsReport, *, after_id: int | None = None, limit: int | None = None
    ) -> CorridorEditsPublic:
        """The edits of ``report`` after the edit ``after_id`` (from the first when None), at
        most ``limit`` (all when None)."""
        start = 0 if after_id is None else bisect_right(report.edits, after_id, key=_edit_id)
        end = len(report.edits) if limit is None else min(len(report.edits), start + limit)
        return cls(
            data=[
                CorridorEditPublic.from_domain(report.edits[k], report.outcomes[k])
                for k in range(start, end)
            ],
            count=len(report.edits),
            applied_count=report.applied_count,
            map_id=report.map_id,
            map_version=report.version.number,
            revision=report.revision,
            next_cursor=edits_cursor(report.edits[end - 1].id) if end < len(report.edits) else None,
        )


def _edit_id(stored: StoredEdit) -> int:
    return stored.id


#: What a cursor of the edits' list says, before its base64: the id of the last edit seen.
_CURSOR = re.compile(r"after:([0-9]{1,20})", re.ASCII)


def edits_cursor(after_id: int) -> str:
    """The opaque cursor of the page after the edit ``after_id`` (URL-safe base64)."""
    return base64.urlsafe_b64encode(f"after:{after_id}".encode()).decode().rstrip("=")


def cursor_after_id(cursor: str) -> int | None:
    """The edit id a cursor of :func:`edits_cursor` names, None if it is not one."""
    try:
        padded = cursor + "=" * (-len(cursor) % 4)
        text = base64.b64decode(padded, altchars=b"-_", validate=True).decode("ascii")
    except ValueError:  # not base64 (binascii.Error), not ASCII (UnicodeDecodeError)
        return None
    match = _CURSOR.fullmatch(text)
    if match is None or edits_cursor(int(match.group(1))) != cursor:  # one spelling per page
        return None
    return int(match.group(1))


class CorridorEditCreated(CorridorEditPublic):
    """The edit stored, as it applies to the map's current version, and the edits' new
    revision."""

    model_config = examples({**EDIT_EXAMPLE, "map_version": 3, "revision": 5})

    map_version: int
    revision: int

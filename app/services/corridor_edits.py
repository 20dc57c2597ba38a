"""Corridor edits of a map (issue 27): list them with what became of each on a version, add one,
delete one; the app-map with the edits.

What the API routers and the dashboard's editor both do; errors are :mod:`app.services.errors`:

    report = edits_report(cache, db_session, info)               # on the current version
    stored, report = add_edit(cache, db_session, map_id, document, principal=…)
    stored = delete_edit(db_session, map_id, edit_id, principal=…)

A new edit must apply to the map's current version as it is, with the edits before it (the
domain's ``apply_new_edit``): a malformed edit, or a place not in the map, is a 422 naming the
field; a duplicate edge, a removal that would cut a tag or point of interest off, a name taken,
a 409; a map without a path graph the 409 ``no_path_graph``. Nothing is stored then. The map's
row is locked and its edit revision raised before the edits are read (``app.storage.
corridor_edits``), so two operators' edits are checked one after the other and neither is lost.
An ``expected_revision`` (the ``If-Match`` of the API) refuses, 412 ``edits_changed``, when the
edits changed since the caller read them. A map holds at most ``max_edits`` edits
(``INVISIBLE_MAP_MAX_CORRIDOR_EDITS``): one more is the 409 ``too_many_corridor_edits``, counted
under the map's lock, so operators adding at once never pass it.

A new edit is applied to the edited graph of the edits before it, which this process keeps
(``app.services.navigation``), not to all of them again: what it costs does not grow with how
many came before. The graph with it is kept when the transaction commits (never before: a
revision rolled back is used again), so the next route in this process is served from it.
"""

from __future__ import annotations

import gzip
from dataclasses import dataclass
from typing import Any

from sqlalchemy import event
from sqlalchemy.orm import Session

from app.domain.formats.derived_documents import DERIVED_GZIP_LEVEL, app_map_of
from app.domain.formats.map_io import map_from_json
from app.domain.navigation.corridor_edits import (
    EditConflict,
    EditInvalid,
    EditOutcome,
    apply_new_edit_to,
    edit_from_json,
    with_edited_pois,
)
from app.services.errors import Conflict, InvalidInput, NotFound, PreconditionFailed
from app.services.maps import app_map_gzip, chosen_version
from app.services.navigation import (
    EDITED_PATH_GRAPH,
    EditedVersion,
    edited_of,
    edited_version,
    keep_edited,
)
from app.services.version_cache import VersionCache
from app.storage import corridor_edits, keys, maps
from app.storage.corridor_edits import StoredEdit
from app.storage.keys import ENVIRONMENT_ADMIN, Principal
from app.storage.maps import MapInfo, VersionInfo

#: The most corridor edits a map may hold unless ``INVISIBLE_MAP_MAX_CORRIDOR_EDITS`` says
#: (``app.config.Settings.max_corridor_edits``, where the choice is explained).
DEFAULT_MAX_EDITS = 5_000


@dataclass(frozen=True, slots=True, kw_only=True)
class EditsReport:
    """A map's corridor edits (oldest first) and what became of each on ``version``: the edits
    as of ``revision``."""

    map_id: int
    version: VersionInfo
    revision: int
    edits: tuple[StoredEdit, ...]
    outcomes: tuple[EditOutcome, ...]

    @property
    def applied_count(self) -> int:
        return sum(1 for outcome in self.outcomes if outcome.applied)

    @classmethod
    def of(cls, info: MapInfo, version: VersionInfo, edited: EditedVersion) -> EditsReport:
        return cls(
            map_id=info.id,
            version=version,
            revision=edited.revision,
            edits=edited.edits,
            outcomes=edited.edited.outcomes,
        )


def edits_report(
    cache: VersionCache, db_session: Session, info: MapInfo, number: int | None = None
) -> EditsReport:
    """The map's edits and their outcomes on version ``number`` (the current one if None);
    404 for no such version, 409 while the map has no version or the version no path graph."""
    version = chosen_version(db_session, info, number)
    edited = edited_version(cache, db_session, version, info.corridor_edits_revision)
    return EditsReport.of(info, version, edited)


def add_edit(
    cache: VersionCache,
    db_session: Session,
    map_id: int,
    document: Any,
    *,
    principal: Principal,
    expected_revision: int | None = None,
    max_edits: int = DEFAULT_MAX_EDITS,
) -> tuple[StoredEdit, EditsReport]:
    """Check ``document`` against the map's current version with its edits, and store it as the
    newest edit; the edit and the report after it (see the module docstring for the refusals;
    409 ``too_many_corridor_edits`` when the map has ``max_edits`` already). Raises
    MapNotFound. A refusal leaves the map's revision raised in the transaction: the caller
    rolls it back (an error raised through the request's transaction does)."""
    try:
        edit = edit_from_json(document)
    except EditInvalid as err:
        raise _refusal(err) from err
    revision = corridor_edits.lock_edits(db_session, map_id)  # the map's row, to the commit
    _check_expected(map_id, expected_revision, revision - 1)
    info = maps.get_map(db_session, map_id)
    version = chosen_version(db_session, info, None)
    # The edits as committed (revision − 1): kept by this process, else read (under the lock).
    before: EditedVersion | None = cache.peek((EDITED_PATH_GRAPH, version.id, revision - 1))
    if before is None:
        _, edits = corridor_edits.list_edits(db_session, map_id)
        before = edited_of(cache, db_session, version, revision - 1, edits)
        keep_edited(cache, before)  # committed: what revision − 1 is, here and elsewhere
    if len(before.edits) >= max_edits:
        raise Conflict(
            "too_many_corridor_edits",
            f"map {map_id} has {len(before.edits):,} corridor edits, the most a map may have "
            f"(INVISIBLE_MAP_MAX_CORRIDOR_EDITS = {max_edits:,}): delete edits it no longer "
            "needs, or rebuild the map's corridors, before adding more",
            field=None,
        )
    try:
        edited = apply_new_edit_to(before.edited, edit)
    except (EditInvalid, EditConflict) as err:
        raise _refusal(err) from err
    stored = corridor_edits.add_edit(
        db_session,
        map_id,
        edit,
        created_by=principal.subject,
        created_by_name=_key_name(db_session, principal),
    )
    after = before.extended(revision, [stored], edited)
    _keep_at_commit(db_session, cache, after)
    return stored, EditsReport.of(info, version, after)


def _keep_at_commit(db_session: Session, cache: VersionCache, value: EditedVersion) -> None:
    """Keep ``value`` in ``cache`` when ``db_session``'s transaction commits; never if it rolls
    back (its revision would be used again, by other edits)."""
    state = {"rolled_back": False}

    def rolled_back(_session: Session) -> None:
        state["rolled_back"] = True

    def committed(_session: Session) -> None:
        if not state["rolled_back"]:
            keep_edited(cache, value)

    event.listen(db_session, "after_soft_rollback", rolled_back, once=True)
    event.listen(db_session, "after_commit", committed, once=True)


def delete_edit(
    db_session: Session,
    map_id: int,
    edit_id: int,
    *,
    expected_revision: int | None = None,
) -> StoredEdit:
    """Delete the map's edit ``edit_id`` (undo); the edit deleted. 404 for no such map or edit.
    The edits after it stay, and apply without it from now on (an edit that needed it is
    reported as not applied)."""
    revision = corridor_edits.lock_edits(db_session, map_id)
    _check_expected(map_id, expected_revision, revision - 1)
    try:
        return corridor_edits.delete_edit(db_session, map_id, edit_id)
    except corridor_edits.EditNotFound as err:
        raise NotFound("not_found", str(err)) from err


def app_map_with_edits_gzip(
    cache: VersionCache, db_session: Session, version: VersionInfo, revision: int
) -> tuple[bytes, str]:
    """The app-map of ``version`` (gzip) made from its path graph with the map's corridor edits
    as of ``revision`` (its points of interest as the edits left them), and the edits' digest
    for its ETag. Without edits (or a path graph to apply them to) it is the version's own file
    (``app.services.maps.app_map_gzip``) and the digest is empty; with them it is made from the
    map document once per process and revision."""
    if revision == 0:
        return app_map_gzip(cache, db_session, version), ""
    try:
        edited = edited_version(cache, db_session, version, revision)
    except Conflict:  # a version built before path graphs: served as it is
        return app_map_gzip(cache, db_session, version), ""
    if not edited.edits:
        return app_map_gzip(cache, db_session, version), ""

    def make() -> bytes:
        stored = map_from_json(maps.map_document(db_session, version.map_id, version.number))
        content = app_map_of(with_edited_pois(stored, edited.path_graph), edited.path_graph)
        return gzip.compress(content, compresslevel=DERIVED_GZIP_LEVEL, mtime=0)

    zipped = cache.get(("app_map_gzip_edited", version.id, edited.revision), make)
    return zipped, edited.digest


def who(stored: StoredEdit) -> str:
    """Who made an edit, for people: the key's name and id, or the server's admin key."""
    if stored.created_by == ENVIRONMENT_ADMIN:
        return "the server's admin key"
    if stored.created_by_name:
        return f"{stored.created_by_name} ({stored.created_by})"
    return stored.created_by


def _key_name(db_session: Session, principal: Principal) -> str | None:
    if principal.key_id is None:
        return None
    try:
        return keys.get_key(db_session, principal.key_id).name
    except keys.KeyNotFound:
        return None


def _check_expected(map_id: int, expected: int | None, current: int) -> None:
    if expected is not None and expected != current:
        raise PreconditionFailed(
            "edits_changed",
            f"the corridor edits of map {map_id} changed since revision {expected} (now "
            f"{current}): read them again and retry",
        )


def _refusal(err: EditInvalid | EditConflict) -> InvalidInput | Conflict:
    field = err.field or None
    if isinstance(err, EditConflict):
        return Conflict("edit_conflict", str(err), field=field)
    return InvalidInput("invalid_edit", str(err), field=field)

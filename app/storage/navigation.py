"""What navigation reads and writes: a version's path graph, and live localization sessions.

A localization session's state is the localizer's JSON (``app.domain.localize``). Updates are
optimistic: :func:`save_update` writes only if the session's ``revision`` is still the one the
caller read, so two API processes handling updates of the same session cannot interleave
(the loser gets :class:`LocalizationConflict` and the client retries).
"""

from __future__ import annotations

import gzip
import json
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from app.storage.maps import MapNotFound, version_bytes
from app.storage.orm import Localization, MapRow, MapVersion, utc_now


class LocalizationNotFound(LookupError):
    """Raised when no localization session has the given id."""

    def __init__(self, localization_id: int) -> None:
        super().__init__(f"localization session {localization_id} not found")
        self.localization_id = localization_id


class LocalizationConflict(RuntimeError):
    """Raised when a localization session changed since it was read (a concurrent update)."""

    def __init__(self, localization_id: int) -> None:
        super().__init__(
            f"localization session {localization_id} was updated concurrently; send the update "
            "again"
        )
        self.localization_id = localization_id


@dataclass(frozen=True, slots=True, kw_only=True)
class LocalizationInfo:
    id: int
    map_id: int
    map_version_id: int
    map_version: int
    created_by: str
    created_at: datetime
    updated_at: datetime
    revision: int
    status: str
    update_count: int
    state: dict[str, Any]


def path_graph_document(db_session: Session, version_id: int) -> dict[str, Any] | None:
    """The version's path graph JSON, or None if the version has none."""
    found = db_session.execute(
        select(MapVersion.path_graph_gzip, MapVersion.path_graph_sha256).where(
            MapVersion.id == version_id
        )
    ).first()
    packed = None if found is None else version_bytes(db_session, *found)
    if packed is None:
        return None
    document: dict[str, Any] = json.loads(gzip.decompress(packed))
    return document


def create_localization(
    db_session: Session,
    *,
    map_id: int,
    map_version_id: int,
    created_by: str,
    status: str,
    state: dict[str, Any],
) -> LocalizationInfo:
    if db_session.get(MapRow, map_id) is None:
        raise MapNotFound(map_id)
    now = utc_now()
    row = Localization(
        map_id=map_id,
        map_version_id=map_version_id,
        created_by=created_by,
        created_at=now,
        updated_at=now,
        revision=0,
        status=status,
        update_count=0,
        state=state,
    )
    db_session.add(row)
    db_session.flush()
    return _info(db_session, row)


def get_localization(db_session: Session, localization_id: int) -> LocalizationInfo:
    row = db_session.get(Localization, localization_id)
    if row is None:
        raise LocalizationNotFound(localization_id)
    return _info(db_session, row)


def save_update(
    db_session: Session,
    localization_id: int,
    *,
    expected_revision: int,
    status: str,
    state: dict[str, Any],
) -> LocalizationInfo:
    """Store a new state if the session is still at ``expected_revision``."""
    updated = db_session.execute(
        update(Localization)
        .where(Localization.id == localization_id, Localization.revision == expected_revision)
        .values(
            revision=expected_revision + 1,
            status=status,
            state=state,
            update_count=Localization.update_count + 1,
            updated_at=utc_now(),
        )
        .returning(Localization.id)
    ).scalar_one_or_none()
    if updated is None:
        if db_session.get(Localization, localization_id) is None:
            raise LocalizationNotFound(localization_id)
        raise LocalizationConflict(localization_id)
    db_session.expire_all()
    return get_localization(db_session, localization_id)


def _info(db_session: Session, row: Localization) -> LocalizationInfo:
    number = db_session.scalar(select(MapVersion.number).where(MapVersion.id == row.map_version_id))
    return LocalizationInfo(
        id=row.id,
        map_id=row.map_id,
        map_version_id=row.map_version_id,
        map_version=int(number or 0),
        created_by=row.created_by,
        created_at=row.created_at,
        updated_at=row.updated_at,
        revision=row.revision,
        status=row.status,
        update_count=row.update_count,
        state=dict(row.state),
    )

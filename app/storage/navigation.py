"""What navigation reads and writes: a version's path graph, and live localization sessions.

A localization session's state is the localizer's JSON (``app.domain.localize``). Updates are
optimistic: :func:`save_update` writes only if the session's ``revision`` is still the one the
caller read, so two API processes handling updates of the same session cannot interleave
(the loser gets :class:`LocalizationConflict` and the client retries).

The API's update path uses the narrow pair instead, one statement each on a connection of
``Database.autocommit()`` (no ORM object, no transaction around them)::

    row = read_state(connection, localization_id, unless_revision=known)  # state text or None
    write_state(connection, localization_id, expected_revision=row.revision, status=…,
                state_json=…)  # UPDATE … WHERE id = ? AND revision = ?, or LocalizationConflict
"""

from __future__ import annotations

import functools
import gzip
import json
import re
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import Connection, Dialect, select, update
from sqlalchemy.exc import DBAPIError
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


@dataclass(frozen=True, slots=True, kw_only=True)
class LocalizationState:
    """What an update needs of its session (:func:`read_state`).

    state_json: the ``state`` column's JSON text, or None when the caller already has this
        revision's state (``unless_revision``).
    """

    id: int
    created_by: str
    map_version_id: int
    revision: int
    state_json: str | None


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


# The update path's statements, as SQL text run on the driver's own cursor: SQLAlchemy's
# statement execution costs several times what SQLite or PostgreSQL spend on a one-row
# statement (0.30 → 0.07 ms of CPU for the pair, measured). Written with sqlite3's ``:name``
# parameters; psycopg's ``%(name)s`` are derived from them. The state goes in as JSON text:
# SQLite keeps it so, and PostgreSQL parses it into the jsonb column (psycopg sends a str
# untyped, so the server takes it as the column's type).
_STATE_TEXT = "CAST(state AS TEXT)"
_SQLITE_STATEMENTS = {
    "read": f"SELECT created_by, map_version_id, revision, {_STATE_TEXT} "
    "FROM localization WHERE id = :id",
    "read_unless": "SELECT created_by, map_version_id, revision, "
    f"CASE WHEN revision = :known THEN NULL ELSE {_STATE_TEXT} END "
    "FROM localization WHERE id = :id",
    "write": "UPDATE localization SET revision = revision + 1, status = :status, "
    "state = :state, update_count = update_count + 1, updated_at = :updated_at "
    "WHERE id = :id AND revision = :expected_revision",
    "exists": "SELECT id FROM localization WHERE id = :id",
}


_STATEMENTS = {
    "sqlite": _SQLITE_STATEMENTS,
    "postgresql": {
        name: re.sub(r":(\w+)", r"%(\1)s", statement)
        for name, statement in _SQLITE_STATEMENTS.items()
    },
}


@contextmanager
def _executed(connection: Connection, name: str, parameters: dict[str, Any]) -> Iterator[Any]:
    """Statement ``name`` run on ``connection``'s driver cursor: the cursor, closed afterwards.
    Driver errors are raised as SQLAlchemy's (``DBAPIError``: the API's 503s), and a connection
    the server dropped is invalidated, as ``Connection.execute`` would."""
    statement = _STATEMENTS[connection.dialect.name][name]
    dbapi_connection = connection.connection
    cursor = dbapi_connection.cursor()
    try:
        try:
            cursor.execute(statement, parameters)
        except connection.dialect.loaded_dbapi.Error as err:
            disconnected = connection.dialect.is_disconnect(err, dbapi_connection, cursor)
            if disconnected:
                connection.invalidate(err)
            raise DBAPIError.instance(
                statement,
                parameters,
                err,
                connection.dialect.loaded_dbapi.Error,
                connection_invalidated=disconnected,
                dialect=connection.dialect,
            ) from err
        yield cursor
    finally:
        cursor.close()


@functools.cache
def _time_processor(dialect: Dialect) -> Callable[[datetime], Any] | None:
    """How the ``updated_at`` column's type stores a datetime on ``dialect`` (None: as it is)."""
    processor: Callable[[datetime], Any] | None = (
        Localization.__table__.c.updated_at.type.bind_processor(dialect)
    )
    return processor


def read_state(
    connection: Connection, localization_id: int, *, unless_revision: int | None = None
) -> LocalizationState:
    """One ``SELECT`` of what an update needs: the owner, the version, the revision and the state
    as JSON text (left out, None, if the revision is ``unless_revision``: the caller has that
    state already). Raises :class:`LocalizationNotFound`."""
    if unless_revision is None:
        statement, parameters = "read", {"id": localization_id}
    else:
        statement, parameters = "read_unless", {"id": localization_id, "known": unless_revision}
    with _executed(connection, statement, parameters) as cursor:
        row = cursor.fetchone()
    if row is None:
        raise LocalizationNotFound(localization_id)
    created_by, map_version_id, revision, state_json = row
    return LocalizationState(
        id=localization_id,
        created_by=created_by,
        map_version_id=map_version_id,
        revision=revision,
        state_json=state_json,
    )


def write_state(
    connection: Connection,
    localization_id: int,
    *,
    expected_revision: int,
    status: str,
    state_json: str,
) -> int:
    """One ``UPDATE … WHERE id = ? AND revision = ?`` (compare-and-set) storing ``state_json``
    (the whole ``state`` column as JSON text) as revision ``expected_revision + 1``, which it
    returns. Raises :class:`LocalizationConflict` if the session is at another revision now
    (:class:`LocalizationNotFound` if it is gone); then nothing is written."""
    now = utc_now()
    process_time = _time_processor(connection.dialect)
    parameters = {
        "id": localization_id,
        "expected_revision": expected_revision,
        "status": status,
        "state": state_json,
        "updated_at": now if process_time is None else process_time(now),
    }
    with _executed(connection, "write", parameters) as cursor:
        updated = cursor.rowcount
    if updated != 1:
        with _executed(connection, "exists", {"id": localization_id}) as cursor:
            found = cursor.fetchone()
        if found is None:
            raise LocalizationNotFound(localization_id)
        raise LocalizationConflict(localization_id)
    return expected_revision + 1

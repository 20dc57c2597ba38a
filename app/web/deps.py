"""Dependencies of the routes, each with a named ``Annotated`` alias; the aliases chain
(``ReadDbSessionDep`` → ``CurrentPrincipal`` → ``AdminPrincipal``), and some double as validators
(``MapDep`` is a map that exists, or a 404).

Authentication: ``Authorization: Bearer <key>`` on every ``/v1`` endpoint. A missing, unknown,
revoked or expired key is a 401 with ``WWW-Authenticate: Bearer``; a device key on an admin
endpoint is a 403. ``INVISIBLE_MAP_ADMIN_KEY``, when set, is an admin key.

Who may do what (``own`` = sessions the key uploaded, and the jobs made from them; someone
else's is a 404, so a device cannot learn what exists)::

    endpoint                               device     admin
    GET  /healthz, /readyz                 yes (no key needed)
    GET  /v1/info                          yes        yes
    POST /v1/sessions                      yes        yes
    GET  /v1/sessions[/{id}[/raw]]         own        all
    GET  /v1/jobs/{id}                     own        all
    GET  /v1/jobs, POST …/cancel, …/retry  403        yes
    GET  /v1/maps[/{id}[/…]]               all        all     (maps are shared for navigation)
    POST /v1/maps/{id}/rebuild             403        yes
    DELETE /v1/maps/{id}                   403        yes
    /v1/keys (create, list, get, revoke)   403        yes
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Iterator
from datetime import timedelta
from typing import Annotated, Any

from anyio import to_thread
from fastapi import Depends, Path, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session

from app.config import Settings
from app.services.keys import PrincipalCache
from app.services.maps import MapState, MapStates
from app.storage import keys, queue, sessions
from app.storage.db import Database
from app.storage.images import MAX_IMAGE_BYTES
from app.storage.maps import MapInfo, MapNotFound
from app.storage.orm import utc_now
from app.storage.queue import JobInfo
from app.storage.sessions import SessionInfo
from app.web.errors import ApiError, not_found, unauthorized
from app.web.upload import RawBody, read_body, read_image_body

logger = logging.getLogger(__name__)

#: Ids are 1 … 2^31 - 1, the range of the columns (32-bit INTEGER on PostgreSQL; SQLite's are
#: wider, but no id beyond it is ever made). Any other number names nothing: it gets the answer an
#: id that does not exist gets (a 404 for a path's id, nothing found for a filter), and never
#: reaches the driver, where PostgreSQL refuses it (issue 40).
MAX_ID = 2**31 - 1
#: The rule as the OpenAPI document states it for every id parameter.
ID_RULE = (
    f"an id, 1 to {MAX_ID}; any other number names nothing and is answered as an id that "
    "does not exist"
)
#: ``last_used_at`` of a key is written at most this often per process, s.
KEY_TOUCH_INTERVAL_S = 60.0


# --------------------------------------------------------------------------- app state


async def get_settings(request: Request) -> Settings:
    """The settings ``create_app`` was given."""
    settings: Settings = request.app.state.settings
    return settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


async def get_db(request: Request) -> Database:
    """The process's database (created by the app's lifespan)."""
    db: Database = request.app.state.db
    return db


DbDep = Annotated[Database, Depends(get_db)]


def read_db_session(db: DbDep) -> Iterator[Session]:
    """One read-only transaction for the request."""
    with db.read() as db_session:
        yield db_session


def write_db_session(db: DbDep) -> Iterator[Session]:
    """One read-write transaction for the request: committed when the route returns (before the
    response is sent), rolled back if it raises."""
    with db.transaction() as db_session:
        yield db_session


ReadDbSessionDep = Annotated[Session, Depends(read_db_session, scope="function")]
WriteDbSessionDep = Annotated[Session, Depends(write_db_session, scope="function")]


# --------------------------------------------------------------------------- authentication


#: The window of :class:`UploadRate`, s.
UPLOAD_WINDOW_S = 60.0


class KeyUsage:
    """Remembers when this process last wrote a key's ``last_used_at``, so that it is written at
    most once per :data:`KEY_TOUCH_INTERVAL_S` instead of on every request."""

    def __init__(self, interval_s: float = KEY_TOUCH_INTERVAL_S) -> None:
        self.interval_s = interval_s
        self._last_s: dict[int, float] = {}
        self._lock = threading.Lock()

    def due(self, key_id: int) -> bool:
        """Whether ``key_id``'s use should be written now (and note that it is)."""
        now_s = time.monotonic()
        with self._lock:
            last_s = self._last_s.get(key_id)
            if last_s is not None and now_s - last_s < self.interval_s:
                return False
            self._last_s[key_id] = now_s
            return True


bearer_scheme = HTTPBearer(
    auto_error=False,
    scheme_name="ApiKey",
    description="An API key (`im_<prefix>_<secret>`) as `Authorization: Bearer <key>`. "
    "Keys have a role: device (upload, read maps and its own sessions and jobs) or admin.",
)
BearerDep = Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)]


async def current_principal(request: Request, credentials: BearerDep) -> keys.Principal:
    """Who is calling: 401 without a valid key. A key this process checked within
    ``INVISIBLE_MAP_KEY_CACHE_S`` is known from memory, on the event loop; otherwise it is read
    on a thread, in its own short transaction (no connection is held while an upload's body
    streams in).

    Every ``/v1`` request solves this dependency, so it takes the settings and the database from
    the app's state itself rather than through ``SettingsDep`` and ``DbDep``: each dependency
    FastAPI solves costs the request CPU on the event loop."""
    if credentials is None:
        raise unauthorized("missing API key: send Authorization: Bearer <key>")
    state = request.app.state
    principals: PrincipalCache = state.principals
    principal = principals.cached(credentials.credentials)
    db: Database = state.db
    if principal is None:
        principal = await run_in_threadpool(
            _authenticate, db, principals, credentials.credentials, state.settings.admin_key
        )
    if principal is None:
        raise unauthorized("unknown, revoked or expired API key", invalid_token=True)
    usage: KeyUsage = state.key_usage
    if principal.key_id is not None and usage.due(principal.key_id):
        await run_in_threadpool(_touch, db, principal.key_id)
    return principal


def _authenticate(
    db: Database, principals: PrincipalCache, key: str, admin_key: str | None
) -> keys.Principal | None:
    with db.read() as db_session:
        return principals.authenticate(db_session, key, admin_key=admin_key)


def _touch(db: Database, key_id: int) -> None:
    """Record a key's use; best effort (a busy database must not fail the request)."""
    try:
        with db.transaction() as db_session:
            keys.touch(db_session, key_id)
    except SQLAlchemyError as err:
        logger.warning("could not record use of key %d: %s", key_id, err)


CurrentPrincipal = Annotated[keys.Principal, Depends(current_principal)]


def admin_principal(principal: CurrentPrincipal) -> keys.Principal:
    """An admin: 403 for a device key."""
    if not principal.is_admin:
        raise ApiError(403, "forbidden", "this needs an admin key; yours is a device key")
    return principal


AdminPrincipal = Annotated[keys.Principal, Depends(admin_principal)]


# --------------------------------------------------------------------------- ids


def is_id(value: int) -> bool:
    """Whether ``value`` can be an id (:data:`MAX_ID`)."""
    return 1 <= value <= MAX_ID


def id_path(what: str) -> Any:
    """A path parameter that is the id of ``what``, with :data:`ID_RULE` in its description."""
    return Path(description=f"the {what}'s id: {ID_RULE} (404 not_found)")


MapId = Annotated[int, id_path("map")]
SessionId = Annotated[int, id_path("session")]
JobId = Annotated[int, id_path("job")]
KeyId = Annotated[int, id_path("API key")]
SweepId = Annotated[int, id_path("sweep")]
EditId = Annotated[int, id_path("corridor edit")]
LocalizationId = Annotated[int, id_path("localization session")]
#: ``?version=N``: a version of the map, the current one when left out.
VersionQuery = Annotated[
    int | None,
    Query(
        description=f"a version number, 1 to {MAX_ID}; the current version when left out; any "
        "other number names nothing and is answered as a version that does not exist (404 "
        "not_found)",
    ),
]
#: A query parameter that lists only one map's: a number that is no id finds nothing, as the id
#: of a map that does not exist would.
MapFilter = Annotated[
    int | None,
    Query(
        description=f"only this map's: {ID_RULE} (an empty list)",
    ),
]
VersionNumber = Annotated[
    int,
    Path(
        description=f"the version's number: 1 to {MAX_ID}; any other number names nothing and "
        "is answered as a version that does not exist (404 not_found)"
    ),
]


# --------------------------------------------------------------------------- validators


# The validators read in short transactions of their own, not the request's: a connection held
# by a dependency would be held while the request waits for a thread for the route
# (app.web.route_class says why that must not happen).


async def valid_map_state(map_id: MapId, request: Request) -> MapState:
    """The map ``map_id`` with its current version and newest job, or 404: from this process's
    memory when it is fresh (``app.services.maps.MapStates``, on the event loop), else read on a
    thread. (The database from the app's state, not ``DbDep``: one dependency less to solve on
    the hot read path.)"""
    if not is_id(map_id):
        raise not_found(f"map {map_id}")
    states: MapStates = request.app.state.map_states
    state = states.fresh(map_id)
    if state is None:
        state = await run_in_threadpool(states.load, request.app.state.db, map_id)
    return state


MapStateDep = Annotated[MapState, Depends(valid_map_state)]


async def valid_map(state: MapStateDep) -> MapInfo:
    """The map ``map_id`` (with its current version), or 404."""
    return state.info


MapDep = Annotated[MapInfo, Depends(valid_map)]


def valid_session(session_id: SessionId, db: DbDep, principal: CurrentPrincipal) -> SessionInfo:
    """The session ``session_id`` if the caller may see it (admin, or its uploader), or 404."""
    if not is_id(session_id):
        raise not_found(f"session {session_id}")
    with db.read() as db_session:
        info = sessions.get_session(db_session, session_id)
    if not principal.is_admin and info.uploaded_by != principal.subject:
        raise not_found(f"session {session_id}")
    return info


SessionDep = Annotated[SessionInfo, Depends(valid_session)]


async def valid_job(job_id: JobId, db: DbDep, principal: CurrentPrincipal) -> JobInfo:
    """The job ``job_id`` if the caller may see it (admin, or the uploader of its session),
    read on a thread (the request's one hop)."""
    if not is_id(job_id):
        raise not_found(f"job {job_id}")
    return await run_in_threadpool(_visible_job, db, job_id, principal)


def _visible_job(db: Database, job_id: int, principal: keys.Principal) -> JobInfo:
    with db.read() as db_session:
        job = queue.get_job(db_session, job_id)
        if principal.is_admin:
            return job
        uploader = (
            None if job.session_id is None else sessions.uploader_of(db_session, job.session_id)
        )
    if uploader is None or uploader != principal.subject:
        raise not_found(f"job {job_id}")
    return job


JobDep = Annotated[JobInfo, Depends(valid_job)]


def valid_version(map_id: int, number: int) -> int:
    """``number`` if it can be a version's number, else the 404 of a version map ``map_id``
    does not have."""
    if not is_id(number):
        raise MapNotFound(map_id, number)
    return number


def valid_id(value: int, what: str) -> int:
    """``value`` if it can be an id, else 404 for ``what``."""
    if not is_id(value):
        raise not_found(f"{what} {value}")
    return value


# --------------------------------------------------------------------------- upload body


class UploadRate:
    """At most ``per_minute`` uploads stored per device key in any 60 s; admin keys are not
    limited. One phone cannot fill the queue for everyone.

    Counted from the ``session`` table (the key's sessions stored in the last 60 s), so the limit
    holds across API processes and restarts; refused uploads and replays store no session and do
    not count. The check comes before the body is read, so uploads of one key already in flight
    when it reaches its limit may still be stored (at most one per request in flight)."""

    def __init__(self, per_minute: int) -> None:
        self.per_minute = per_minute

    def retry_after_s(self, db: Database, subject: str) -> int | None:
        """None if ``subject`` may upload now, else the seconds until it may."""
        if self.per_minute <= 0:
            return None
        now = utc_now()
        with db.read() as db_session:
            oldest_counted = sessions.nth_latest_upload_at(
                db_session,
                subject,
                n=self.per_minute,
                since=now - timedelta(seconds=UPLOAD_WINDOW_S),
            )
        if oldest_counted is None:
            return None
        return max(1, math.ceil((oldest_counted - now).total_seconds() + UPLOAD_WINDOW_S))


def upload_rate(request: Request) -> UploadRate:
    rate: UploadRate = request.app.state.upload_rate
    return rate


async def upload_body(
    request: Request,
    settings: SettingsDep,
    principal: CurrentPrincipal,
    rate: Annotated[UploadRate, Depends(upload_rate)],
    db: DbDep,
) -> RawBody:
    """The raw upload (415 for another media type or encoding, 413 over the raw limit); 429 with
    ``Retry-After`` before reading it when the device key uploaded its
    ``INVISIBLE_MAP_UPLOADS_PER_MINUTE`` already."""
    if not principal.is_admin:
        wait_s = await to_thread.run_sync(rate.retry_after_s, db, principal.subject)
        if wait_s is not None:
            raise ApiError(
                429,
                "rate_limited",
                f"this key uploaded {rate.per_minute} sessions in the last minute, its limit; "
                f"try again in {wait_s} s",
                headers={"Retry-After": str(wait_s)},
            )
    return await read_body(request, max_upload_bytes=settings.max_upload_bytes)


UploadBodyDep = Annotated[RawBody, Depends(upload_body)]


async def image_body(request: Request) -> bytes:
    """A picture's JPEG bytes (415 for another media type, 413 over the limit)."""
    return await read_image_body(request, max_bytes=MAX_IMAGE_BYTES)


ImageBodyDep = Annotated[bytes, Depends(image_body)]

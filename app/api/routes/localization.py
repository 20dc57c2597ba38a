"""Live localization: ``POST /v1/maps/{id}/localizations`` starts a navigation session pinned to
the map's current version; ``POST /v1/localizations/{id}/updates`` folds in the phone's new
odometry and tag detections and answers where the phone is in the map.

The localizer (``app.domain.localize``) is a pure function of (state, update); its state lives in
the ``localization`` row, so any API process can take the next update, and a restart loses
nothing. An update reads the state (one statement), computes, and writes the new state only if
the row's revision is still the one it read (one ``UPDATE … WHERE revision = ?``), all on one
thread off the event loop (one update at a time per process: :data:`LOCALIZER_THREADS`); a
concurrent update of the same session makes the later one a 409 ``concurrent_update`` (send it
again). Each process keeps the states it wrote decoded (:class:`HotStates`) and uses one only
while the row is still at its revision. A malformed update (an unknown tag, pose ids or
timestamps going backwards, a pose that is not a rigid transform, a non-finite number, more
poses or detections than one update may hold) is a 422 naming the field, and the session is left
as it was.

Device keys see only the navigation sessions they started (another's is a 404).
"""

from __future__ import annotations

import functools
import threading
from collections import OrderedDict
from typing import Annotated, Any

import orjson
from anyio import CapacityLimiter, to_thread
from fastapi import APIRouter, Body, Request, Response

from app.api.schemas.navigation import LocalizationEstimate, LocalizationPublic, LocalizationUpdate
from app.domain.frames import FloatArray, pose_from_xyz_quat_xyzw
from app.domain.localize import (
    MAX_UPDATE_DETECTIONS,
    MAX_UPDATE_POSES,
    LocalizationUpdateError,
    LocalizerState,
    parse_update,
    update,
)
from app.services.maps import chosen_version
from app.services.version_cache import VersionCache
from app.storage import maps, navigation
from app.storage.db import Database
from app.storage.keys import Principal
from app.storage.navigation import LocalizationConflict, LocalizationInfo
from app.web.deps import (
    CurrentPrincipal,
    DbDep,
    LocalizationId,
    MapId,
    ReadDbSessionDep,
    valid_id,
)
from app.web.errors import ApiError, error_responses
from app.web.route_class import SessionEndingRoute

router = APIRouter(tags=["localization"], route_class=SessionEndingRoute)

#: Threads of an API process that run localization updates at once; the others wait their turn
#: on the event loop. One: an update is pure Python and numpy that holds the GIL (it lets go
#: twice, in a stacked SVD and an einsum) and the interpreter makes a thread that holds it give
#: it up every 5 ms to one that waits, so updates on several threads of one process hand the GIL
#: back and forth and each costs far more CPU (``bench/http.py``'s update row, 8 connections, one
#: API process: 2.66 → 1.77 ms of CPU per update, 416 → 559 updates/s, p99 40 → 23 ms).
#: Processes, not threads, add capacity (``serve --api-processes``).
LOCALIZER_THREADS = 1


def localizer_threads() -> CapacityLimiter:
    """A new limiter of :data:`LOCALIZER_THREADS` (the lifespan makes one per app and event loop,
    ``app.state.localizer_threads``)."""
    return CapacityLimiter(LOCALIZER_THREADS)


def _public(info: LocalizationInfo) -> LocalizationPublic:
    last = info.state.get("last_result")
    return LocalizationPublic(
        id=info.id,
        map_id=info.map_id,
        map_version=info.map_version,
        created_at=info.created_at,
        updated_at=info.updated_at,
        updates=info.update_count,
        estimate=LocalizationEstimate.from_result_json(last) if last else None,
    )


def _owned(info: LocalizationInfo, principal: Principal) -> LocalizationInfo:
    if not principal.is_admin and info.created_by != principal.subject:
        raise ApiError(404, "not_found", f"localization session {info.id} not found")
    return info


def _map_tags(request: Request, db: Database, version_id: int) -> dict[int, FloatArray]:
    def load() -> dict[int, FloatArray]:
        with db.read() as db_session:
            rows = maps.tag_poses(db_session, version_id)
        return {
            row.tag_id: pose_from_xyz_quat_xyzw([*row.position_m, *row.quat_xyzw]) for row in rows
        }

    cache: VersionCache = request.app.state.version_cache
    return cache.get(("map_tags", version_id), load)


@router.post(
    "/maps/{map_id}/localizations",
    status_code=201,
    summary="Start a navigation session",
    description="A navigation session in the map's current version (the version stays pinned for "
    "the session). It is `not_localized` until an update brings a detection of a tag in the map.",
    responses=error_responses(401, 404, 409, 422),
)
def start(
    map_id: MapId, principal: CurrentPrincipal, db: DbDep, response: Response
) -> LocalizationPublic:
    # Committed here, in the route's own thread (not by a dependency after the answer is
    # validated on another thread): SQLite's write lock is never held while waiting for a thread.
    with db.transaction() as db_session:
        info = maps.get_map(db_session, valid_id(map_id, "map"))
        current = chosen_version(db_session, info, None)  # 409 map_not_ready without a version
        created = navigation.create_localization(
            db_session,
            map_id=info.id,
            map_version_id=current.id,
            created_by=principal.subject,
            status="not_localized",
            state={"localizer": LocalizerState.initial().to_json(), "last_result": None},
        )
    response.headers["Location"] = f"/v1/localizations/{created.id}"
    return _public(created)


@router.get(
    "/localizations/{localization_id}",
    summary="Get a navigation session",
    description="The session's map version and its latest estimate.",
    responses=error_responses(401, 404, 422),
)
def get(
    localization_id: LocalizationId, principal: CurrentPrincipal, db_session: ReadDbSessionDep
) -> LocalizationPublic:
    info = navigation.get_localization(
        db_session, valid_id(localization_id, "localization session")
    )
    return _public(_owned(info, principal))


@router.post(
    "/localizations/{localization_id}/updates",
    summary="Send odometry and detections; get the phone's pose in the map",
    description="Folds the new poses and detections into the session (warm-started, a cost per "
    "update that does not grow with the session) and answers the phone's newest pose in the map, "
    "the session-to-map transform with its covariance, the tags used, and the status "
    "(`not_localized` until the first known tag). An update holds at most "
    f"{MAX_UPDATE_POSES:,} poses and {MAX_UPDATE_DETECTIONS} detections (a larger backlog goes "
    "in several). 422 names a malformed field and changes nothing; 409 when another update of "
    "the same session got in first (send it again).",
    response_model=LocalizationEstimate,
    responses=error_responses(
        401,
        404,
        409,
        422,
        examples={
            422: ("invalid_update", "tag_data[0][0].tag_id: tag 999 is not in this map"),
            409: ("concurrent_update", "localization session 7 was updated concurrently"),
        },
    ),
)
async def post_update(
    localization_id: LocalizationId,
    body: Annotated[LocalizationUpdate, Body()],
    principal: CurrentPrincipal,
    request: Request,
) -> Response:
    localization_id = valid_id(localization_id, "localization session")
    # (what parse_update reads; the model's lists hold the parsed JSON as it came)
    document: dict[str, Any] = {"poses": body.poses, "tag_data": body.tag_data}
    # Read, compute and write on one thread of the pool: one hop off the event loop.
    estimate = await to_thread.run_sync(
        functools.partial(apply_update, request, localization_id, document, principal),
        limiter=request.app.state.localizer_threads,
    )
    return Response(content=estimate, media_type="application/json")


def apply_update(
    request: Request, localization_id: int, document: dict[str, Any], principal: Principal
) -> bytes:
    """One update of a navigation session: its state read in one statement, the localizer run,
    the new state written in one compare-and-set statement; the answer's JSON.

    The state in the database is the truth. This process keeps the states it wrote last
    (:class:`HotStates`) and skips reading and decoding the state when the row is still at the
    revision it wrote; after another process's update the revisions differ and the row's state
    is read."""
    db: Database = request.app.state.db
    hot = hot_states(request)
    known = hot.get(localization_id)
    # (durable=False: a crash of PostgreSQL itself may lose the last fraction of a second of
    # updates; the phone's next update then follows the state before them)
    with db.autocommit(durable=False) as connection:
        row = navigation.read_state(
            connection, localization_id, unless_revision=None if known is None else known[0]
        )
        if not principal.is_admin and row.created_by != principal.subject:
            raise ApiError(404, "not_found", f"localization session {localization_id} not found")
        map_tags = _map_tags(request, db, row.map_version_id)
        try:
            if row.state_json is None and known is not None:
                state = known[1]
            else:
                assert row.state_json is not None
                state = LocalizerState.from_json(orjson.loads(row.state_json)["localizer"])
            new_state, result = update(state, parse_update(document), map_tags)
        except LocalizationUpdateError as err:
            raise ApiError(422, "invalid_update", str(err), field=err.field or None) from err
        # (non-finite numbers, an unbounded covariance, become null: orjson and pydantic's JSON
        # both write them so)
        result_json = result.to_json()
        state_json = orjson.dumps(
            {"localizer": new_state.to_json(), "last_result": result_json},
            option=orjson.OPT_SERIALIZE_NUMPY,
        ).decode()
        try:
            revision = navigation.write_state(
                connection,
                localization_id,
                expected_revision=row.revision,
                status=result.status,
                state_json=state_json,
            )
        except LocalizationConflict as err:
            hot.forget(localization_id)
            raise ApiError(409, "concurrent_update", str(err)) from err
    hot.put(localization_id, revision, new_state)
    return LocalizationEstimate.from_result_json(result_json).model_dump_json().encode()


#: Navigation sessions whose latest state an API process keeps decoded (:class:`HotStates`).
HOT_STATES = 1024


class HotStates:
    """The localizer states this process wrote last, by session: ``(revision, state)``, an LRU
    of :data:`HOT_STATES` sessions. Only a cache: an update uses its state only while the row is
    still at that revision (``navigation.read_state(…, unless_revision=…)``), so any process may
    take any update."""

    def __init__(self, max_entries: int = HOT_STATES) -> None:
        self.max_entries = max_entries
        self._states: OrderedDict[int, tuple[int, LocalizerState]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, localization_id: int) -> tuple[int, LocalizerState] | None:
        with self._lock:
            return self._states.get(localization_id)

    def put(self, localization_id: int, revision: int, state: LocalizerState) -> None:
        with self._lock:
            known = self._states.get(localization_id)
            if known is not None and known[0] > revision:
                return  # a later update of this process got in first
            self._states[localization_id] = (revision, state)
            self._states.move_to_end(localization_id)
            while len(self._states) > self.max_entries:
                self._states.popitem(last=False)

    def forget(self, localization_id: int) -> None:
        with self._lock:
            self._states.pop(localization_id, None)


def hot_states(request: Request) -> HotStates:
    """The app's :class:`HotStates` (made by ``create_app``)."""
    states: HotStates = request.app.state.hot_localizer_states
    return states

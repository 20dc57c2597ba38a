"""Maps: the version a request means, rebuilds, deletion, the app-map document.

What the API routers and the dashboard pages both do; errors are :mod:`app.services.errors`.
"""

from __future__ import annotations

import gzip
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy.orm import Session

from app.domain.errors import InvisibleMapError, ParameterError
from app.domain.evaluation.ground_truth import ground_truth_to_json, parse_ground_truth_json
from app.domain.formats.derived_documents import APP_MAP_EXPORT as APP_MAP_EXPORT
from app.domain.formats.derived_documents import DERIVED_GZIP_LEVEL, app_map_bytes
from app.domain.mapping.params import SlamParams
from app.services.errors import Conflict, InvalidInput, NotFound, require_text
from app.services.version_cache import VersionCache, size_in_bytes
from app.storage import images, maps, queue, sessions
from app.storage.changes import MAP_CHANGES
from app.storage.db import Database
from app.storage.images import MapImage, StoredImage
from app.storage.maps import BUILD_MAP, MapInfo, TagPose, VersionInfo
from app.storage.navigation import path_graph_document
from app.storage.orm import TERMINAL_STATES, JobState, MapRow
from app.storage.queue import JobInfo
from app.storage.sessions import AUTO_TUNE_TRIALS, SESSION_IDS


@dataclass(frozen=True, slots=True, kw_only=True)
class BuildQueued:
    """What a change of a map (a rebuild, a session added, taken out or merged in) queued: the
    map after it, the job that builds its new generation, and what that job replaced."""

    info: MapInfo
    job_id: int
    #: the map's generation the job builds (``app.storage.maps.bump_generation``)
    generation: int
    #: the change was folded into job ``job_id``, queued before and not started yet
    coalesced: bool
    #: running builds asked to stop (and older queued ones canceled): their result would not
    #: have been of the map's current sessions and parameters
    superseded: tuple[int, ...]
    #: the parameter overrides the job builds with
    params: dict[str, Any]


def request_build(
    db_session: Session,
    map_id: int,
    overrides: dict[str, Any] | None,
    *,
    max_attempts: int,
    change: str,
    session_ids: list[int] | None = None,
) -> BuildQueued:
    """After a change of map ``map_id`` (``change`` says which, for the job's log), in the
    caller's transaction: bump its generation and have one build of its current sessions with
    ``overrides`` (already checked, see :func:`checked_overrides`) under way — a queued build
    absorbs it, a running one is superseded (``app.storage.queue.enqueue_coalesced``).
    ``overrides`` None (a change of sessions): the map's parameters as they stand
    (:func:`map_parameters`), so a change folded into a rebuild not yet built keeps its
    parameters; ``auto_tune_trials`` among them is dropped, with a line in the job's log, once
    the map has several sessions.
    ``session_ids``: build from these (an older version's, to make it again; checked by
    :func:`checked_session_ids`); they become the map's sessions, since only a version of the
    map's own sessions can be current. A 422 naming ``auto_tune_trials`` when the build would be
    of several sessions (tuning a map of several walks is not supported: a sweep tunes one).
    Raises MapNotFound, also when a delete of the map commits meanwhile (the map row is locked
    first, so a delete waits for this transaction, or this one for the delete)."""
    maps.lock_maps(db_session, [map_id])
    if session_ids is not None:
        maps.set_sessions(db_session, map_id, session_ids)
    info = maps.get_map(db_session, map_id)
    ids = list(info.session_ids)
    if overrides is None:
        overrides = map_parameters(db_session, info)
        if overrides.get(AUTO_TUNE_TRIALS) and len(ids) > 1:
            change += (
                f" (its {AUTO_TUNE_TRIALS}={overrides.pop(AUTO_TUNE_TRIALS)} dropped: "
                f"it tunes a map of one session)"
            )
    if overrides.get(AUTO_TUNE_TRIALS) and len(ids) > 1:
        raise tuning_refused(map_id, len(ids))
    generation = maps.bump_generation(db_session, map_id)
    params = dict(overrides)
    if len(ids) > 1:
        params[SESSION_IDS] = ids
    done = queue.enqueue_coalesced(
        db_session,
        kind=BUILD_MAP,
        map_id=info.id,
        session_id=ids[0],
        params=params,
        map_generation=generation,
        max_attempts=max_attempts,
        note=f"{change}; generation {generation} builds sessions {ids}",
    )
    info = maps.get_map(db_session, map_id)
    return BuildQueued(
        info=info,
        job_id=done.job_id,
        generation=generation,
        coalesced=done.coalesced,
        superseded=done.superseded,
        params=dict(overrides),
    )


def map_parameters(db_session: Session, info: MapInfo) -> dict[str, Any]:
    """The parameter overrides map ``info`` is being built with: those of its newest queued or
    running build (a rebuild asked for and not built yet), else its current version's
    (:func:`current_overrides`)."""
    pending = queue.jobs_of_map(
        db_session, info.id, kind=BUILD_MAP, states=(JobState.QUEUED, JobState.RUNNING)
    )
    if pending:
        return {name: v for name, v in pending[-1].params.items() if name != SESSION_IDS}
    return current_overrides(info)


def tuning_refused(map_id: int, session_count: int | None = None) -> InvalidInput:
    """The 422 of ``auto_tune_trials`` asked for a build of several sessions (``session_count``;
    None: an upload into map ``map_id``, which then holds it and at least one more)."""
    built_from = (
        f"would be built from {session_count} sessions"
        if session_count is not None
        else "would be built from its sessions and this one"
    )
    return InvalidInput(
        "invalid_parameter",
        f"auto_tune_trials tunes a map of one session; map {map_id} {built_from}: tune a map "
        f"of several with a sweep (POST /v1/maps/{map_id}/sweeps), which tunes their joint map, "
        "then apply its best parameters",
        field="auto_tune_trials",
    )


def enqueue_rebuild(
    db_session: Session,
    map_id: int,
    overrides: dict[str, Any],
    *,
    max_attempts: int,
    session_ids: list[int] | None = None,
) -> tuple[MapInfo, int]:
    """A rebuild of map ``map_id`` (:func:`request_build`): the map and the build's job id."""
    queued = request_build(
        db_session,
        map_id,
        overrides,
        max_attempts=max_attempts,
        change="rebuild requested",
        session_ids=session_ids,
    )
    return queued.info, queued.job_id


def checked_session_ids(db_session: Session, session_ids: list[int]) -> None:
    """A 422 naming the first session id that is repeated or is no session."""
    seen: set[int] = set()
    for k, session_id in enumerate(session_ids):
        if session_id in seen:
            raise InvalidInput(
                "invalid_sessions",
                f"session {session_id} is listed twice",
                field=f"session_ids.{k}",
            )
        seen.add(session_id)
        try:
            sessions.get_session(db_session, session_id)
        except sessions.SessionNotFound as err:
            raise InvalidInput(
                "invalid_sessions", f"session {session_id} not found", field=f"session_ids.{k}"
            ) from err


def current_overrides(info: MapInfo) -> dict[str, Any]:
    """The current version's parameters that differ from the defaults (a rebuild after a change
    of sessions keeps them); none before the first version."""
    if info.current is None:
        return {}
    defaults = SlamParams().to_dict()
    return {
        name: value
        for name, value in info.current.params.items()
        if name in defaults and value != defaults[name]
    }


def add_session_to_map(
    db_session: Session, map_id: int, session_id: int, *, max_attempts: int
) -> BuildQueued:
    """Add an uploaded session to a map and have the build of all its sessions under way
    (:func:`request_build`). 404 for no such map or session, 409 ``already_in_map``."""
    sessions.get_session(db_session, session_id)  # SessionNotFound: 404
    try:
        maps.add_session(db_session, map_id, session_id)
    except maps.MapMembershipError as err:
        raise Conflict(err.code, str(err)) from err
    return request_build(
        db_session, map_id, None, max_attempts=max_attempts, change=f"session {session_id} added"
    )


def remove_session_from_map(
    db_session: Session, map_id: int, session_id: int, *, max_attempts: int
) -> BuildQueued:
    """Take a session out of a map (the upload stays) and have the build without it under way.
    404 for no such map, 409 ``not_in_map`` or ``last_session``."""
    try:
        maps.remove_session(db_session, map_id, session_id)
    except maps.MapMembershipError as err:
        if err.code == "not_in_map":
            raise NotFound(err.code, str(err)) from err
        raise Conflict(err.code, str(err)) from err
    return request_build(
        db_session,
        map_id,
        None,
        max_attempts=max_attempts,
        change=f"session {session_id} taken out",
    )


def merge_maps(
    db_session: Session, map_id: int, other_map_id: int, *, max_attempts: int
) -> BuildQueued:
    """Merge map ``other_map_id`` into ``map_id``: its sessions join this map's (after them) and
    it is deleted (its sessions' uploads stay); has the build of this map under way. Both maps
    are locked first, in ascending id order, so that a merge racing another merge of the same
    maps (either way), a delete, or a change of their sessions waits for it and then finds what
    it left: 404 for either map missing, 409 ``same_map`` for a map merged into itself."""
    if map_id == other_map_id:
        raise Conflict("same_map", f"map {map_id} cannot be merged into itself")
    maps.lock_maps(db_session, [map_id, other_map_id], for_delete=True)
    ids = maps.map_session_ids(db_session, map_id)
    other_ids = maps.map_session_ids(db_session, other_map_id)
    for session_id in other_ids:
        if session_id not in ids:
            maps.add_session(db_session, map_id, session_id)
            ids.append(session_id)
    delete_map_and_jobs(db_session, other_map_id)
    return request_build(
        db_session, map_id, None, max_attempts=max_attempts, change=f"map {other_map_id} merged in"
    )


def checked_overrides(overrides: dict[str, Any]) -> dict[str, Any]:
    """The overrides as the worker will read them (values coerced, e.g. "1e-3" → 0.001), each
    within its range (``params.PARAM_RANGES``: a Huber threshold of 1e308 or a billion
    iterations is no setting), or a 422 naming the first bad parameter and its range."""
    defaults = SlamParams()
    for name, value in overrides.items():
        try:
            defaults.with_checked_overrides({name: value})
        except ParameterError as err:
            raise InvalidInput("invalid_parameter", str(err), field=f"params.{name}") from err
    try:
        params = defaults.with_checked_overrides(overrides).to_dict()
    except ParameterError as err:
        raise InvalidInput("invalid_parameter", str(err), field="params") from err
    return {name: params[name] for name in overrides}


def checked_ground_truth(document: dict[str, Any]) -> dict[str, Any]:
    """Ground truth in the JSON form sweeps take, as the job keeps it (its poses alone, numbers
    normalized: no unknown key or text of the client's reaches the database), else a 422
    ``invalid_ground_truth`` whose detail names the field and the reason."""
    try:
        return ground_truth_to_json(parse_ground_truth_json(document))
    except InvisibleMapError as err:
        raise InvalidInput("invalid_ground_truth", str(err), field="ground_truth") from err


#: Longest display name, characters (the column's size).
MAX_DISPLAY_NAME_LENGTH = 200
#: Media type of the pictures the app sends.
JPEG_MEDIA_TYPE = "image/jpeg"


#: gzip level of the app-map kept in memory: made once per version, so the smaller file wins.
APP_MAP_GZIP_LEVEL = DERIVED_GZIP_LEVEL


def app_map_gzip(cache: VersionCache, db_session: Session, version: VersionInfo) -> bytes:
    """:func:`app_map_content` of ``version``, gzip-compressed, read or made once per API
    process and then served from ``cache`` (a version never changes; a rebuild is another
    version). Only the compressed file is kept: a quarter of the memory, and a client that does
    not take gzip costs a decompression (about 2 ms per MB) instead of a rebuild of the file."""
    return cache.get(("app_map_gzip", version.id), lambda: stored_app_map_gzip(db_session, version))


def stored_app_map_gzip(db_session: Session, version: VersionInfo) -> bytes:
    """The app-map of ``version``, gzip: as the worker stored it with the version when the
    current export (:data:`APP_MAP_EXPORT`) made it (1–2 MiB read, nothing decoded: issue 19,
    finding 3), else made by :func:`app_map_content` (versions stored before, or made by an
    older export), which decodes the whole map document (for a 100,000-pose walk the
    API grows by about 100 MiB while it does)."""
    if version.app_map_export == APP_MAP_EXPORT:
        stored = maps.derived_bytes(db_session, version.app_map_sha256)
        if stored is not None:
            return stored
    return gzip.compress(
        app_map_content(db_session, version), compresslevel=APP_MAP_GZIP_LEVEL, mtime=0
    )


def app_map_content(db_session: Session, version: VersionInfo) -> bytes:
    """The app's map file (docs/architecture.md §7) of ``version``, as compact JSON bytes, made
    from its stored map document (``app.domain.formats.derived_documents.app_map_bytes``: what the
    worker stores with a new version)."""
    return app_map_bytes(
        maps.map_document(db_session, version.map_id, version.number),
        path_graph_document(db_session, version.id),
    )


def delete_map_and_jobs(db_session: Session, map_id: int) -> None:
    """Cancel the map's unfinished jobs and delete it with its versions, in the caller's
    transaction; its jobs stay, with no map (``maps.delete_map``). Raises MapNotFound (and the
    caller's rollback undoes the cancel). The map row
    is locked first (``maps.lock_maps``), then its jobs, the order every change of a map and
    every build storing into it takes, so none of them deadlocks with it; a rebuild racing it
    waits for it and then finds no map."""
    maps.lock_maps(db_session, [map_id], for_delete=True)
    if db_session.get(MapRow, map_id) is None:
        raise maps.MapNotFound(map_id)
    maps.delete_map(db_session, map_id)  # cancels the unfinished jobs, keeps them all


def chosen_version(db_session: Session, info: MapInfo, number: int | None) -> VersionInfo:
    """The asked-for version (404 if there is none with that number), or the current one
    (409 while there is none)."""
    if number is not None:
        return maps.get_version(db_session, info.id, number)
    if info.current is not None:
        return info.current
    jobs, _ = queue.list_jobs(db_session, map_id=info.id, limit=1)
    raise map_not_ready(info.id, jobs[0] if jobs else None)


def current_version(state: MapState) -> VersionInfo:
    """The current version of the map ``state`` saw (409 while there is none), no query."""
    if state.info.current is None:
        raise map_not_ready(state.info.id, state.latest_job)
    return state.info.current


def map_not_ready(map_id: int, latest_job: JobInfo | None) -> Conflict:
    """The 409 of a map with no version yet, saying what its newest job is doing."""
    building = (
        f": its build job {latest_job.id} is {latest_job.state}; follow /v1/jobs/{latest_job.id}"
        if latest_job is not None
        else ": rebuild it to make one"
    )
    return Conflict("map_not_ready", f"map {map_id} has no version yet{building}")


# --------------------------------------------------------------------------- per-process memory


@dataclass(frozen=True, slots=True, kw_only=True)
class MapState:
    """A map as one read saw it: the map with its current version and its newest job.
    ``documents``: answers made from exactly this state (the API's map document, as bytes),
    made at most once per state."""

    info: MapInfo
    latest_job: JobInfo | None
    loaded_at_s: float
    change_count: int
    documents: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def settled(self) -> bool:
        """Whether nothing is under way that a worker will change (no job, or it has finished):
        only such a state is kept."""
        return self.latest_job is None or self.latest_job.state in TERMINAL_STATES


def tag_poses_of(cache: VersionCache, db_session: Session, version_id: int) -> list[TagPose]:
    """The tag poses of a version (cached per process: a version never changes)."""
    return cache.get(("tag_poses", version_id), lambda: maps.tag_poses(db_session, version_id))


#: Maps whose state one API process keeps.
MAP_STATES_ENTRIES = 4096
#: Bytes of answers (map documents) kept with those states.
MAP_STATES_BYTES = 64 * 2**20


class MapStates:
    """Per process: what each map's current version and newest job are, for ``ttl_s`` (0: not
    kept). A state is kept only while the map's newest job has finished (a queued or running
    build changes the map from another process at any time, so such maps are read on every
    request); this process's own changes of a map (``app.storage.changes.MAP_CHANGES``) drop
    its state at once; another process's are seen within ``ttl_s``. Unknown maps are not kept.
    Bounded by ``max_entries`` states and ``max_bytes`` of the answers made from them."""

    def __init__(
        self,
        ttl_s: float,
        *,
        max_entries: int = MAP_STATES_ENTRIES,
        max_bytes: int = MAP_STATES_BYTES,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.ttl_s = ttl_s
        self.max_entries = max_entries
        self.max_bytes = max_bytes
        self.clock = clock
        self._states: OrderedDict[int, MapState] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._states)

    @property
    def size_bytes(self) -> int:
        """Bytes of the answers kept with the states now."""
        return self._bytes

    def fresh(self, map_id: int) -> MapState | None:
        """The kept state of ``map_id`` if it is still good, else None (read it: :meth:`load`)."""
        state = self._states.get(map_id)
        if state is None:
            return None
        if (
            self.clock() - state.loaded_at_s >= self.ttl_s
            or MAP_CHANGES.count(map_id) != state.change_count
        ):
            with self._lock:
                if self._states.get(map_id) is state:
                    self._drop(map_id)
            return None
        return state

    def load(self, db: Database, map_id: int) -> MapState:
        """Read the map (MapNotFound if there is none) and its newest job, and keep the state
        if it is settled. (Blocking: call it on a thread.)"""
        change_count = MAP_CHANGES.count(map_id)  # before the read: a change meanwhile wins
        loaded_at_s = self.clock()
        with db.read() as db_session:
            info = maps.get_map(db_session, map_id)
            jobs, _ = queue.list_jobs(db_session, map_id=map_id, limit=1)
        state = MapState(
            info=info,
            latest_job=jobs[0] if jobs else None,
            loaded_at_s=loaded_at_s,
            change_count=change_count,
        )
        if self.ttl_s > 0 and state.settled:
            with self._lock:
                if map_id in self._states:
                    self._drop(map_id)
                self._states[map_id] = state
                self._evict()
        return state

    def attach(self, state: MapState, name: str, document: object) -> None:
        """Keep ``document``, an answer made from exactly ``state``, with it (under ``name``);
        its bytes count against ``max_bytes`` while the state is kept."""
        with self._lock:
            if name in state.documents:
                return
            state.documents[name] = document
            if self._states.get(state.info.id) is state:
                self._bytes += size_in_bytes(document)
                self._evict()

    def _drop(self, map_id: int) -> None:
        state = self._states.pop(map_id)
        self._bytes -= sum(size_in_bytes(document) for document in state.documents.values())

    def _evict(self) -> None:
        while self._states and (
            len(self._states) > self.max_entries or self._bytes > self.max_bytes
        ):
            self._drop(next(iter(self._states)))


#: Pages of the maps list one API process keeps.
MAP_PAGES_ENTRIES = 64


@dataclass(frozen=True, slots=True, kw_only=True)
class _KeptPage:
    content: bytes
    loaded_at_s: float
    change_total: int


class MapPages:
    """Per process: encoded pages of the maps list for ``ttl_s`` (0: not kept), keyed by the
    query; any change of any map in this process drops them all at once (a new map, a rename, a
    rebuild); another process's changes (a worker's new version) are seen within ``ttl_s``."""

    def __init__(
        self,
        ttl_s: float,
        *,
        max_entries: int = MAP_PAGES_ENTRIES,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.ttl_s = ttl_s
        self.max_entries = max_entries
        self.clock = clock
        self._pages: OrderedDict[Hashable, _KeptPage] = OrderedDict()
        self._lock = threading.Lock()

    def fresh(self, query: Hashable) -> bytes | None:
        page = self._pages.get(query)
        if page is None:
            return None
        if self.clock() - page.loaded_at_s >= self.ttl_s or MAP_CHANGES.total != page.change_total:
            return None
        return page.content

    def make(self, query: Hashable, build: Callable[[], bytes]) -> bytes:
        """``build()``'s page, kept for ``query``. (Blocking: call it on a thread.)"""
        change_total = MAP_CHANGES.total
        loaded_at_s = self.clock()
        content = build()
        if self.ttl_s > 0:
            with self._lock:
                self._pages[query] = _KeptPage(
                    content=content, loaded_at_s=loaded_at_s, change_total=change_total
                )
                self._pages.move_to_end(query)
                while len(self._pages) > self.max_entries:
                    self._pages.popitem(last=False)
        return content


@dataclass(frozen=True, slots=True, kw_only=True)
class MapSessionUse:
    """One session of a map: whether the current version was made with it, and what it
    contributed (the version's ``statistics["sessions"]`` entry; None when it has none)."""

    session_id: int
    in_current_version: bool
    contribution: dict[str, Any] | None


def map_session_uses(info: MapInfo) -> list[MapSessionUse]:
    """The sessions a map is made of, in order (the first is the map frame)."""
    used = (info.current.session_ids or [info.session_id]) if info.current else []
    contributions = {
        int(item["session_id"]): item
        for item in (info.current.statistics.get("sessions", []) if info.current else [])
    }
    return [
        MapSessionUse(
            session_id=session_id,
            in_current_version=session_id in used,
            contribution=contributions.get(session_id),
        )
        for session_id in info.session_ids
    ]


def image_url(info: MapInfo) -> str | None:
    """Where the map's picture is served, versioned by its content (so the answer can be cached
    for good: a new picture has a new URL); None without a picture."""
    if info.image_sha256 is None:
        return None
    return f"/v1/maps/{info.id}/image?v={info.image_sha256[:16]}"


def rename_map(db_session: Session, map_id: int, display_name: str) -> MapInfo:
    """Set the name people see (surrounding spaces dropped); 422 naming ``display_name`` if it
    is empty or too long. Raises MapNotFound."""
    name = display_name.strip()
    require_text("display_name", name)
    if not name:
        raise InvalidInput("validation_error", "display_name is empty", field="display_name")
    if len(name) > MAX_DISPLAY_NAME_LENGTH:
        raise InvalidInput(
            "validation_error",
            f"display_name is longer than {MAX_DISPLAY_NAME_LENGTH} characters ({len(name)})",
            field="display_name",
        )
    return maps.set_display_name(db_session, map_id, name)


def store_session_image(
    db_session: Session,
    session_id: int,
    data: bytes,
    *,
    max_bytes: int = images.MAX_IMAGE_BYTES,
) -> StoredImage:
    """Keep ``data`` as the session's picture (the same bytes again change nothing); 422 naming
    the body when it is no JPEG. The caller checks the media type and the size limit first.
    Raises SessionNotFound."""
    problem = images.jpeg_problem(data, max_bytes=max_bytes)
    if problem is not None:
        raise InvalidInput("invalid_image", problem, field="body")
    MAP_CHANGES.note(db_session)  # every map of the session shows the picture's URL
    return images.put_session_image(db_session, session_id=session_id, jpeg=data)


def picture_of_map(db_session: Session, map_id: int) -> MapImage:
    """The map's picture; 404 ``no_image`` while it has none. Raises MapNotFound."""
    picture = images.map_image(db_session, map_id)
    if picture is None:
        raise NotFound(
            "no_image",
            f"map {map_id} has no picture: the app sends one with the "
            "session (PUT /v1/sessions/{session_id}/image)",
        )
    return picture

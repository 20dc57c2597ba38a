"""A building map's incremental side of a build (issue 38), used by
``pipeline.joint.optimize_joint``.

    change, note = incremental_change(db, map_id, walks, params, load_removed, job_id)
    joint = served_joint_map(change.building, change.served, params)   # str: the batch decides
    note += "; " + compared_with_batch(change.served, joint, params)   # "check": the batch's
    state, line = state_of_batch(joint, walks, params, job_id)   # a batch build's state
    save_state(tx, map_id, version_id, state, job_id)           # in the version's transaction

Every batch build of several walks makes the ISAM2 state its next add can start from
(``incremental.from_batch``: no solve) and the store keeps it with the version. With
``Settings.incremental_builds`` a change of one walk is made in the state restored from the
database (``incremental.changes``) and, where the batch build's later steps would change no walk
(``incremental.served_map``), served without a batch solve, the engine's own state stored with
the version; with ``Settings.incremental_check`` too the batch build still runs and is served,
and the job's log says how far the engine's map is from it. None of it fails a build: the state
is an optimization, and a build without one is a batch build.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence

from sqlalchemy.orm import Session as DbSession

from app.config import Settings
from app.domain.errors import InvisibleMapError
from app.domain.mapping.incremental import (
    IncrementalMap,
    IsamBuilding,
    IsamState,
    StaleStateError,
    Walk,
)
from app.domain.mapping.incremental.changes import apply_change, one_walk_change
from app.domain.mapping.incremental.from_batch import state_from_batch, why_not_incremental
from app.domain.mapping.incremental.served_map import served_joint_map
from app.domain.mapping.joint import JointMap
from app.domain.mapping.params import SlamParams
from app.domain.upload.session import Session
from app.storage import isam_states
from app.storage.db import Database, database_fault
from workers.failures import log_failure

logger = logging.getLogger(__name__)

#: How far the incremental map may be from the batch build's, m (issue 38: tags, poses).
INCREMENTAL_TAG_BOUND_M = 0.01
INCREMENTAL_POSE_BOUND_M = 0.05


def mode_of(settings: Settings) -> str:
    """The worker's incremental mode: "off", "serve" (the engine's map served where the checks
    pass) or "check" (the batch build served, the engine's compared with it)."""
    if not settings.incremental_builds:
        return "off"
    return "check" if settings.incremental_check else "serve"


def session_id_of(name: str) -> int | None:
    """The session id of a walk named ``session 12`` (``pipeline.joint.optimize_joint``'s names)."""
    prefix, _, number = name.partition(" ")
    return int(number) if prefix == "session" and number.isdigit() else None


def incremental_change(
    db: Database,
    map_id: int,
    walks: Sequence[Walk],
    params: SlamParams,
    load_session: Callable[[int], Session | None],
    job_id: int,
) -> tuple[tuple[IsamBuilding, IncrementalMap] | None, str]:
    """The build's change made in the ISAM2 state stored with the map's current version
    (``app.storage.isam_states``; restored from the database, so any worker, restarted or not,
    takes this path), when it is one walk added last or taken out and the state is current for
    the others (``incremental.changes.one_walk_change``); and a note for the job's log: what was
    made and how long it took, or why the batch build alone makes the version (None instead
    of the tree and its map). ``load_session``: a stored session by id, None when it is gone
    (a walk taken out: its factors come out of its data). Never fails the build."""
    started_s = time.perf_counter()
    try:
        with db.read() as tx:
            stored = isam_states.current_state(tx, map_id)
        if stored is None:
            return None, "a batch build (the current version has no state)"
        by_id = {walk.walk_id: walk for walk in walks}
        for name in stored.state.walk_ids:
            if name not in by_id and (session_id := session_id_of(name)) is not None:
                session = load_session(session_id)
                if session is not None:  # deleted: not at hand (one_walk_change says so)
                    by_id[name] = Walk(walk_id=name, session=session)
        wanted = [walk.walk_id for walk in walks]
        change = one_walk_change(stored.state, wanted, params, by_id)
        if isinstance(change, str):
            return None, f"a batch build ({change})"
        building, served, timings_ms = apply_change(stored.state, change, params)
    except (InvisibleMapError, StaleStateError) as err:  # AlignmentError among them
        return None, f"a batch build ({type(err).__name__}: {err})"
    except Exception as err:
        log_failure(logger, f"job {job_id}: the incremental change failed", err)
        return None, f"a batch build (failed: {type(err).__name__})"
    return (building, served), (
        f"{change.summary} in version {stored.version_number}'s state, "
        f"{(time.perf_counter() - started_s) * 1e3:.0f} ms (restore "
        f"{timings_ms['restore']:.0f} ms, change {timings_ms['change']:.0f} ms, "
        f"{served.rounds} updates)"
    )


def engine_joint_map(
    building: IsamBuilding, served: IncrementalMap, params: SlamParams, job_id: int
) -> JointMap | str:
    """The engine's map as the ``JointMap`` the later stages read
    (``incremental.served_map``), or why the batch build makes the version instead. Never
    fails the build."""
    try:
        return served_joint_map(building, served, params)
    except Exception as err:
        log_failure(logger, f"job {job_id}: the incremental map could not be served", err)
        return f"the engine's map could not be served ({type(err).__name__})"


def compared_with_batch(served: IncrementalMap, joint: JointMap, params: SlamParams) -> str:
    """How far the incremental map ``served`` is from the batch build ``joint`` of the same
    walks (the largest tag and pose position differences), or why the batch build's graph is
    not the tree's (a walk rescaled or down-weighted, a tag set apart: the incremental map is
    then not the batch map)."""
    why_not = why_not_incremental(joint, params)
    if why_not is not None:
        return f"not the batch map, whose build changed {why_not}"
    try:
        tag_m, pose_m = served.largest_differences_m(joint)
    except ValueError:
        return "not the batch map (other walks or tags)"
    within = tag_m <= INCREMENTAL_TAG_BOUND_M and pose_m <= INCREMENTAL_POSE_BOUND_M
    return (
        f"{tag_m * 1e3:.2f} mm (tags), {pose_m * 1e3:.2f} mm (poses) from the batch map, "
        f"{'within' if within else 'BEYOND'} "
        f"{INCREMENTAL_TAG_BOUND_M * 1e3:.0f} / {INCREMENTAL_POSE_BOUND_M * 1e3:.0f} mm"
    )


def state_of_batch(
    joint: JointMap, walks: Sequence[Walk], params: SlamParams, job_id: int
) -> tuple[IsamState | None, str]:
    """What lets the map's next add be incremental, made from the joint optimum
    (``incremental.from_batch``: no solve, ~2% of the build's time), and the job log's line
    about it. A map the batch build changed beyond the tree's graph (a walk rescaled or
    down-weighted, a tag set apart) gets none, and its next build is a batch build."""
    started_s = time.perf_counter()
    try:
        state, why_not = state_from_batch(joint, list(walks), params)
    except Exception as err:
        log_failure(logger, f"job {job_id}: no incremental state", err)
        state, why_not = None, f"failed ({type(err).__name__})"
    elapsed_ms = (time.perf_counter() - started_s) * 1e3
    if state is not None:
        return state, f"optimize: incremental state made ({elapsed_ms:.0f} ms)"
    return None, f"optimize: no incremental state: {why_not}"


def save_state(tx: DbSession, map_id: int, version_id: int, state: IsamState, job_id: int) -> None:
    """Store the version's incremental state in its transaction, under a savepoint: a state the
    database refuses (not a fault of the database: that fails the whole store, which is tried
    again) leaves the version stored without one, and the map's next build a batch build."""
    try:
        with tx.begin_nested():
            written = isam_states.save_state(
                tx, map_id=map_id, map_version_id=version_id, state=state
            )
    except Exception as err:
        if database_fault(err) is not None:
            raise
        log_failure(logger, f"job {job_id}: the incremental state was not stored", err)
        return
    logger.info(
        "job %d: incremental state of %d walks stored, %.0f kB",
        job_id,
        len(state.walks),
        written / 1e3,
        extra={"action": "isam_state_stored", "job_id": job_id},
    )

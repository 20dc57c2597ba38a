"""A map of several sessions, the joint half of the ``optimize`` stage (:func:`optimize_joint`),
and the warm start from this process's last build of the same map (:func:`warm_start`)."""

from __future__ import annotations

import functools
import hashlib
import logging
import time
from collections.abc import Mapping

import numpy as np

from app.domain.mapping.incremental import Walk
from app.domain.mapping.joint import JointMap, optimize_sessions
from app.domain.mapping.params import SlamParams
from app.domain.upload.session import Session
from app.storage.db import Database
from app.storage.sessions import raw_sha256s
from workers import incremental_builds

from .context import JobContext, PermanentJobError, need
from .loading import PARSED_SESSIONS, load_session_upload, parsed_session_key

#: the package's one logger (its records keep the name they had before the split)
logger = logging.getLogger("workers.pipeline")

#: per worker process, the last joint map built of each of a few maps (most recent last): the
#: next build of the same map starts from it (``optimize_sessions(initial=…)``: the walks it
#: holds are not optimized alone again, LM starts from its optimum; the result is a cold build's
#: to within the convergence tolerance, tested). Another worker's build starts cold.
#: Its walks are known by name ("session 12") and by the fingerprint of their data, so that
#: another database's session 12 (a test's, a restored backup's) is never taken for this one.
LAST_JOINT_MAPS: dict[int, tuple[dict[str, str], JointMap]] = {}
WARM_START_MAPS = 4


def _fingerprint(session: Session) -> str:
    digest = hashlib.blake2b(digest_size=16)
    for array in (session.timestamp_s, session.world_T_phone, session.detections.camera_T_tag):
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


def remember_joint_map(map_id: int, fingerprints: dict[str, str], joint: JointMap) -> None:
    LAST_JOINT_MAPS.pop(map_id, None)
    LAST_JOINT_MAPS[map_id] = (fingerprints, joint)
    while len(LAST_JOINT_MAPS) > WARM_START_MAPS:
        del LAST_JOINT_MAPS[next(iter(LAST_JOINT_MAPS))]


def warm_start(
    map_id: int, fingerprints: Mapping[str, str], params: SlamParams
) -> tuple[JointMap | None, list[str]]:
    """The last joint map this process built of ``map_id`` (taken out of the cache), if the
    next build can start from it, and the walks whose own optimization it reuses. None when a
    walk of the same name holds other data (another database's session 12), or when no walk of
    it was optimized with these parameters (a rebuild with others starts cold)."""
    previous_fingerprints, previous = LAST_JOINT_MAPS.pop(map_id, ({}, None))
    if previous is None or any(
        part.dataset in fingerprints
        and fingerprints[part.dataset] != previous_fingerprints.get(part.dataset)
        for part in previous.parts
    ):
        return None, []
    reused = [
        part.dataset
        for part in previous.parts
        if part.dataset in fingerprints and part.fit is not None and part.fit.alone.params == params
    ]
    return (previous, reused) if reused else (None, [])


def optimize_joint(ctx: JobContext) -> None:
    """Several sessions into one map (``app.domain.mapping.joint``): each walk alone with its
    noise estimated, all placed together, one graph; progress by step, a cancel between LM
    iterations' rounds and walks. A session the others' tags cannot place fails the job with the
    reason (AlignmentError is an InvisibleMapError). With incremental builds, a change of one
    walk is made in the map's stored ISAM2 state and, where the checks pass, served without the
    batch build (``workers.incremental_builds``)."""
    started_s = time.perf_counter()
    names = [f"session {session_id}" for session_id in ctx.session_ids]

    def on_progress(step: str, fraction: float) -> None:
        ctx.report(0.7 * fraction if step == "walks" else 0.7 + 0.3 * fraction)
        ctx.check_interrupted()

    map_id = need(ctx.lease.map_id, "map_id")
    params = need(ctx.params, "params")
    walks = [Walk(walk_id=n, session=s) for n, s in zip(names, ctx.sessions, strict=True)]
    incremental = (
        incremental_builds.incremental_change(
            ctx.db,
            map_id,
            walks,
            params,
            functools.partial(_stored_session, ctx.db),
            ctx.lease.job_id,
        )
        if ctx.incremental_builds != "off"
        else None
    )
    fingerprints = {name: _fingerprint(s) for name, s in zip(names, ctx.sessions, strict=True)}
    change, note = incremental if incremental is not None else (None, "")
    if change is not None and ctx.incremental_builds == "serve":
        building, served = change
        ctx.report(0.7)
        ctx.check_interrupted()
        engine = incremental_builds.engine_joint_map(building, served, params, ctx.lease.job_id)
        if isinstance(engine, JointMap):
            remember_joint_map(map_id, fingerprints, engine)
            _serve(ctx, engine, started_s)
            _log_incremental(ctx, f"{note}; served ({_timings(engine)})")
            ctx.isam_state = building.state()
            ctx.log("optimize: incremental state of the engine kept")
            return
        incremental = change, f"{note}; the batch build decides: {engine}"
    previous, reused = warm_start(map_id, fingerprints, need(ctx.params, "params"))
    if previous is not None:
        ctx.log(
            "optimize: warm start from this worker's last build of the map "
            f"({', '.join(reused)} not optimized alone again)"
        )
    joint = optimize_sessions(
        ctx.sessions,
        need(ctx.params, "params"),
        names=names,
        initial=previous,
        on_progress=on_progress,
    )
    remember_joint_map(map_id, fingerprints, joint)
    _serve(ctx, joint, started_s)
    if incremental is not None:  # after the walks' lines: the log keeps its last lines
        change, note = incremental
        if change is not None and ctx.incremental_builds == "check":
            note = f"{note}; {incremental_builds.compared_with_batch(change[1], joint, params)}"
        _log_incremental(ctx, note)
    ctx.isam_state, line = incremental_builds.state_of_batch(joint, walks, params, ctx.lease.job_id)
    ctx.log(line)


def _serve(ctx: JobContext, joint: JointMap, started_s: float) -> None:
    """``joint`` as the job's map, and its lines in the job's log (the map, then each walk)."""
    ctx.joint, ctx.result, ctx.session = joint, joint.map, joint.combined
    stats = joint.map.stats
    if joint.map.detections_used == 0:
        raise PermanentJobError("every tag detection of every session was rejected")
    ctx.log(
        f"optimize: {len(joint.parts)} sessions, {joint.rounds} rounds, {stats.iterations} "
        f"iterations, error {stats.initial_error:.6g} → {stats.final_error:.6g}, "
        f"{(time.perf_counter() - started_s) * 1e3:.0f} ms ({_timings(joint)})"
    )
    for part in joint.parts:
        ctx.log(
            f"optimize: {part.dataset}: placed by {len(part.alignment.inlier_tags)} of "
            f"{len(part.alignment.shared_tags)} shared tags, {part.detections_used} detections "
            f"used; {part.weighting}"
        )


def _timings(joint: JointMap) -> str:
    return ", ".join(f"{k} {v:.0f} ms" for k, v in joint.timings_ms.items())


def _log_incremental(ctx: JobContext, note: str) -> None:
    ctx.log(f"optimize: incremental: {note}")
    logger.info(
        "job %d: incremental: %s",
        ctx.lease.job_id,
        note,
        extra={"action": "incremental_build", "job_id": ctx.lease.job_id},
    )


def _stored_session(db: Database, session_id: int) -> Session | None:
    """A stored session by id, None when it is gone (a walk taken out of a building map): from
    this process's cache of parsed walks when it holds it (``loading.PARSED_SESSIONS``)."""
    with db.read() as tx:
        digest = raw_sha256s(tx, [session_id]).get(session_id)
    if digest is None:
        return None
    if (kept := PARSED_SESSIONS.get(parsed_session_key(db, session_id, digest))) is not None:
        return kept
    try:
        return load_session_upload(db, session_id)[1]
    except PermanentJobError:
        return None

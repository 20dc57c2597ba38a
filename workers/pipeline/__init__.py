"""Jobs as lists of stages, and the runner that carries one out under a lease.

    stages = PIPELINES["build_map"]     # load → tune → optimize → evaluate → path_graph → store
    report = run_job(db, lease, stages=stages, control=JobControl(), retry_backoff_s=2.0)
    report.outcome                            # Outcome.SUCCEEDED, FAILED, RETRYING, …

A :class:`Stage` is a name, a weight (its share of the progress bar) and a function of the
:class:`JobContext`, which carries the job's inputs and what earlier stages produced. To extend a
job, add a stage (and, if it produces something, a field of the context); the last stage must end
the job with ``queue.finish`` in the transaction that stores its result (see :func:`store`).

Between stages the runner writes the stage and the overall progress (``queue.report_progress``,
which also returns whether a cancel was requested) and carries out what was asked meanwhile:
a cancel (``queue.mark_canceled``), a release by a worker shutting down (``queue.release``), or a
lost lease (abandon: write nothing). Errors decide between retrying and failing:

- :class:`~app.domain.errors.InvisibleMapError` (the core refusing its input: a malformed upload,
  a bad parameter) and :class:`PermanentJobError` (a missing or corrupt stored input) can never
  succeed, so the job fails at once with the error's message;
- any other ``Exception`` (out of memory, a bug, the database unreachable for longer than the
  lease) is transient: the job is queued again after a back-off that doubles per attempt, until
  ``max_attempts``.

A database outage shorter than the lease does not cost the attempt: a stage or a job-state write
that fails with a database fault (``app.storage.db.database_fault``: unreachable, restarting,
full, read-only) is tried again, waiting 0.5 s, 1 s, 2 s, 4 s, 4 s … while the lease holds
(``JobControl.lease_deadline_s``, kept by the heartbeat thread). Stages are idempotent (``store``
commits all or nothing and is fenced), so trying one again is safe; and once the database is back
the job carries on where it was, in the same attempt, and runs once.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import hashlib
import json
import logging
import math
import sys
import time
import zlib
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
from sqlalchemy.exc import DataError
from sqlalchemy.orm import Session as DbSession

from app.domain.errors import InvisibleMapError
from app.domain.evaluation.ground_truth import parse_ground_truth_json
from app.domain.evaluation.metrics import joint_shift_metric, shift_metric
from app.domain.evaluation.sweep_plan import SweepPlan
from app.domain.evaluation.table import Evaluation, compare_walk, evaluate_map
from app.domain.evaluation.tuning import SearchSpace, Trial, TuningTarget, best_trial
from app.domain.formats.derived_documents import APP_MAP_EXPORT, packed_documents
from app.domain.formats.map_io import map_from_json, map_to_app_format, map_to_json
from app.domain.frames import FloatArray
from app.domain.json_values import finite_or_none
from app.domain.mapping.incremental import IsamState, Walk
from app.domain.mapping.joint import JointMap, optimize_sessions
from app.domain.mapping.map_result import MapResult
from app.domain.mapping.noise import COMPONENTS
from app.domain.mapping.params import SlamParams
from app.domain.mapping.slam import optimize_session
from app.domain.navigation.path_graph import (
    ELEVATOR,
    JUNCTION,
    STAIRS,
    path_graph_from_json,
    path_graph_to_json,
)
from app.domain.navigation.skeleton import build_skeleton
from app.domain.upload.json_stream import gunzipped
from app.domain.upload.session import Session, parse_session_stream, require_tags
from app.render.map_plot import render_map_png
from app.storage import blobs, maps, queue
from app.storage.db import Database, database_fault, first_line
from app.storage.maps import VersionInfo
from app.storage.orm import JobState
from app.storage.queue import Lease, LeaseLost
from app.storage.sessions import (
    AUTO_TUNE_TRIALS,
    BUILD_MAP,
    GROUND_TRUTH,
    SESSION_IDS,
    STORED_PIECE_BYTES,
    SessionNotFound,
    raw_upload_gzip_pieces,
)
from workers import incremental_builds
from workers.failures import log_failure
from workers.lease import JobControl

logger = logging.getLogger(__name__)

#: Least time between two progress writes from inside a stage, s (at most ~4 writes/s).
PROGRESS_INTERVAL_S = 0.25
#: First and longest wait before trying a stage or a job-state write again while the database is
#: unavailable, s (the wait doubles in between).
OUTAGE_FIRST_WAIT_S = 0.5
OUTAGE_MAX_WAIT_S = 4.0

T = TypeVar("T")


class PermanentJobError(Exception):
    """Raised by a stage when the job can never succeed as given (an input is missing or
    corrupt in storage); the job fails at once instead of being retried."""


class Interrupted(Exception):
    """Raised inside a stage (:meth:`JobContext.check_interrupted`, from an optimizer's iteration
    callback or between trials) when a cancel or a release was asked: the runner then cancels or
    releases the job at once instead of at the next stage boundary."""


class Outcome(enum.StrEnum):
    """How one attempt at a job ended (what the runner wrote to the job row)."""

    #: the result is stored and the job is ``succeeded``
    SUCCEEDED = "succeeded"
    #: the map changed while it was built: the result is not stored and the job is ``canceled``
    SUPERSEDED = "superseded"
    #: a transient error; the job is ``queued`` again, after a back-off
    RETRYING = "retrying"
    #: a permanent error, or the last attempt's transient one; the job is ``failed``
    FAILED = "failed"
    #: a cancel was requested; the job is ``canceled``
    CANCELED = "canceled"
    #: the worker is shutting down; the job is ``queued`` again, the attempt not counted
    RELEASED = "released"
    #: the lease was lost; nothing was written (another worker may be running the job)
    LEASE_LOST = "lease_lost"


@dataclass(frozen=True, slots=True, kw_only=True)
class JobReport:
    """The outcome of one attempt, for the worker's log."""

    outcome: Outcome
    error: str | None = None
    version: VersionInfo | None = None
    duration_s: float = 0.0
    #: each stage that ran to its end in this attempt, in order: (name, duration in s)
    stage_durations_s: tuple[tuple[str, float], ...] = ()


@dataclass(slots=True, kw_only=True)
class JobContext:
    """A job's inputs, what its stages produced so far, and how a stage reports progress.

    Stages read and fill the fields in order: ``load`` sets ``params`` and ``session``;
    ``optimize`` sets ``result``; ``evaluate`` sets ``evaluation`` and ``plot_png``;
    ``path_graph`` sets ``path_graph``; ``store`` sets ``version`` and ``finished``.
    ``log_tail`` is the job's log as the worker will next write it (started from
    ``lease.log_tail``); add to it with :meth:`log`.
    """

    db: Database
    lease: Lease
    control: JobControl
    log_tail: str
    params: SlamParams | None = None
    session: Session | None = None
    result: MapResult | None = None
    evaluation: Evaluation | None = None
    plot_png: bytes | None = None
    #: ``app.domain.navigation.path_graph.path_graph_to_json`` of the map's path graph
    path_graph: dict[str, Any] | None = None
    #: the sessions the map is built from, in order (``SESSION_IDS``; else the job's one)
    session_ids: list[int] = field(default_factory=list)
    #: each of them parsed, when there are several (``session`` is then their joint session)
    sessions: list[Session] = field(default_factory=list)
    #: the joint optimization of several sessions (``app.domain.mapping.joint``)
    joint: JointMap | None = None
    #: what makes the next add to this building map incremental (issue 38), made from the
    #: joint optimum; stored with the version (``app.storage.isam_states``); None when the
    #: batch graph is not the tree's (``incremental.from_batch``)
    isam_state: IsamState | None = None
    #: ``Settings.incremental_builds``: a change of one walk is made in the stored state too
    #: (``workers.incremental_builds``) and checked against the batch build
    incremental_builds: bool = False
    #: build_map with ``auto_tune_trials``: sampler trials by the shift metric before optimizing
    auto_tune_trials: int = 0
    #: build_map with ``ground_truth``: tag id → world_T_tag, for the ground-truth metric
    ground_truth: dict[int, FloatArray] | None = None
    #: sweep_trials jobs (``workers/sweep.py``): the prepared session and the finished trials
    tuning_target: TuningTarget | None = None
    trials: list[Trial] | None = None
    version: VersionInfo | None = None
    #: the map's generation the build was queued for (``lease.map_generation``): its version is
    #: stored only while it is still the map's (:func:`store`)
    map_generation: int = 0
    #: set by the stage that committed the job as succeeded (``queue.finish``), or as
    #: superseded (``superseded`` then)
    finished: bool = False
    superseded: bool = False
    stage: str = ""
    stage_start: float = 0.0
    stage_weight: float = 0.0
    _last_write_s: float = field(default=-math.inf, repr=False)
    #: time.monotonic() after which the attempt fails (``Settings.job_time_budget_s``)
    deadline_s: float = math.inf
    time_budget_s: float = 0.0

    def begin_stage(self, name: str, *, start: float, weight: float) -> None:
        """Set the stage that :meth:`report` reports within (its first report is always
        written): it starts at overall progress ``start`` and spans ``weight`` of it."""
        self.stage, self.stage_start, self.stage_weight = name, start, weight
        self._last_write_s = -math.inf

    def log(self, message: str) -> None:
        """Add a timestamped line to the job's log tail (written with the next progress write)."""
        self.log_tail = queue.append_log(self.log_tail, message)

    def check_interrupted(self) -> None:
        """Stop the stage now if the job must stop: :class:`Interrupted` for a cancel or a
        release, LeaseLost for a lost lease, PermanentJobError past the time budget. Stages call
        it where they can stop safely (each optimizer iteration, each trial): a cancel then
        takes effect within a heartbeat (``heartbeat_s``) and one iteration."""
        control = self.control
        if control.lease_lost:
            raise LeaseLost(self.lease.job_id)
        if control.cancel_requested or control.release_requested:
            raise Interrupted(self.stage)
        if time.monotonic() > self.deadline_s:
            raise PermanentJobError(
                f"the job ran longer than its time budget of {self.time_budget_s:g} s "
                "(INVISIBLE_MAP_JOB_TIME_BUDGET_S)"
            )

    def on_trial_iteration(self, _iteration: int, _error: float) -> None:
        """The iteration callback of a tuning or sweep trial (``TuningTarget.run``): a cancel
        stops the trial within one Levenberg–Marquardt iteration, not after the trial."""
        self.check_interrupted()

    def report(self, fraction_within_stage: float, message: str | None = None) -> None:
        """Report progress within the current stage (0–1), and optionally log ``message``.

        Writes at most every :data:`PROGRESS_INTERVAL_S` (the first report of a stage always);
        never raises. A cancel request it sees
        is recorded in ``control`` (carried out at the next stage boundary), as is a lost lease.
        """
        if message is not None:
            self.log(message)
        now_s = time.monotonic()
        if now_s - self._last_write_s < PROGRESS_INTERVAL_S or self.control.lease_lost:
            return
        self._last_write_s = now_s
        fraction = min(max(fraction_within_stage, 0.0), 1.0)
        try:
            if queue.report_progress(
                self.db,
                self.lease,
                progress=self.stage_start + self.stage_weight * fraction,
                stage=self.stage,
                log_tail=self.log_tail,
            ):
                self.control.cancel_requested = True
        except LeaseLost:
            self.control.lease_lost = True
        except Exception as err:
            log_failure(logger, f"job {self.lease.job_id}: progress write failed", err)


@dataclass(frozen=True, slots=True, kw_only=True)
class Stage:
    """One step of a job: ``run(context)`` does the work; ``weight`` is its share of progress."""

    name: str
    weight: float
    run: Callable[[JobContext], None]


def _need(value: T | None, what: str) -> T:
    if value is None:
        raise RuntimeError(f"pipeline order: {what} is not set by an earlier stage")
    return value


# --------------------------------------------------------------------------- build_map stages


def load(ctx: JobContext) -> None:
    """Check the parameters, read the session's raw upload and parse it."""
    lease = ctx.lease
    if lease.session_id is None or lease.map_id is None:
        raise PermanentJobError(f"a {lease.kind} job needs a session and a map")
    overrides = dict(lease.params)
    ctx.map_generation = lease.map_generation
    ctx.auto_tune_trials = _auto_tune_trials(overrides.pop(AUTO_TUNE_TRIALS, 0))
    ctx.session_ids = _session_ids(overrides.pop(SESSION_IDS, None), lease.session_id)
    if (ground_truth := overrides.pop(GROUND_TRUTH, None)) is not None:
        ctx.ground_truth = parse_ground_truth_json(ground_truth)  # checked by the API already
    ctx.params = SlamParams().with_overrides(overrides)
    if len(ctx.session_ids) > 1:
        if ctx.auto_tune_trials:
            raise PermanentJobError(f"{AUTO_TUNE_TRIALS} is for maps of one session")
        for session_id in ctx.session_ids:
            size_bytes, session = load_session_upload(ctx.db, session_id)
            ctx.sessions.append(session)
            ctx.log(
                f"load: session {session_id}: {session.num_poses} poses, "
                f"{len(session.detections)} detections of {len(session.tag_ids)} tags, "
                f"{size_bytes / 1e6:.2f} MB"
            )
        return
    size_bytes, ctx.session = load_session_upload(ctx.db, lease.session_id)
    session = ctx.session
    require_tags(session)  # before any tuning: a walk with no tag makes no map
    ctx.log(
        f"load: {session.num_poses} poses, {len(session.detections)} detections of "
        f"{len(session.tag_ids)} tags, {size_bytes / 1e6:.2f} MB"
    )


def _session_ids(value: Any, session_id: int) -> list[int]:
    if value is None:
        return [session_id]
    if (
        not isinstance(value, list)
        or not value
        or not all(isinstance(v, int) and not isinstance(v, bool) for v in value)
        or len(set(value)) != len(value)
    ):
        raise PermanentJobError(
            f"{SESSION_IDS} must be a list of distinct session ids, got {value!r}"
        )
    return list(value)


def _auto_tune_trials(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 1000:
        raise PermanentJobError(f"{AUTO_TUNE_TRIALS} must be an integer 0–1000, got {value!r}")
    return value


def tune(ctx: JobContext) -> None:
    """With ``auto_tune_trials`` N > 0: choose the noise variances by the shift metric (Optuna's
    sampler, N trials over the paper grid's box, warm-started) before the final optimization."""
    if ctx.auto_tune_trials <= 0:
        return
    session, params = _need(ctx.session, "session"), _need(ctx.params, "params")
    target = TuningTarget.prepare(session, params)
    plan = SweepPlan(method="sampler", space=SearchSpace.paper_grid(), trials=ctx.auto_tune_trials)
    trials: list[Trial] = []
    while batch := plan.next_batch(trials, len(trials)):
        for values in batch:
            ctx.check_interrupted()
            trials.append(target.run(values, on_iteration=ctx.on_trial_iteration))
            ctx.report(len(trials) / plan.total)
    best = best_trial(trials, "shift")
    if best is None:
        ctx.log(f"tune: no trial of {len(trials)} converged; keeping the parameters")
        return
    ctx.params = params.with_overrides(best.values)
    shift_pre = target.baseline()[0]
    ctx.log(
        f"tune: {len(trials)} trials, shift {shift_pre:.4g} (pre-optimized) → {best.shift:.4g} "
        f"with {', '.join(f'{k}={v:.3g}' for k, v in best.values.items())}"
    )


def load_session_upload(db: Database, session_id: int) -> tuple[int, Session]:
    """A session's stored upload parsed as it is read from the database a piece at a time and
    inflated (``parse_session_stream``: never the whole JSON, nor its object graph, in memory);
    its size (bytes of JSON) and the parse. PermanentJobError if missing or corrupt."""
    inflated: list[int] = []
    try:
        with db.read() as tx:
            session = parse_session_stream(
                _counted(
                    gunzipped(
                        raw_upload_gzip_pieces(tx, session_id, STORED_PIECE_BYTES),
                        STORED_PIECE_BYTES,
                        complete=True,
                    ),
                    inflated,
                ),
                max_poses=sys.maxsize,  # accepted once, within the limit there was then
                source=f"stored upload of session {session_id}",
            )
    except SessionNotFound as err:
        raise PermanentJobError(f"the raw upload of session {session_id} is missing") from err
    except (EOFError, zlib.error) as err:
        raise PermanentJobError(
            f"the stored upload of session {session_id} is corrupt (not valid gzip: {err})"
        ) from err
    return sum(inflated), session


def _counted(pieces: Iterable[bytes], lengths: list[int]) -> Iterator[bytes]:
    """``pieces``, each one's length appended to ``lengths`` as it passes."""
    for piece in pieces:
        lengths.append(len(piece))
        yield piece


def optimize(ctx: JobContext) -> None:
    """Graph SLAM; progress per Levenberg–Marquardt iteration (an estimate: LM stops early)."""
    if ctx.sessions:
        _optimize_joint(ctx)
        return
    session = _need(ctx.session, "session")

    def on_iteration(iteration: int, _error: float) -> None:
        ctx.report(1.0 - 0.6**iteration)
        ctx.check_interrupted()  # a cancel stops the optimization here, not after it

    started_s = time.perf_counter()
    ctx.result = optimize_session(session, _need(ctx.params, "params"), on_iteration=on_iteration)
    stats = ctx.result.stats
    if len(session.detections) > 0 and ctx.result.detections_used == 0:
        counts = ", ".join(f"{n} {why}" for why, n in sorted(ctx.result.rejection_counts().items()))
        raise PermanentJobError(
            f"every one of the session's {len(session.detections)} tag detections was rejected "
            f"({counts}): the map would have no tags; loosen the screening parameters"
        )
    noise = ctx.result.noise
    estimated = ""
    if noise is not None:  # one line per stage: the walk's noise goes on the optimize line
        variances = noise.variances(_need(ctx.params, "params"))
        estimated = (
            f"; noise from the walk's residuals ({noise.rounds} rounds): odometry "
            f"{variances.odom_linear_var_m2_per_s:.3g} m²/s and "
            f"{variances.odom_angular_var_rad2_per_s:.3g} rad²/s, tags "
            f"{variances.tag_position_var_m2:.3g} m² at 1 m and "
            f"{variances.tag_orientation_var_rad2:.3g} rad²"
            + (f" ({noise.note})" if noise.note else "")
        )
    ctx.log(
        f"optimize: {stats.iterations} iterations, error {stats.initial_error:.6g} → "
        f"{stats.final_error:.6g}, {len(ctx.result.rejections)} detections rejected, "
        f"{(time.perf_counter() - started_s) * 1e3:.0f} ms{estimated}"
    )


#: per worker process, the last joint map built of each of a few maps (most recent last): the
#: next build of the same map starts from it (``optimize_sessions(initial=…)``: the walks it
#: holds are not optimized alone again, LM starts from its optimum; the result is a cold build's
#: to within the convergence tolerance, tested). Another worker's build starts cold.
#: Its walks are known by name ("session 12") and by the fingerprint of their data, so that
#: another database's session 12 (a test's, a restored backup's) is never taken for this one.
_LAST_JOINT_MAPS: dict[int, tuple[dict[str, str], JointMap]] = {}
WARM_START_MAPS = 4


def _fingerprint(session: Session) -> str:
    digest = hashlib.blake2b(digest_size=16)
    for array in (session.timestamp_s, session.world_T_phone, session.detections.camera_T_tag):
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()


def _remember_joint_map(map_id: int, fingerprints: dict[str, str], joint: JointMap) -> None:
    _LAST_JOINT_MAPS.pop(map_id, None)
    _LAST_JOINT_MAPS[map_id] = (fingerprints, joint)
    while len(_LAST_JOINT_MAPS) > WARM_START_MAPS:
        del _LAST_JOINT_MAPS[next(iter(_LAST_JOINT_MAPS))]


def warm_start(
    map_id: int, fingerprints: Mapping[str, str], params: SlamParams
) -> tuple[JointMap | None, list[str]]:
    """The last joint map this process built of ``map_id`` (taken out of the cache), if the
    next build can start from it, and the walks whose own optimization it reuses. None when a
    walk of the same name holds other data (another database's session 12), or when no walk of
    it was optimized with these parameters (a rebuild with others starts cold)."""
    previous_fingerprints, previous = _LAST_JOINT_MAPS.pop(map_id, ({}, None))
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


def _optimize_joint(ctx: JobContext) -> None:
    """Several sessions into one map (``app.domain.mapping.joint``): each walk alone with its
    noise estimated, all placed together, one graph; progress by step, a cancel between LM
    iterations' rounds and walks. A session the others' tags cannot place fails the job with the
    reason (AlignmentError is an InvisibleMapError)."""
    started_s = time.perf_counter()
    names = [f"session {session_id}" for session_id in ctx.session_ids]

    def on_progress(step: str, fraction: float) -> None:
        ctx.report(0.7 * fraction if step == "walks" else 0.7 + 0.3 * fraction)
        ctx.check_interrupted()

    map_id = _need(ctx.lease.map_id, "map_id")
    params = _need(ctx.params, "params")
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
        if ctx.incremental_builds
        else None
    )
    fingerprints = {name: _fingerprint(s) for name, s in zip(names, ctx.sessions, strict=True)}
    previous, reused = warm_start(map_id, fingerprints, _need(ctx.params, "params"))
    if previous is not None:
        ctx.log(
            "optimize: warm start from this worker's last build of the map "
            f"({', '.join(reused)} not optimized alone again)"
        )
    joint = optimize_sessions(
        ctx.sessions,
        _need(ctx.params, "params"),
        names=names,
        initial=previous,
        on_progress=on_progress,
    )
    _remember_joint_map(map_id, fingerprints, joint)
    ctx.joint, ctx.result, ctx.session = joint, joint.map, joint.combined
    stats = joint.map.stats
    if joint.map.detections_used == 0:
        raise PermanentJobError("every tag detection of every session was rejected")
    timings = ", ".join(f"{k} {v:.0f} ms" for k, v in joint.timings_ms.items())
    ctx.log(
        f"optimize: {len(ctx.sessions)} sessions, {joint.rounds} rounds, {stats.iterations} "
        f"iterations, error {stats.initial_error:.6g} → {stats.final_error:.6g}, "
        f"{(time.perf_counter() - started_s) * 1e3:.0f} ms ({timings})"
    )
    for part in joint.parts:
        ctx.log(
            f"optimize: {part.dataset}: placed by {len(part.alignment.inlier_tags)} of "
            f"{len(part.alignment.shared_tags)} shared tags, {part.detections_used} detections "
            f"used; {part.weighting}"
        )
    if incremental is not None:  # after the walks' lines: the log keeps its last lines
        served, note = incremental
        if served is not None:
            note = f"{note}; {incremental_builds.compared_with_batch(served, joint, params)}"
        ctx.log(f"optimize: incremental: {note}")
        logger.info(
            "job %d: incremental: %s",
            ctx.lease.job_id,
            note,
            extra={"action": "incremental_build", "job_id": ctx.lease.job_id},
        )
    ctx.isam_state, line = incremental_builds.state_of_batch(joint, walks, params, ctx.lease.job_id)
    ctx.log(line)


def _stored_session(db: Database, session_id: int) -> Session | None:
    """A stored session by id, None when it is gone (a walk taken out of a building map)."""
    try:
        return load_session_upload(db, session_id)[1]
    except PermanentJobError:
        return None


def _session_contributions(ctx: JobContext) -> list[dict[str, Any]] | None:
    """What each session of a joint map contributed (a version's ``statistics["sessions"]``):
    its share of the map, what it weighs and why (its noise estimated alone, the factor joining
    raised its variances by, its odometry scale), and how its own map alone compares with the
    building map on all its tags, its shared ones and its own ones (how far joining moved them
    after a rigid fit, and the shift metric over its own sightings: no ground truth here)."""
    joint = ctx.joint
    if joint is None:
        return None
    params = _need(ctx.params, "params")
    out = []
    for session_id, part, session, mask in zip(
        ctx.session_ids, joint.parts, joint.sessions, joint.session_masks(), strict=True
    ):
        report = compare_walk(joint, part, part.alone) if part.alone is not None else None
        out.append(
            {
                "session_id": session_id,
                "poses": part.pose_rows.stop - part.pose_rows.start,
                "first_pose_row": part.pose_rows.start,
                "tags": list(part.tag_ids),
                "detections_used": part.detections_used,
                "detections_rejected": part.detections_rejected,
                "tag_chi2_mean": None if math.isnan(part.tag_chi2_mean) else part.tag_chi2_mean,
                "shared_tags": list(part.alignment.shared_tags),
                "placed_by_tags": list(part.alignment.inlier_tags),
                "own_landmark_tags": list(part.local_tags),
                "odometry_variance_scale": part.odometry_variance_scale,
                "tag_depth_scale": part.tag_depth_scale,
                "yaw_rad": part.alignment.yaw_rad,
                "odometry_scale": part.alignment.odometry_scale,
                "noise": None if part.noise is None else part.noise.to_dict(params),
                "noise_scales": dict(zip(COMPONENTS, part.noise_scales.tolist(), strict=True)),
                "disagreement_factor": part.disagreement_factor,
                "cost_alone": finite_or_none(part.cost_alone),
                "cost_joint": finite_or_none(part.cost_joint),
                "redundancy_gain": part.redundancy_gain,
                "weighting": part.weighting,
                "alone_vs_joint": None
                if report is None or part.alone is None
                else {
                    "all": report.all_tags.to_dict(),
                    "shared": report.shared.to_dict(),
                    "own": report.own.to_dict(),
                    "shift_alone": finite_or_none(
                        shift_metric(session, part.alone.tag_poses(), detection_mask=mask)
                    ),
                    "shift_joint": finite_or_none(
                        shift_metric(session, joint.map.tag_poses(), detection_mask=mask)
                    ),
                },
            }
        )
    return out


def evaluate(ctx: JobContext) -> None:
    """Shift metric, the ground-truth metric when the job has ground truth, and the top-down
    plot."""
    session = _need(ctx.session, "session")
    result = _need(ctx.result, "result")
    ctx.evaluation = evaluate_map(session, result, ctx.ground_truth)
    if ctx.joint is not None:  # the shift metric over each session's own detections
        ctx.evaluation = dataclasses.replace(
            ctx.evaluation,
            shift_pre=joint_shift_metric(ctx.joint, result.tag_poses_pre()),
            shift_opt=joint_shift_metric(ctx.joint),
        )
    ctx.report(0.5)
    try:
        ctx.plot_png = render_map_png(result, session)
    except Exception as err:  # a plot is a picture of the map: the map is built without one
        logger.warning("job %d: the plot failed", ctx.lease.job_id, exc_info=True)
        ctx.log(f"evaluate: no plot ({type(err).__name__}); the map is stored without one")
        ctx.plot_png = None
    evaluation = ctx.evaluation
    truth = (
        f"ground-truth metric {evaluation.gt_metric_opt:.4g} "
        f"(pre-optimized {evaluation.gt_metric_pre:.4g}, "
        f"{evaluation.tags_with_ground_truth} tags), "
        if ctx.ground_truth is not None
        else ""
    )
    ctx.log(
        f"evaluate: shift metric {evaluation.shift_opt:.4g} "
        f"(pre-optimized {evaluation.shift_pre:.4g}), {truth}"
        + (f"plot {len(ctx.plot_png) / 1e3:.0f} kB" if ctx.plot_png is not None else "no plot")
    )


def path_graph(ctx: JobContext) -> None:
    """Where a pedestrian can walk: the corridor skeleton of the optimized path (passes merged
    into centrelines, junctions where corridors branch), floors, stairs and elevators, and the
    tags and points of interest attached to it (app.domain.navigation.skeleton). A map of several
    sessions gets one skeleton fused from all its walks (issue 26).
    """
    result = _need(ctx.result, "result")
    walk_starts = [0] if ctx.joint is None else [p.pose_rows.start for p in ctx.joint.parts]
    graph = build_skeleton(result, walk_starts=walk_starts)
    ctx.path_graph = path_graph_to_json(graph)
    # what the app-map had to adjust (a walk that falls apart, repeated names) is the map's news
    notes = map_to_app_format(result, path_graph=graph)["notes"]
    if notes:
        ctx.result = dataclasses.replace(
            result, warnings=(*result.warnings, *(f"app map: {note}" for note in notes))
        )
        for note in notes:
            ctx.log(f"app map: {note}")
    walk = graph.graph
    kinds = Counter(walk.edges[u, v]["kind"] for u, v in walk.edges)
    junctions = sum(1 for node in walk.nodes if walk.nodes[node]["kind"] == JUNCTION)
    ctx.log(
        f"path graph: corridor skeleton{_fused_from(len(walk_starts))}, "
        f"{walk.number_of_nodes()} nodes ({junctions} junctions), "
        f"{walk.number_of_edges()} edges ({kinds[STAIRS]} stairs, {kinds[ELEVATOR]} "
        f"elevator), {len(graph.floor_levels_m)} floor(s)"
    )


def _fused_from(walks: int) -> str:
    return f" fused from {walks} walks" if walks > 1 else " of 1 walk"


def derived_documents(ctx: JobContext, document: dict[str, Any]) -> maps.DerivedDocuments:
    """What the API would otherwise make of the stored version on every process's first request
    (issue 19, finding 3), made once here from the version as stored (its map document read
    back, the path graph through JSON) so that it equals what the API makes: the app's map file
    (``app.domain.formats.derived_documents.app_map_bytes``) and the dashboard's overview.
    ``document``: the version's map document (``map_to_json`` of the result)."""
    stored = map_from_json(document)  # JSON keeps its floats exactly: no round trip needed
    graph = (
        None
        if ctx.path_graph is None
        else path_graph_from_json(json.loads(json.dumps(ctx.path_graph, allow_nan=False)))
    )
    app_map_gzip, overview_gzip = packed_documents(
        stored,
        ctx.session if ctx.joint is None else None,
        graph,
        sessions=_session_contributions(ctx) or [],
    )
    return maps.DerivedDocuments(
        app_map_gzip=app_map_gzip, app_map_export=APP_MAP_EXPORT, overview_gzip=overview_gzip
    )


def store(ctx: JobContext) -> None:
    """Write the version's bulk data (map document, plot, path graph) and what is derived from
    it (:func:`derived_documents`) as blobs, each chunk in a small transaction of its own;
    then, in ONE small transaction: end the job as succeeded (fenced: raises LeaseLost, and the
    transaction rolls back, if the lease is gone) and add the map version that refers to the
    blobs. So the build's write lock (SQLite's only one) is held
    for milliseconds, not for the seconds the bulk data takes (issue 19, finding 4). Afterwards,
    blobs nobody refers to for an hour (a failed attempt's, a deleted map's) are collected.

    The version is stored only if the map is still at the generation the build was queued for
    (``maps.generation_for_store``, under the map's lock, first thing in that transaction); a
    build overtaken by a change of the map is superseded instead (:func:`_supersede`), and if
    that is already known before the bulk data is written, none is written."""
    session = _need(ctx.session, "session")
    result = _need(ctx.result, "result")
    map_id = _need(ctx.lease.map_id, "map_id")
    with ctx.db.read() as tx:  # overtaken already: write no bulk data for nothing
        seen = maps.map_generation(tx, map_id)
    if seen is not None and seen != ctx.map_generation:
        with ctx.db.transaction() as tx:
            generation = maps.generation_for_store(tx, map_id)
            if generation is not None and generation != ctx.map_generation:
                _supersede(ctx, tx, map_id, generation)
                return
    document = map_to_json(result)
    derived: maps.DerivedDocuments | None
    try:
        derived = derived_documents(ctx, document)
    except Exception as err:  # what the API would make: it makes it then, as for older versions
        logger.warning("job %d: the derived documents failed", ctx.lease.job_id, exc_info=True)
        derived, made = None, f"no app-map or overview stored ({type(err).__name__})"
    else:
        made = (
            f"app-map {len(derived.app_map_gzip) / 1e3:.0f} kB, "
            f"overview {len(derived.overview_gzip) / 1e3:.0f} kB (gzip)"
        )
    ctx.log(f"store: map {map_id}, {len(result.tag_ids)} tags, {session.num_poses} poses; {made}")
    bulk = maps.write_version_bulk(
        ctx.db,
        result=result,
        document=document,
        plot_png=ctx.plot_png,
        path_graph=ctx.path_graph,
        derived=derived,
    )
    ctx.report(0.9)
    with ctx.db.transaction() as tx:
        # the map first, then the job: the order every change of the map takes
        now = maps.generation_for_store(tx, map_id)
        if now is not None and now != ctx.map_generation:
            _supersede(ctx, tx, map_id, now)
            return
        queue.finish(tx, ctx.lease, log_tail=ctx.log_tail)
        ctx.version = maps.store_version(
            tx,
            map_id=map_id,
            job_id=ctx.lease.job_id,
            result=result,
            evaluation=_need(ctx.evaluation, "evaluation"),
            path_length_m=(
                sum(s.path_length_m() for s in ctx.sessions)
                if ctx.sessions
                else session.path_length_m()
            ),
            session_ids=ctx.session_ids,
            sessions=_session_contributions(ctx),
            bulk=bulk,
            generation=ctx.map_generation,
        )
        if ctx.isam_state is not None:  # in the version's transaction: never one without it
            incremental_builds.save_state(
                tx, map_id, ctx.version.id, ctx.isam_state, ctx.lease.job_id
            )
    ctx.finished = True
    try:
        collected = blobs.collect_orphan_blobs(ctx.db)
    except Exception as err:  # the map is stored; the orphans wait for the next build
        log_failure(logger, f"job {ctx.lease.job_id}: collecting orphan blobs failed", err)
    else:
        if collected:
            logger.info("job %d: %d orphan blobs collected", ctx.lease.job_id, collected)


def _supersede(ctx: JobContext, tx: DbSession, map_id: int, generation: int) -> None:
    """End the build without storing its version: map ``map_id`` changed while it was built
    (its generation is ``generation`` now, the build's ``ctx.map_generation``), so its result is
    not of the map's current sessions and parameters. (Dropped, not kept as a version: the
    newest version is the current one everywhere — the API, the app-map, localization — and a
    version of an old set can be made again by a rebuild with its ``session_ids``.) The build of
    the current generation is the change's own job; only if there is none at all (nothing else
    makes one) is one queued here, from the map's sessions with this build's parameters."""
    jobs = [
        job
        for job in queue.jobs_of_map(tx, map_id, kind=BUILD_MAP)
        if (job.map_generation or 0) == generation
    ]
    if jobs:
        follow_up = jobs[-1]
        builds = f"job {follow_up.id} ({follow_up.state}) builds"
    else:
        overrides = {
            name: value
            for name, value in ctx.lease.params.items()
            if name not in (SESSION_IDS, AUTO_TUNE_TRIALS)
        }
        ids = maps.map_session_ids(tx, map_id)
        params = dict(overrides)
        if len(ids) > 1:
            params[SESSION_IDS] = ids
        job_id = queue.enqueue(
            tx,
            kind=BUILD_MAP,
            map_id=map_id,
            session_id=ids[0],
            params=params,
            max_attempts=ctx.lease.max_attempts,
            map_generation=generation,
        )
        builds = f"job {job_id} (queued now) builds"
    reason = (
        f"map {map_id} changed while it was built (generation {ctx.map_generation} → "
        f"{generation}); its version is not stored: {builds} the map's current sessions"
    )
    queue.supersede(tx, ctx.lease, reason=reason, log_tail=ctx.log_tail)
    ctx.finished = ctx.superseded = True


BUILD_MAP_STAGES: tuple[Stage, ...] = (
    Stage(name="load", weight=0.2, run=load),
    Stage(name="tune", weight=0.3, run=tune),
    Stage(name="optimize", weight=0.3, run=optimize),
    Stage(name="evaluate", weight=0.12, run=evaluate),
    Stage(name="path_graph", weight=0.03, run=path_graph),
    Stage(name="store", weight=0.05, run=store),
)

#: The stages of each job kind a worker runs.
PIPELINES: Mapping[str, Sequence[Stage]] = {BUILD_MAP: BUILD_MAP_STAGES}


# --------------------------------------------------------------------------- the runner


def is_permanent(err: BaseException) -> bool:
    """Whether retrying cannot help: the core refused the input, a stored input is bad, or the
    error is deterministic (the database refusing a value as such, SQLSTATE class 22; text
    that cannot be encoded; a number that overflows): the same input fails the same way."""
    return isinstance(
        err, InvisibleMapError | PermanentJobError | DataError | UnicodeError | OverflowError
    )


def through_outages(control: JobControl, job_id: int, what: str, call: Callable[[], T]) -> T:
    """``call()``, tried again while it fails with a database fault and the lease holds (see the
    module docstring); any other error, a lost lease, or a fault outlasting the lease is raised."""
    wait_s = OUTAGE_FIRST_WAIT_S
    while True:
        try:
            return call()
        except Exception as err:
            fault = database_fault(err)
            if fault is None or time.monotonic() + wait_s >= control.lease_deadline_s:
                raise
            if control.lease_lost:
                raise LeaseLost(job_id) from err
            logger.warning(
                "job %d: %s: %s (%s); trying again in %g s, while the lease holds",
                job_id,
                what,
                fault.value,
                first_line(err),
                wait_s,
                extra={"action": "database_fault", "job_id": job_id},
            )
            time.sleep(wait_s)
            wait_s = min(2 * wait_s, OUTAGE_MAX_WAIT_S)


def run_job(
    db: Database,
    lease: Lease,
    *,
    stages: Sequence[Stage],
    control: JobControl,
    retry_backoff_s: float,
    time_budget_s: float = 0.0,
    incremental_builds: bool = False,
) -> JobReport:
    """Run ``stages`` for ``lease``'s job and record how it ended; see the module docstring.
    ``time_budget_s`` > 0: the attempt fails for good (PermanentJobError, with the reason) once
    it has run that long, at the next :meth:`JobContext.check_interrupted`.
    ``incremental_builds``: ``Settings.incremental_builds`` (``workers.incremental_builds``).

    Never raises for an ``Exception`` of a stage (it is recorded on the job), only when recording
    fails too (the database unreachable: the lease then expires and the reaper requeues the job).
    A ``BaseException`` (KeyboardInterrupt, SystemExit) gives the job back to the queue and
    propagates.
    """
    started_s = time.perf_counter()
    ctx = JobContext(
        db=db,
        lease=lease,
        control=control,
        log_tail=lease.log_tail,
        incremental_builds=incremental_builds,
    )
    if time_budget_s > 0:
        ctx.time_budget_s, ctx.deadline_s = time_budget_s, time.monotonic() + time_budget_s
    total_weight = sum(stage.weight for stage in stages) or 1.0

    def ended(outcome: Outcome, error: str | None = None) -> JobReport:
        return JobReport(
            outcome=outcome,
            error=error,
            version=ctx.version,
            duration_s=time.perf_counter() - started_s,
            stage_durations_s=tuple(stage_durations_s),
        )

    def retrying(call: Callable[[], T], what: str) -> T:
        return through_outages(control, lease.job_id, what, call)

    done_weight = 0.0
    stage_durations_s: list[tuple[str, float]] = []
    try:
        for stage in stages:
            if control.lease_lost:
                raise LeaseLost(lease.job_id)
            if control.release_requested:
                retrying(lambda: queue.release(db, lease, log_tail=ctx.log_tail), "release")
                return ended(Outcome.RELEASED)
            ctx.begin_stage(
                stage.name, start=done_weight / total_weight, weight=stage.weight / total_weight
            )
            if retrying(
                lambda: queue.report_progress(
                    db, lease, progress=ctx.stage_start, stage=ctx.stage, log_tail=ctx.log_tail
                ),
                "progress",
            ):
                control.cancel_requested = True
            if control.cancel_requested:
                # (the API's own "cancel requested" line is overwritten by the worker's tail)
                ctx.log(f"cancel requested: stopping before {stage.name}")
                retrying(lambda: queue.mark_canceled(db, lease, log_tail=ctx.log_tail), "cancel")
                return ended(Outcome.CANCELED)
            stage_started_s = time.perf_counter()
            retrying(functools.partial(stage.run, ctx), f"stage {stage.name}")
            stage_durations_s.append((stage.name, time.perf_counter() - stage_started_s))
            if ctx.finished:
                return ended(Outcome.SUPERSEDED if ctx.superseded else Outcome.SUCCEEDED)
            done_weight += stage.weight
        raise PermanentJobError(f"the {lease.kind} pipeline ended without storing a result")
    except LeaseLost:
        return ended(Outcome.LEASE_LOST)
    except Interrupted:
        try:
            if control.release_requested:
                ctx.log(f"release requested: stopping {ctx.stage}")
                retrying(lambda: queue.release(db, lease, log_tail=ctx.log_tail), "release")
                return ended(Outcome.RELEASED)
            ctx.log(f"cancel requested: stopped during {ctx.stage}")
            retrying(lambda: queue.mark_canceled(db, lease, log_tail=ctx.log_tail), "cancel")
        except LeaseLost:
            return ended(Outcome.LEASE_LOST)
        return ended(Outcome.CANCELED)
    except Exception as err:
        error = f"{ctx.stage or 'start'}: {type(err).__name__}: {err}"
        permanent = is_permanent(err)
        # the log tail is readable with a device key: only the core's own messages go there in
        # full (app.services.jobs.public_job_error); the whole error is in job.error and the log
        shown = error if permanent else f"{ctx.stage or 'start'}: {type(err).__name__}"
        ctx.log(f"{'permanent' if permanent else 'transient'} error in {shown}")
        try:
            state = retrying(
                lambda: queue.fail(
                    db,
                    lease,
                    error=error,
                    permanent=permanent,
                    backoff_s=retry_backoff_s,
                    log_tail=ctx.log_tail,
                ),
                "recording the error",
            )
        except LeaseLost:
            return ended(Outcome.LEASE_LOST, error)
        outcome = Outcome.RETRYING if state == JobState.QUEUED else Outcome.FAILED
        return ended(outcome, error)
    except BaseException:
        if not ctx.finished:
            try:
                queue.release(db, lease, log_tail=ctx.log_tail)
            except Exception:
                logger.warning("job %d: could not release it", lease.job_id, exc_info=True)
        raise

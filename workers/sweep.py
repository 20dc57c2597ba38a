"""The ``sweep_trials`` job: run some trials of a sweep and store them (``app.storage.sweeps``).

    load_sweep → run_trials → store_trials

A worker process keeps the last few prepared sessions (:class:`TuningTarget`, screened and
warm-started once), so the many small jobs of one sweep do not parse and prepare it again.
"""

from __future__ import annotations

from collections import OrderedDict
from datetime import datetime

from app.domain.evaluation.ground_truth import parse_ground_truth_json
from app.domain.evaluation.tuning import TuningTarget
from app.domain.mapping.params import SlamParams
from app.storage import queue, sweeps
from workers.pipeline import JobContext, PermanentJobError, Stage, load_session_upload

#: Prepared sessions a worker process keeps, by (database, sweep id, sweep creation time).
TARGET_CACHE_SIZE = 2
_targets: OrderedDict[tuple[str, int, datetime], TuningTarget] = OrderedDict()


def _sweep_id(ctx: JobContext) -> int:
    try:
        return int(ctx.lease.params["sweep_id"])
    except (KeyError, TypeError, ValueError) as err:
        raise PermanentJobError(f"job {ctx.lease.job_id} names no sweep") from err


def load_sweep(ctx: JobContext) -> None:
    """The sweep's session, prepared for trials (from the cache when this worker has it)."""
    sweep_id = _sweep_id(ctx)
    try:
        with ctx.db.read() as tx:
            info = sweeps.get_sweep(tx, sweep_id)
        key = (ctx.db.url.render_as_string(hide_password=True), sweep_id, info.created_at)
        target = _targets.get(key)
        if target is None:  # the ground truth is read only when the session is prepared
            with ctx.db.read() as tx:
                ground_truth = sweeps.ground_truth_of(tx, sweep_id)
    except sweeps.SweepNotFound as err:
        raise PermanentJobError(str(err)) from err
    if target is None:
        base_params = SlamParams().with_overrides(info.base_params)
        truth = parse_ground_truth_json(ground_truth) if ground_truth else None
        if len(info.session_ids) > 1:  # the joint map of the map's sessions
            loaded = [load_session_upload(ctx.db, i)[1] for i in info.session_ids]
            target = TuningTarget.prepare_joint(
                loaded, base_params, truth, names=[f"session {i}" for i in info.session_ids]
            )
            session = target.session
        else:
            _, session = load_session_upload(ctx.db, info.session_id)
            target = TuningTarget.prepare(session, base_params, truth)
        _targets[key] = target
        while len(_targets) > TARGET_CACHE_SIZE:
            _targets.popitem(last=False)
        tags = len(target.inputs.tag_rows)
        ctx.log(f"sweep {sweep_id}: prepared {session.num_poses} poses and {tags} tags")
    _targets.move_to_end(key)
    ctx.tuning_target = target


def run_trials(ctx: JobContext) -> None:
    target = ctx.tuning_target
    if target is None:
        raise RuntimeError("pipeline order: load_sweep did not run")
    values = ctx.lease.params.get("values")
    if not isinstance(values, list) or not values:
        raise PermanentJobError(f"job {ctx.lease.job_id} has no trial values")
    trials = []
    for k, trial_values in enumerate(values):
        ctx.check_interrupted()  # a cancel (or release, lost lease, spent budget) stops here,
        # and inside the trial after any Levenberg–Marquardt iteration
        trials.append(target.run(trial_values, on_iteration=ctx.on_trial_iteration))
        ctx.report((k + 1) / len(values))
    ctx.trials = trials
    best = min((t.shift for t in trials), default=float("nan"))
    ctx.log(f"trials {len(trials)}: best shift {best:.4g}")


def store_trials(ctx: JobContext) -> None:
    """In ONE transaction: finish the job (fenced), store its trials, and start the next batch."""
    target, trials = ctx.tuning_target, ctx.trials
    if target is None or trials is None:
        raise RuntimeError("pipeline order: run_trials did not run")
    sweep_id = _sweep_id(ctx)
    with ctx.db.transaction() as tx:
        queue.finish(tx, ctx.lease, log_tail=ctx.log_tail)
        sweeps.set_baseline(tx, sweep_id, target.baseline())
        sweeps.store_trials(
            tx,
            sweep_id,
            first_number=int(ctx.lease.params["first_number"]),
            trials=trials,
            job_id=ctx.lease.job_id,
            max_attempts=ctx.lease.max_attempts,
        )
    ctx.finished = True


SWEEP_STAGES: tuple[Stage, ...] = (
    Stage(name="load", weight=0.1, run=load_sweep),
    Stage(name="trials", weight=0.85, run=run_trials),
    Stage(name="store", weight=0.05, run=store_trials),
)

"""Sweeps in the database: created with their first jobs, filled in by ``sweep_trials`` jobs.

    sweep_id = create_sweep(tx, map_id=3, plan=plan, ground_truth=gt_json, …)   # + its jobs
    store_trials(tx, sweep_id, first_number=40, trials=[…], job_id=17)   # in the job's finish txn
    info = get_sweep(tx, sweep_id); trials = list_trials(tx, sweep_id)

A grid's trials are split into jobs of ``GRID_CHUNK`` when the sweep is created; a sampler's are
proposed a batch at a time: the job that stores the last trial of a batch proposes the next one
(under a lock on the sweep row, so two jobs finishing together cannot both do it). Each job
carries the values it must try, so a job run again after its worker died tries the same values,
and the unique ``(sweep_id, number)`` makes a trial stored twice impossible.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from app.domain.evaluation.ground_truth import parse_ground_truth_json
from app.domain.evaluation.metrics import SHIFT_METRIC_VERSION
from app.domain.evaluation.sweep_plan import GRID_CHUNK, SweepPlan
from app.domain.evaluation.tuning import SearchSpace, SweepSummary, Trial, summarize
from app.domain.json_values import finite_or_none
from app.storage import maps, queue
from app.storage.orm import Job, JobState, Sweep, SweepTrial, utc_now

#: The job kind that runs some trials of a sweep.
SWEEP_TRIALS = "sweep_trials"


class SweepNotFound(LookupError):
    def __init__(self, sweep_id: int) -> None:
        super().__init__(f"sweep {sweep_id} not found")
        self.sweep_id = sweep_id


@dataclass(frozen=True, slots=True, kw_only=True)
class SweepInfo:
    id: int
    map_id: int
    session_id: int
    method: str
    objective: str
    space: dict[str, Any]
    base_params: dict[str, Any]
    trials_total: int
    trials_started: int
    trials_done: int
    batch: int
    seed: int
    has_ground_truth: bool
    baseline: dict[str, Any] | None
    state: str
    error: str | None
    applied_job_id: int | None
    created_at: datetime
    shift_metric_version: int
    #: the map's sessions its trials optimize together (empty: the one ``session_id``)
    session_ids: list[int]
    finished_at: datetime | None

    @property
    def progress(self) -> float:
        return self.trials_done / self.trials_total if self.trials_total else 1.0

    def plan(self) -> SweepPlan:
        return SweepPlan(
            method=self.method,
            space=SearchSpace.from_dict(self.space),
            trials=self.trials_total,
            objective=self.objective,
            seed=self.seed,
            batch=self.batch,
        )


def create_sweep(
    db_session: Session,
    *,
    map_id: int,
    session_id: int,
    plan: SweepPlan,
    base_params: dict[str, Any],
    ground_truth: dict[str, Any] | None,
    max_attempts: int,
) -> int:
    """Add a sweep and the jobs of its first trials (all of a grid's); returns its id. A map of
    several sessions is swept as their joint map (its sessions now, recorded on the sweep)."""
    if ground_truth is not None:
        parse_ground_truth_json(ground_truth)  # raises InvisibleMapError naming the problem
    session_ids = maps.map_session_ids(db_session, map_id)
    row = Sweep(
        map_id=map_id,
        session_id=session_id,
        method=plan.method,
        objective=plan.objective,
        space=plan.space.to_dict(),
        base_params=base_params,
        trials_total=plan.total,
        batch=plan.batch,
        seed=plan.seed,
        ground_truth=ground_truth,
        state="running",
        shift_metric_version=SHIFT_METRIC_VERSION,
        session_ids=session_ids if len(session_ids) > 1 else None,
        created_at=utc_now(),
    )
    db_session.add(row)
    db_session.flush()
    first = plan.next_batch([], 0)
    _enqueue_trials(db_session, row, first, max_attempts=max_attempts)
    return row.id


def _enqueue_trials(
    db_session: Session, row: Sweep, values: list[dict[str, float]], *, max_attempts: int
) -> None:
    """Jobs for trials ``row.trials_started`` … of ``values``, ``GRID_CHUNK`` (grid) or one
    half-batch (sampler, so two workers share a batch) per job."""
    size = GRID_CHUNK if row.method == "grid" else max(1, math.ceil(len(values) / 2))
    for start in range(0, len(values), size):
        queue.enqueue(
            db_session,
            kind=SWEEP_TRIALS,
            map_id=row.map_id,
            session_id=row.session_id,
            params={
                "sweep_id": row.id,
                "first_number": row.trials_started + start,
                "values": values[start : start + size],
            },
            max_attempts=max_attempts,
            sweep_id=row.id,
        )
    row.trials_started += len(values)


def store_trials(
    db_session: Session,
    sweep_id: int,
    *,
    first_number: int,
    trials: list[Trial],
    job_id: int,
    max_attempts: int,
) -> None:
    """Record a job's trials (in the transaction that finishes the job), then propose the next
    sampler batch if this completed one, or end the sweep if every trial is in."""
    row = db_session.scalars(
        select(Sweep).where(Sweep.id == sweep_id).with_for_update()
    ).one_or_none()
    if row is None:
        raise SweepNotFound(sweep_id)
    now = utc_now()
    for offset, trial in enumerate(trials):
        db_session.add(
            SweepTrial(
                sweep_id=sweep_id,
                number=first_number + offset,
                values=trial.values,
                shift=finite_or_none(trial.shift),
                gt_metric=finite_or_none(trial.gt_metric),
                tag_rmse_m=finite_or_none(trial.tag_rmse_m),
                iterations=trial.iterations,
                converged=trial.converged,
                duration_s=trial.duration_s,
                error=trial.error,
                job_id=job_id,
                created_at=now,
            )
        )
    db_session.flush()
    done = _count_trials(db_session, sweep_id)
    if done >= row.trials_total:
        row.state, row.finished_at = "succeeded", now
    elif done == row.trials_started and row.method == "sampler":
        info = _info(db_session, row)
        values = info.plan().next_batch(list_trials(db_session, sweep_id), row.trials_started)
        _enqueue_trials(db_session, row, values, max_attempts=max_attempts)


def set_baseline(db_session: Session, sweep_id: int, baseline: tuple[float, float, float]) -> None:
    """Record the pre-optimized map's (shift, ground-truth metric, tag RMSE m), once."""
    row = db_session.get(Sweep, sweep_id)
    if row is not None and row.baseline is None:
        shift, gt_metric, rmse_m = baseline
        row.baseline = {
            "shift": finite_or_none(shift),
            "gt_metric": finite_or_none(gt_metric),
            "tag_rmse_m": finite_or_none(rmse_m),
        }


def cancel_sweep(db_session: Session, sweep_id: int) -> SweepInfo:
    """Request the cancel of every unfinished job of the sweep and end it as canceled."""
    row = db_session.get(Sweep, sweep_id)
    if row is None:
        raise SweepNotFound(sweep_id)
    job_ids = db_session.scalars(
        select(Job.id).where(
            Job.sweep_id == sweep_id,
            Job.state.in_([JobState.QUEUED.value, JobState.RUNNING.value]),
        )
    ).all()
    for job_id in job_ids:
        # a job that finished since the select has nothing left to cancel (not an error)
        with contextlib.suppress(queue.InvalidTransition):
            queue.request_cancel(db_session, job_id)
    if row.state == "running":
        row.state, row.finished_at = "canceled", utc_now()
    db_session.flush()
    return _info(db_session, row)


def set_applied(db_session: Session, sweep_id: int, job_id: int) -> None:
    row = db_session.get(Sweep, sweep_id)
    if row is None:
        raise SweepNotFound(sweep_id)
    row.applied_job_id = job_id


def get_sweep(db_session: Session, sweep_id: int) -> SweepInfo:
    row = db_session.get(Sweep, sweep_id)
    if row is None:
        raise SweepNotFound(sweep_id)
    return _info(db_session, row)


def ground_truth_of(db_session: Session, sweep_id: int) -> dict[str, Any] | None:
    row = db_session.get(Sweep, sweep_id)
    if row is None:
        raise SweepNotFound(sweep_id)
    return row.ground_truth


def list_sweeps(
    db_session: Session, *, map_id: int | None = None, limit: int = 50, offset: int = 0
) -> tuple[list[SweepInfo], int]:
    query = select(Sweep)
    count = select(func.count()).select_from(Sweep)
    if map_id is not None:
        query, count = query.where(Sweep.map_id == map_id), count.where(Sweep.map_id == map_id)
    rows = db_session.scalars(query.order_by(Sweep.id.desc()).limit(limit).offset(offset)).all()
    return [_info(db_session, row) for row in rows], int(db_session.scalar(count) or 0)


def list_trials(db_session: Session, sweep_id: int) -> list[Trial]:
    """The finished trials, by number."""
    return [trial for _, trial in numbered_trials(db_session, sweep_id)]


def numbered_trials(db_session: Session, sweep_id: int) -> list[tuple[int, Trial]]:
    """The finished trials with their numbers (a trial still running leaves a gap)."""
    rows = db_session.scalars(
        select(SweepTrial).where(SweepTrial.sweep_id == sweep_id).order_by(SweepTrial.number)
    ).all()
    return [(row.number, _trial(row)) for row in rows]


def summary(db_session: Session, info: SweepInfo) -> SweepSummary:
    baseline = info.baseline or {}
    return summarize(
        list_trials(db_session, info.id),
        info.objective,
        (
            _nan_if_none(baseline.get("shift")),
            _nan_if_none(baseline.get("gt_metric")),
            _nan_if_none(baseline.get("tag_rmse_m")),
        ),
    )


def _count_trials(db_session: Session, sweep_id: int) -> int:
    count = select(func.count()).select_from(SweepTrial).where(SweepTrial.sweep_id == sweep_id)
    return int(db_session.scalar(count) or 0)


def _trial(row: SweepTrial) -> Trial:
    return Trial(
        values={name: float(value) for name, value in row.values.items()},
        shift=_nan_if_none(row.shift),
        gt_metric=_nan_if_none(row.gt_metric),
        tag_rmse_m=_nan_if_none(row.tag_rmse_m),
        iterations=row.iterations,
        duration_s=row.duration_s,
        error=row.error,
    )


def _info(db_session: Session, row: Sweep) -> SweepInfo:
    state, error = row.state, row.error
    if state == "running":  # a job that ended without storing its trials ends the sweep
        ended = db_session.execute(
            select(Job.state, Job.error)
            .where(
                Job.sweep_id == row.id,
                Job.state.in_([JobState.FAILED.value, JobState.CANCELED.value]),
            )
            .limit(1)
        ).first()
        if ended is not None:
            state = "failed" if ended.state == JobState.FAILED.value else "canceled"
            error = ended.error or f"a job of the sweep was {ended.state}"
    return SweepInfo(
        id=row.id,
        map_id=row.map_id,
        session_id=row.session_id,
        method=row.method,
        objective=row.objective,
        space=row.space,
        base_params=row.base_params,
        trials_total=row.trials_total,
        trials_started=row.trials_started,
        trials_done=_count_trials(db_session, row.id),
        batch=row.batch,
        seed=row.seed,
        has_ground_truth=row.ground_truth is not None,
        baseline=row.baseline,
        state=state,
        error=error,
        applied_job_id=row.applied_job_id,
        created_at=row.created_at,
        shift_metric_version=row.shift_metric_version,
        session_ids=list(row.session_ids or []),
        finished_at=row.finished_at,
    )


def _nan_if_none(value: float | None) -> float:
    return math.nan if value is None else float(value)

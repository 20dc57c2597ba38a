"""What ``/metrics`` reads from the database at each scrape, and the worker's record of how long
each stage of a job took (docs/operations.md, "Metrics").

    record_stages(db, job_id=7, kind="build_map", attempt=1, durations_s=[("load", 0.21), …])
    with db.read() as db_session:
        queue_depth(db_session)                   # {(kind, state): jobs} queued or running
        oldest_queued_at(db_session)              # {kind: created_at of its oldest queued job}
        finished_jobs(db_session)                 # {(kind, state): jobs} that finished
        job_durations(db_session, (1.0, 10.0))    # {(kind, state): Distribution} of those that ran
        stage_durations(db_session, (1.0, 10.0))  # {(kind, stage): Distribution}
        workers_alive(db_session, within_s=15.0)  # {state: worker processes}

The database is the one place every API process and every worker shares, so each scrape of any
API process reads the same numbers. Every query is one aggregate statement: queue depth reads the
``job`` claim index (``state`` first); the finished jobs and the durations read every row of
``job`` and ``job_stage`` (a lab's thousands of jobs: milliseconds) and hold nothing in memory but
the groups.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

from sqlalchemy import ColumnElement, Float, case, cast, func, select
from sqlalchemy.orm import InstrumentedAttribute, Session

from app.storage.db import Database
from app.storage.orm import TERMINAL_STATES, Job, JobStageRun, JobState, WorkerRow, utc_now

#: The job states that make up the queue's depth.
QUEUE_STATES = (JobState.QUEUED, JobState.RUNNING)


@dataclass(frozen=True, slots=True, kw_only=True)
class Distribution:
    """Durations grouped as a Prometheus histogram: ``below[k]`` of them took at most
    ``bounds_s[k]`` s (cumulative), ``count`` in all, summing to ``sum_s``."""

    bounds_s: tuple[float, ...]
    below: tuple[int, ...]
    count: int
    sum_s: float


def record_stages(
    db: Database,
    *,
    job_id: int,
    kind: str,
    attempt: int,
    durations_s: Iterable[tuple[str, float]],
    now: datetime | None = None,
) -> int:
    """Store how long each stage of an attempt at job ``job_id`` took (stage name, seconds), in
    one transaction; returns how many rows: none when the job is gone (its session was deleted
    meanwhile). Not fenced: the attempt's work was done whatever became of its lease."""
    now = now or utc_now()
    rows = [
        JobStageRun(
            job_id=job_id,
            kind=kind,
            stage=stage,
            attempt=attempt,
            duration_s=max(float(duration_s), 0.0),
            finished_at=now,
        )
        for stage, duration_s in durations_s
    ]
    if not rows:
        return 0
    with db.transaction() as db_session:
        if db_session.get(Job, job_id) is None:
            return 0
        db_session.add_all(rows)
    return len(rows)


def queue_depth(db_session: Session) -> dict[tuple[str, str], int]:
    """Jobs queued (runnable now or after a back-off) and running, by (kind, state)."""
    rows = db_session.execute(
        select(Job.kind, Job.state, func.count())
        .where(Job.state.in_([state.value for state in QUEUE_STATES]))
        .group_by(Job.kind, Job.state)
    )
    return {(kind, state): count for kind, state, count in rows}


def oldest_queued_at(db_session: Session) -> dict[str, datetime]:
    """When the oldest job of each kind that is waiting now was queued."""
    rows = db_session.execute(
        select(Job.kind, func.min(Job.created_at))
        .where(Job.state == JobState.QUEUED.value)
        .group_by(Job.kind)
    )
    return {kind: _utc(created_at) for kind, created_at in rows if created_at is not None}


def finished_jobs(db_session: Session) -> dict[tuple[str, str], int]:
    """Jobs that finished (succeeded, failed, canceled), by (kind, state)."""
    rows = db_session.execute(
        select(Job.kind, Job.state, func.count())
        .where(Job.state.in_([state.value for state in TERMINAL_STATES]))
        .group_by(Job.kind, Job.state)
    )
    return {(kind, state): count for kind, state, count in rows}


def job_durations(
    db_session: Session, bounds_s: Sequence[float]
) -> dict[tuple[str, str], Distribution]:
    """How long the finished jobs that ran took, from the start of their last attempt to their
    end, by (kind, state). (A job canceled while queued never ran and is not among them.)"""
    seconds = _seconds_between(db_session, Job.started_at, Job.finished_at)
    return _distributions(
        db_session,
        (Job.kind, Job.state),
        seconds,
        bounds_s,
        Job.state.in_([state.value for state in TERMINAL_STATES]),
        Job.started_at.is_not(None),
        Job.finished_at.is_not(None),
    )


def stage_durations(
    db_session: Session, bounds_s: Sequence[float]
) -> dict[tuple[str, str], Distribution]:
    """How long each stage took, by (kind, stage), over the stages that ran to their end."""
    seconds = cast(JobStageRun.duration_s, Float)
    return _distributions(db_session, (JobStageRun.kind, JobStageRun.stage), seconds, bounds_s)


def workers_alive(
    db_session: Session, *, within_s: float, now: datetime | None = None
) -> dict[str, int]:
    """Worker processes that reported in the last ``within_s`` seconds, by state (idle, busy)."""
    now = now or utc_now()
    rows = db_session.execute(
        select(WorkerRow.state, func.count())
        .where(WorkerRow.heartbeat_at >= now - timedelta(seconds=within_s))
        .group_by(WorkerRow.state)
    )
    return {str(state): int(count) for state, count in rows}


def _distributions(
    db_session: Session,
    keys: tuple[InstrumentedAttribute[str], InstrumentedAttribute[str]],
    seconds: ColumnElement[float],
    bounds_s: Sequence[float],
    *conditions: ColumnElement[bool],
) -> dict[tuple[str, str], Distribution]:
    bounds = tuple(float(bound) for bound in bounds_s)
    below = [func.sum(case((seconds <= bound, 1), else_=0)) for bound in bounds]
    statement = select(*keys, func.count(), func.sum(seconds), *below).group_by(*keys)
    if conditions:
        statement = statement.where(*conditions)
    out = {}
    for row in db_session.execute(statement):
        first, second, count, total_s, *counts = row
        out[(first, second)] = Distribution(
            bounds_s=bounds,
            below=tuple(int(n or 0) for n in counts),
            count=int(count),
            sum_s=max(float(total_s or 0.0), 0.0),
        )
    return out


def _seconds_between(
    db_session: Session,
    start: InstrumentedAttribute[datetime | None],
    end: InstrumentedAttribute[datetime | None],
) -> ColumnElement[float]:
    """``end - start`` in seconds, as the database computes it."""
    if db_session.get_bind().dialect.name == "sqlite":  # naive UTC text (orm.UTCDateTime)
        return (func.julianday(end) - func.julianday(start)) * 86400.0
    return cast(func.extract("epoch", end - start), Float)


def _utc(value: datetime) -> datetime:
    return value.replace(tzinfo=UTC) if value.tzinfo is None else value

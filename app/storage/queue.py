"""The durable job queue, in the ``job`` table.

Every state change is one committed transaction. A worker *claims* a queued job in one statement
(``UPDATE … WHERE id = (SELECT … FOR UPDATE SKIP LOCKED LIMIT 1) RETURNING …`` on PostgreSQL; the
same statement on SQLite, where ``BEGIN IMMEDIATE`` serializes writers) and gets a :class:`Lease`
that expires unless renewed by :func:`heartbeat`. Each claim increments ``lease_token``; every
later write by the worker names its token and requires an unexpired lease (*fencing*), so a worker
that lost its lease — it stalled, or the reaper requeued its job, or another worker claimed it —
gets :class:`LeaseLost` instead of writing. :func:`reap_expired` requeues (or fails, after
``max_attempts``) jobs whose lease ran out.

Exceptions::

    QueueError
    ├── LeaseLost          a fenced write found the lease gone
    ├── JobNotFound        no job with that id
    └── InvalidTransition  cancel/retry asked of a job whose state does not allow it
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import ColumnElement, Update, and_, delete, func, select, update
from sqlalchemy.orm import Session

from app.storage.db import Database
from app.storage.orm import TERMINAL_STATES, Job, JobState, SessionRow, WorkerRow, utc_now
from app.storage.rows import info_from_row

#: How many lines of a job's log are kept on its row.
LOG_TAIL_LINES = 40


class QueueError(Exception):
    """Base of the queue's errors."""


class LeaseLost(QueueError):
    """Raised when a worker writes to a job whose lease it no longer holds."""

    def __init__(self, job_id: int) -> None:
        super().__init__(f"job {job_id}: lease lost (expired, requeued or claimed by another)")
        self.job_id = job_id


class JobNotFound(QueueError):
    """Raised when no job has the given id."""

    def __init__(self, job_id: int) -> None:
        super().__init__(f"job {job_id} not found")
        self.job_id = job_id


class InvalidTransition(QueueError):
    """Raised when an action (cancel, retry) is not allowed in the job's current state."""

    def __init__(self, job_id: int, state: str, action: str) -> None:
        super().__init__(f"job {job_id} is {state}: cannot {action} it")
        self.job_id = job_id
        self.state = state
        self.action = action


class MapOfJobDeleted(InvalidTransition):
    """Raised when a job whose map was deleted is to be retried: there is no map to build."""

    def __init__(self, job_id: int, state: str) -> None:
        super().__init__(job_id, state, "retry")
        self.args = (f"job {job_id}'s map was deleted: cannot retry it",)

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass(frozen=True, slots=True, kw_only=True)
class JobInfo:
    """A job as the API shows it."""

    id: int
    kind: str
    state: JobState
    map_id: int | None
    session_id: int | None
    params: dict[str, Any]
    attempts: int
    max_attempts: int
    progress: float
    #: a build's map generation (``Job.map_generation``; None: none)
    map_generation: int | None = None
    stage: str | None
    error: str | None
    log_tail: str
    cancel_requested: bool
    lease_owner: str | None
    created_at: datetime
    run_after: datetime
    started_at: datetime | None
    finished_at: datetime | None
    updated_at: datetime

    @classmethod
    def from_row(cls, row: Job) -> JobInfo:
        return info_from_row(cls, row)

    @property
    def map_deleted(self) -> bool:
        """Whether the job's map was deleted (the job kept, :func:`keep_jobs_of_deleted_map`):
        a map's job names its session too, and a deleted session takes its jobs with it."""
        return self.map_id is None and self.session_id is not None


@dataclass(frozen=True, slots=True, kw_only=True)
class Lease:
    """What a worker holds while it runs a job: the job's inputs and the fencing token."""

    job_id: int
    token: int
    owner: str
    kind: str
    map_id: int | None
    session_id: int | None
    params: dict[str, Any]
    attempt: int
    max_attempts: int
    log_tail: str
    #: a build's map generation (0 for builds queued before generations)
    map_generation: int = 0


# --------------------------------------------------------------------------- the API's side


def enqueue(
    db_session: Session,
    *,
    kind: str,
    map_id: int | None,
    session_id: int | None,
    params: dict[str, Any] | None = None,
    max_attempts: int = 3,
    priority: int = 0,
    sweep_id: int | None = None,
    map_generation: int | None = None,
    now: datetime | None = None,
) -> int:
    """Add a queued job in the caller's transaction; returns its id. ``map_generation``: of a
    build, the map's generation it builds."""
    now = now or utc_now()
    job = Job(
        kind=kind,
        state=JobState.QUEUED.value,
        map_id=map_id,
        session_id=session_id,
        params=params or {},
        max_attempts=max_attempts,
        priority=priority,
        sweep_id=sweep_id,
        map_generation=map_generation,
        run_after=now,
        created_at=now,
        updated_at=now,
        log_tail=_log_line(now, "queued"),
    )
    db_session.add(job)
    db_session.flush()
    return job.id


@dataclass(frozen=True, slots=True, kw_only=True)
class Coalesced:
    """What :func:`enqueue_coalesced` did: the job that will do the work, whether it was a
    queued job that absorbed the request (else it is new), and the jobs it superseded."""

    job_id: int
    #: the request was folded into job ``job_id``, queued before and not started yet
    coalesced: bool
    #: running jobs asked to stop, and older queued ones canceled, because job ``job_id``
    #: replaces them
    superseded: tuple[int, ...] = ()


def enqueue_coalesced(
    db_session: Session,
    *,
    kind: str,
    map_id: int,
    session_id: int,
    params: dict[str, Any],
    map_generation: int,
    note: str,
    max_attempts: int = 3,
    now: datetime | None = None,
) -> Coalesced:
    """Ask for one job of ``kind`` on map ``map_id`` with ``params``, building its generation
    ``map_generation``, that replaces whatever of
    that kind the map has under way, in the caller's transaction: the newest queued job (not
    started) absorbs the request (its parameters replaced, its attempts and back-off reset,
    ``note`` added to its log) instead of a second job being queued; otherwise a new job is
    queued. Any other queued job of the map and kind is canceled, and any running one asked to
    stop, with ``error`` naming the job that replaces it. The caller holds the map's lock
    (``app.storage.maps.lock_maps``), so changes of one map do this one at a time; a worker
    claiming the queued job meanwhile either took it first (it is then running, and superseded)
    or takes it afterwards, with the new parameters."""
    now = now or utc_now()
    rows = db_session.scalars(
        select(Job)
        .where(
            Job.map_id == map_id,
            Job.kind == kind,
            Job.state.in_([JobState.QUEUED.value, JobState.RUNNING.value]),
        )
        .order_by(Job.id)
        .with_for_update()
        .execution_options(populate_existing=True)
    ).all()
    queued = [row for row in rows if row.state == JobState.QUEUED]
    running = [row for row in rows if row.state == JobState.RUNNING]
    if queued:
        target = queued.pop()
        target.params = params
        target.map_generation = map_generation
        target.session_id = session_id
        target.attempts = 0
        target.max_attempts = max_attempts
        target.error = None
        target.run_after = now
        target.updated_at = now
        target.log_tail = _append(target.log_tail, now, f"coalesced: {note}")
        db_session.flush()
        job_id, coalesced = target.id, True
    else:
        job_id = enqueue(
            db_session,
            kind=kind,
            map_id=map_id,
            session_id=session_id,
            params=params,
            max_attempts=max_attempts,
            map_generation=map_generation,
            now=now,
        )
        row = db_session.get(Job, job_id)
        assert row is not None
        row.log_tail = _append(row.log_tail, now, note)
        job_id, coalesced = row.id, False
    why = f"superseded by job {job_id}: {note}"
    for row in queued:
        row.state = JobState.CANCELED.value
        row.finished_at = now
        row.error = why
        row.log_tail = _append(row.log_tail, now, why)
    for row in running:
        # the worker owns a running job's log: the reason goes in ``error``, which it keeps
        row.cancel_requested = True
        row.error = why
    for row in (*queued, *running):
        row.updated_at = now
    db_session.flush()
    return Coalesced(
        job_id=job_id,
        coalesced=coalesced,
        superseded=tuple(row.id for row in (*queued, *running)),
    )


def jobs_of_map(
    db_session: Session, map_id: int, *, kind: str, states: tuple[JobState, ...] | None = None
) -> list[JobInfo]:
    """The jobs of ``kind`` on map ``map_id`` (only those in ``states`` when given), oldest
    first."""
    query = select(Job).where(Job.map_id == map_id, Job.kind == kind)
    if states is not None:
        query = query.where(Job.state.in_([state.value for state in states]))
    return [JobInfo.from_row(row) for row in db_session.scalars(query.order_by(Job.id))]


def get_job(db_session: Session, job_id: int) -> JobInfo:
    row = db_session.get(Job, job_id)
    if row is None:
        raise JobNotFound(job_id)
    return JobInfo.from_row(row)


def list_jobs(
    db_session: Session,
    *,
    state: JobState | None = None,
    map_id: int | None = None,
    session_id: int | None = None,
    finished_after: datetime | None = None,
    limit: int = 50,
    offset: int = 0,
) -> tuple[list[JobInfo], int]:
    """Jobs, newest first, and how many match in all: only those in ``state``, of ``map_id``,
    of ``session_id``, or finished after ``finished_after`` when given."""
    conditions: list[ColumnElement[bool]] = []
    if state is not None:
        conditions.append(Job.state == state.value)
    if map_id is not None:
        conditions.append(Job.map_id == map_id)
    if session_id is not None:
        conditions.append(Job.session_id == session_id)
    if finished_after is not None:
        conditions.append(Job.finished_at > finished_after)
    where = and_(*conditions) if conditions else and_(True)
    total = db_session.scalar(select(func.count()).select_from(Job).where(where)) or 0
    rows = db_session.scalars(
        select(Job).where(where).order_by(Job.id.desc()).limit(limit).offset(offset)
    )
    return [JobInfo.from_row(row) for row in rows], total


def count_by_state(db_session: Session) -> dict[str, int]:
    counts = {state.value: 0 for state in JobState}
    for state, count in db_session.execute(select(Job.state, func.count()).group_by(Job.state)):
        counts[state] = count
    return counts


def request_cancel(db_session: Session, job_id: int, *, now: datetime | None = None) -> JobInfo:
    """Cancel a queued job now; ask a running one to stop at its next stage boundary."""
    now = now or utc_now()
    row = _locked(db_session, job_id)
    if row.state == JobState.QUEUED:
        row.state = JobState.CANCELED.value
        row.finished_at = now
        row.log_tail = _append(row.log_tail, now, "canceled while queued")
    elif row.state == JobState.RUNNING:
        # The worker owns a running job's log (its writes replace the tail); it logs the cancel
        # when it sees this flag at the next stage boundary.
        row.cancel_requested = True
    else:
        raise InvalidTransition(job_id, row.state, "cancel")
    row.updated_at = now
    db_session.flush()
    return JobInfo.from_row(row)


def retry(db_session: Session, job_id: int, *, now: datetime | None = None) -> JobInfo:
    """Queue a failed or canceled job again, with a fresh count of attempts."""
    now = now or utc_now()
    row = _locked(db_session, job_id)
    if row.state not in (JobState.FAILED, JobState.CANCELED):
        raise InvalidTransition(job_id, row.state, "retry")
    if row.map_id is None and row.session_id is not None:  # map deleted (JobInfo.map_deleted)
        raise MapOfJobDeleted(job_id, row.state)
    row.state = JobState.QUEUED.value
    row.attempts = 0
    row.error = None
    row.progress = 0.0
    row.stage = None
    row.cancel_requested = False
    row.started_at = None
    row.finished_at = None
    row.run_after = now
    row.updated_at = now
    row.log_tail = _append(row.log_tail, now, "retry requested")
    db_session.flush()
    return JobInfo.from_row(row)


def cancel_unfinished_for_map(
    db_session: Session, map_id: int, *, now: datetime | None = None
) -> int:
    """Cancel a map's queued jobs and ask its running ones to stop; returns how many."""
    now = now or utc_now()
    queued = _rowcount(
        db_session,
        update(Job)
        .where(Job.map_id == map_id, Job.state == JobState.QUEUED.value)
        .values(state=JobState.CANCELED.value, finished_at=now, updated_at=now),
    )
    running = _rowcount(
        db_session,
        update(Job)
        .where(Job.map_id == map_id, Job.state == JobState.RUNNING.value)
        .values(cancel_requested=True, updated_at=now),
    )
    return queued + running


def keep_jobs_of_deleted_map(
    db_session: Session, map_id: int, *, now: datetime | None = None
) -> int:
    """Let the jobs of map ``map_id``, which the caller deletes in this transaction, outlive it
    (the map's foreign key would delete them): their ``map_id`` becomes null, their log says the
    map was deleted, and their page and ``GET /v1/jobs/{id}`` still answer; the queued ones are
    canceled first, the running ones asked to stop (:func:`cancel_unfinished_for_map`). Returns
    how many."""
    now = now or utc_now()
    cancel_unfinished_for_map(db_session, map_id, now=now)
    line = _log_line(now, f"map {map_id} deleted; this job is kept")
    return _rowcount(
        db_session,
        update(Job)
        .where(Job.map_id == map_id)
        .values(map_id=None, updated_at=now, log_tail=Job.log_tail + line),
    )


def _rowcount(db_session: Session, statement: Update) -> int:
    """How many rows an UPDATE changed (via RETURNING, which both backends support)."""
    return len(db_session.execute(statement.returning(Job.id)).all())


def _locked(db_session: Session, job_id: int) -> Job:
    row = db_session.scalar(select(Job).where(Job.id == job_id).with_for_update())
    if row is None:
        raise JobNotFound(job_id)
    return row


# --------------------------------------------------------------------------- the worker's side


def claim(
    db: Database,
    *,
    worker_id: str,
    lease_s: float,
    kinds: tuple[str, ...] | None = None,
    now: datetime | None = None,
) -> Lease | None:
    """Take the next runnable job, or None if there is none: the highest priority first, then
    in turns across uploaders, then the oldest.

    Turns: a waiting job's turn is its place among its uploader's waiting jobs (1 for the oldest)
    plus how many of that uploader's jobs were started since the oldest waiting job was queued.
    So a key that was just served waits for the others' next job, and one key's hundred queued
    uploads do not make another key's one wait behind them (sweeps' trials count as their
    session's uploader's). Computed per claim over the waiting jobs and the jobs started since
    the oldest waiting one: a scan of the queue, not of the job table's history.

    An idle worker asks this several times a second: whether any job is runnable is read first
    (one indexed ``SELECT``, no write transaction, so no SQLite write lock taken from the API's
    writers; a tenth of the claim's CPU), and only then is one claimed."""
    now = now or utc_now()
    uploader = func.coalesce(SessionRow.uploaded_by, "")
    queued = and_(Job.state == JobState.QUEUED.value, Job.run_after <= now)
    if kinds is not None:
        queued = and_(queued, Job.kind.in_(kinds))
    with db.read() as db_session:
        if db_session.scalar(select(Job.id).where(queued).limit(1)) is None:
            return None
    waiting = (
        select(
            Job.id.label("id"),
            uploader.label("uploader"),
            func.row_number()
            .over(partition_by=uploader, order_by=(Job.priority.desc(), Job.id))
            .label("place"),
        )
        .select_from(Job)
        .outerjoin(SessionRow, SessionRow.id == Job.session_id)
        .where(queued)
        .subquery()
    )
    oldest_waiting = (
        select(func.min(Job.created_at)).where(Job.state == JobState.QUEUED.value).scalar_subquery()
    )
    served = (
        select(uploader.label("uploader"), func.count().label("jobs"))
        .select_from(Job)
        .outerjoin(SessionRow, SessionRow.id == Job.session_id)
        .where(Job.started_at >= oldest_waiting)
        .group_by(uploader)
        .subquery()
    )
    turn = waiting.c.place + func.coalesce(served.c.jobs, 0)
    candidate = (
        select(Job.id)
        .join(waiting, waiting.c.id == Job.id)
        .outerjoin(served, served.c.uploader == waiting.c.uploader)
        .order_by(Job.priority.desc(), turn, Job.id)
        .limit(1)
        .with_for_update(skip_locked=True, of=Job)
    )
    statement = (
        update(Job)
        .where(Job.id == candidate.scalar_subquery(), Job.state == JobState.QUEUED.value)
        .values(
            state=JobState.RUNNING.value,
            lease_owner=worker_id,
            lease_token=Job.lease_token + 1,
            lease_expires_at=now + timedelta(seconds=lease_s),
            attempts=Job.attempts + 1,
            started_at=now,
            updated_at=now,
            progress=0.0,
            stage=None,
        )
        .returning(
            Job.id,
            Job.lease_token,
            Job.kind,
            Job.map_id,
            Job.session_id,
            Job.params,
            Job.attempts,
            Job.max_attempts,
            Job.log_tail,
            Job.map_generation,
        )
    )
    with db.transaction() as db_session:
        row = db_session.execute(statement).one_or_none()
        if row is None:
            return None
        line = f"attempt {row.attempts} of {row.max_attempts} started by {worker_id}"
        log_tail = _append(row.log_tail, now, line)
        db_session.execute(update(Job).where(Job.id == row.id).values(log_tail=log_tail))
    return Lease(
        job_id=row.id,
        token=row.lease_token,
        owner=worker_id,
        kind=row.kind,
        map_id=row.map_id,
        session_id=row.session_id,
        params=dict(row.params),
        attempt=row.attempts,
        max_attempts=row.max_attempts,
        log_tail=log_tail,
        map_generation=row.map_generation or 0,
    )


def _fenced(lease: Lease, now: datetime) -> ColumnElement[bool]:
    """The WHERE clause of every write a worker makes: its lease is still its own and valid."""
    return and_(
        Job.id == lease.job_id,
        Job.lease_token == lease.token,
        Job.state == JobState.RUNNING.value,
        Job.lease_expires_at > now,
    )


def heartbeat(db: Database, lease: Lease, *, lease_s: float, now: datetime | None = None) -> bool:
    """Extend the lease; returns whether a cancel was requested. Raises LeaseLost."""
    now = now or utc_now()
    with db.transaction() as db_session:
        cancel = db_session.execute(
            update(Job)
            .where(_fenced(lease, now))
            .values(lease_expires_at=now + timedelta(seconds=lease_s), updated_at=now)
            .returning(Job.cancel_requested),
        ).scalar_one_or_none()
    if cancel is None:
        raise LeaseLost(lease.job_id)
    return bool(cancel)


def report_progress(
    db: Database,
    lease: Lease,
    *,
    progress: float,
    stage: str,
    log_tail: str,
    now: datetime | None = None,
) -> bool:
    """Write progress (0–1), the stage and the log tail; returns whether a cancel was requested.
    Raises LeaseLost."""
    now = now or utc_now()
    with db.transaction() as db_session:
        cancel = db_session.execute(
            update(Job)
            .where(_fenced(lease, now))
            .values(
                progress=round(min(max(progress, 0.0), 1.0), 4),
                stage=stage,
                log_tail=log_tail,
                updated_at=now,
            )
            .returning(Job.cancel_requested),
        ).scalar_one_or_none()
    if cancel is None:
        raise LeaseLost(lease.job_id)
    return bool(cancel)


def finish(
    db_session: Session, lease: Lease, *, log_tail: str, now: datetime | None = None
) -> None:
    """Mark the job succeeded inside the caller's transaction (the one storing its result), so
    the result commits only if the lease still holds. Raises LeaseLost (roll back then)."""
    now = now or utc_now()
    updated = db_session.execute(
        update(Job)
        .where(_fenced(lease, now))
        .values(
            state=JobState.SUCCEEDED.value,
            progress=1.0,
            stage=None,
            error=None,
            finished_at=now,
            updated_at=now,
            lease_owner=None,
            lease_expires_at=None,
            log_tail=_append(log_tail, now, "succeeded"),
        )
        .returning(Job.id),
    ).scalar_one_or_none()
    if updated is None:
        raise LeaseLost(lease.job_id)


def fail(
    db: Database,
    lease: Lease,
    *,
    error: str,
    permanent: bool,
    backoff_s: float,
    log_tail: str,
    now: datetime | None = None,
) -> JobState:
    """Record a failed attempt: requeue with exponential backoff if the error is transient and
    attempts remain, else fail for good. Returns the new state. Raises LeaseLost."""
    now = now or utc_now()
    if permanent or lease.attempt >= lease.max_attempts:
        state = JobState.FAILED
        why = "permanent error" if permanent else f"attempt {lease.attempt} of {lease.max_attempts}"
        values: dict[str, Any] = {"finished_at": now, "log_tail": _append(log_tail, now, why)}
    else:
        state = JobState.QUEUED
        delay_s = backoff_s * 2 ** (lease.attempt - 1)
        values = {
            "run_after": now + timedelta(seconds=delay_s),
            "log_tail": _append(log_tail, now, f"retrying in {delay_s:g} s"),
        }
    return _end_attempt(db, lease, state, now, error=error, **values)


def supersede(
    db_session: Session, lease: Lease, *, reason: str, log_tail: str, now: datetime | None = None
) -> None:
    """End the job as ``canceled`` because its result was overtaken (``reason``, also its
    ``error``), in the caller's transaction, fenced like :func:`finish`: its result is not
    stored. Raises LeaseLost (roll back then)."""
    now = now or utc_now()
    updated = db_session.execute(
        update(Job)
        .where(_fenced(lease, now))
        .values(
            state=JobState.CANCELED.value,
            stage=None,
            error=reason,
            finished_at=now,
            updated_at=now,
            lease_owner=None,
            lease_expires_at=None,
            log_tail=_append(log_tail, now, f"superseded: {reason}"),
        )
        .returning(Job.id),
    ).scalar_one_or_none()
    if updated is None:
        raise LeaseLost(lease.job_id)


def mark_canceled(
    db: Database, lease: Lease, *, log_tail: str, now: datetime | None = None
) -> None:
    """The worker stopped a job whose cancel was requested. Raises LeaseLost."""
    now = now or utc_now()
    line = _append(log_tail, now, "canceled")
    _end_attempt(db, lease, JobState.CANCELED, now, finished_at=now, log_tail=line)


def release(db: Database, lease: Lease, *, log_tail: str, now: datetime | None = None) -> None:
    """Give a job back unfinished (graceful shutdown): queued again, the attempt not counted."""
    now = now or utc_now()
    line = _append(log_tail, now, f"released by {lease.owner} (shutting down)")
    _end_attempt(
        db, lease, JobState.QUEUED, now, run_after=now, attempts=Job.attempts - 1, log_tail=line
    )


def _end_attempt(
    db: Database, lease: Lease, state: JobState, now: datetime, **values: Any
) -> JobState:
    with db.transaction() as db_session:
        updated = db_session.execute(
            update(Job)
            .where(_fenced(lease, now))
            .values(
                state=state.value,
                lease_owner=None,
                lease_expires_at=None,
                updated_at=now,
                **values,
            )
            .returning(Job.id),
        ).scalar_one_or_none()
    if updated is None:
        raise LeaseLost(lease.job_id)
    return state


def reap_expired(db: Database, *, backoff_s: float, now: datetime | None = None) -> int:
    """Requeue running jobs whose lease expired (their worker died or stalled), after the same
    doubling back-off as :func:`fail`; fail those out of attempts and cancel those whose cancel
    was requested. Returns how many jobs were reaped."""
    now = now or utc_now()
    lost = "lease expired (worker lost)"
    with db.transaction() as db_session:
        rows = db_session.scalars(
            select(Job)
            .where(Job.state == JobState.RUNNING.value, Job.lease_expires_at <= now)
            .order_by(Job.id)
            .with_for_update(skip_locked=True)
        ).all()
        for row in rows:
            if row.cancel_requested:
                row.state = JobState.CANCELED.value
                row.finished_at = now
                row.log_tail = _append(row.log_tail, now, f"{lost}; canceled as requested")
            elif row.attempts >= row.max_attempts:
                row.state = JobState.FAILED.value
                row.finished_at = now
                row.error = f"{lost} on the last attempt"
                row.log_tail = _append(row.log_tail, now, f"{lost}; no attempts left")
            else:
                delay_s = backoff_s * 2 ** max(row.attempts - 1, 0)
                row.state = JobState.QUEUED.value
                row.run_after = now + timedelta(seconds=delay_s)
                row.log_tail = _append(row.log_tail, now, f"{lost}; requeued in {delay_s:g} s")
            row.lease_owner = None
            row.lease_expires_at = None
            row.updated_at = now
    return len(rows)


def expire_leases_of_dead_process(
    db: Database, *, hostname: str, pid: int, now: datetime | None = None
) -> int:
    """End now the leases of worker process ``pid`` on ``hostname``, which its supervisor saw die
    (and reaped), and remove its worker row: the reaper then requeues its job at once instead of
    when the lease would have run out. Returns how many leases ended. (Worker ids are
    ``{hostname[:60]}:{pid}:{8 hex}``; call it before a new process can have that pid.)"""
    now = now or utc_now()
    owner = f"{hostname[:60]}:{pid}:"
    with db.transaction() as db_session:
        ended = _rowcount(
            db_session,
            update(Job)
            .where(
                Job.state == JobState.RUNNING.value,
                Job.lease_owner.startswith(owner, autoescape=True),
            )
            .values(lease_expires_at=now, updated_at=now),
        )
        db_session.execute(
            delete(WorkerRow).where(WorkerRow.hostname == hostname, WorkerRow.pid == pid)
        )
    return ended


# --------------------------------------------------------------------------- workers


def register_worker(
    db: Database, *, worker_id: str, hostname: str, pid: int, now: datetime | None = None
) -> None:
    now = now or utc_now()
    with db.transaction() as db_session:
        db_session.merge(
            WorkerRow(
                id=worker_id,
                hostname=hostname,
                pid=pid,
                started_at=now,
                heartbeat_at=now,
                current_job_id=None,
                jobs_done=0,
                state="idle",
            )
        )


def worker_heartbeat(
    db: Database,
    *,
    worker_id: str,
    state: str,
    current_job_id: int | None,
    jobs_done: int,
    now: datetime | None = None,
) -> None:
    now = now or utc_now()
    with db.transaction() as db_session:
        db_session.execute(
            update(WorkerRow)
            .where(WorkerRow.id == worker_id)
            .values(
                heartbeat_at=now, state=state, current_job_id=current_job_id, jobs_done=jobs_done
            )
        )


def unregister_worker(db: Database, *, worker_id: str) -> None:
    with db.transaction() as db_session:
        row = db_session.get(WorkerRow, worker_id)
        if row is not None:
            db_session.delete(row)


@dataclass(frozen=True, slots=True, kw_only=True)
class WorkerInfo:
    id: str
    hostname: str
    pid: int
    state: str
    current_job_id: int | None
    jobs_done: int
    started_at: datetime
    heartbeat_at: datetime


def alive_workers(
    db_session: Session, *, within_s: float, now: datetime | None = None
) -> list[WorkerInfo]:
    """Workers that reported in the last ``within_s`` seconds."""
    now = now or utc_now()
    rows = db_session.scalars(
        select(WorkerRow)
        .where(WorkerRow.heartbeat_at >= now - timedelta(seconds=within_s))
        .order_by(WorkerRow.id)
    )
    return [
        WorkerInfo(
            id=row.id,
            hostname=row.hostname,
            pid=row.pid,
            state=row.state,
            current_job_id=row.current_job_id,
            jobs_done=row.jobs_done,
            started_at=row.started_at,
            heartbeat_at=row.heartbeat_at,
        )
        for row in rows
    ]


# --------------------------------------------------------------------------- log tail


def _log_line(now: datetime, message: str) -> str:
    return f"{now.strftime('%Y-%m-%dT%H:%M:%S')}Z {message}\n"


def _append(log_tail: str, now: datetime, message: str) -> str:
    lines = (log_tail + _log_line(now, message)).splitlines(keepends=True)
    return "".join(lines[-LOG_TAIL_LINES:])


def append_log(log_tail: str, message: str, *, now: datetime | None = None) -> str:
    """``log_tail`` with one more timestamped line, keeping the last :data:`LOG_TAIL_LINES`."""
    return _append(log_tail, now or utc_now(), message)


__all__ = [
    "TERMINAL_STATES",
    "InvalidTransition",
    "JobInfo",
    "JobNotFound",
    "Lease",
    "LeaseLost",
    "MapOfJobDeleted",
    "QueueError",
    "WorkerInfo",
]

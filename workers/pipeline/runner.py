"""The runner: :func:`run_job` carries out a job's stages under its lease and records how the
attempt ended; :func:`through_outages` rides out a database outage shorter than the lease (see
the package docstring)."""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable, Sequence
from typing import TypeVar

from sqlalchemy.exc import DataError

from app.domain.errors import InvisibleMapError
from app.storage import queue
from app.storage.db import Database, database_fault, first_line
from app.storage.orm import JobState
from app.storage.queue import Lease, LeaseLost
from workers.lease import JobControl

from .context import Interrupted, JobContext, JobReport, Outcome, PermanentJobError, Stage

#: the package's one logger (its records keep the name they had before the split)
logger = logging.getLogger("workers.pipeline")

#: First and longest wait before trying a stage or a job-state write again while the database is
#: unavailable, s (the wait doubles in between).
OUTAGE_FIRST_WAIT_S = 0.5
OUTAGE_MAX_WAIT_S = 4.0

T = TypeVar("T")


def is_permanent(err: BaseException) -> bool:
    """Whether retrying cannot help: the core refused the input, a stored input is bad, or the
    error is deterministic (the database refusing a value as such, SQLSTATE class 22; text
    that cannot be encoded; a number that overflows): the same input fails the same way."""
    return isinstance(
        err, InvisibleMapError | PermanentJobError | DataError | UnicodeError | OverflowError
    )


def through_outages(control: JobControl, job_id: int, what: str, call: Callable[[], T]) -> T:
    """``call()``, tried again while it fails with a database fault and the lease holds (see the
    package docstring); any other error, a lost lease, or a fault outlasting the lease is raised."""
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
    incremental_builds: str = "off",
) -> JobReport:
    """Run ``stages`` for ``lease``'s job and record how it ended; see the package docstring.
    ``time_budget_s`` > 0: the attempt fails for good (PermanentJobError, with the reason) once
    it has run that long, at the next :meth:`JobContext.check_interrupted`.
    ``incremental_builds``: "off", "serve" or "check" (``workers.incremental_builds.mode_of``).

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

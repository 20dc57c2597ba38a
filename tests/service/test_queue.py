"""The job queue (``app.storage.queue``) on SQLite and PostgreSQL: claim order, leases and their
fencing, the reaper, failure and back-off, cancel, retry, release, the log tail, the worker rows.

Time is moved with the functions' ``now=`` parameters, never by sleeping.
"""

from __future__ import annotations

import threading
from datetime import datetime, timedelta
from typing import Any

import pytest
from sqlalchemy import func, select

from app.storage import queue
from app.storage.db import SQLITE_BUSY_TIMEOUT_MS, Database
from app.storage.orm import Job, JobState, utc_now
from app.storage.queue import InvalidTransition, JobNotFound, Lease, LeaseLost

LEASE_S = 10.0


def s(seconds: float) -> timedelta:
    return timedelta(seconds=seconds)


def add_job(db: Database, *, now: datetime | None = None, **kwargs: Any) -> int:
    kwargs.setdefault("kind", "build_map")
    with db.transaction() as tx:
        return queue.enqueue(tx, map_id=None, session_id=None, now=now, **kwargs)


def job(db: Database, job_id: int) -> queue.JobInfo:
    with db.read() as tx:
        return queue.get_job(tx, job_id)


def claim(db: Database, now: datetime, worker_id: str = "w1") -> Lease:
    lease = queue.claim(db, worker_id=worker_id, lease_s=LEASE_S, now=now)
    assert lease is not None
    return lease


def job_row_snapshot(db: Database, job_id: int) -> dict[str, Any]:
    """Every column of the job's row, to show that a refused write changed nothing."""
    with db.read() as tx:
        row = tx.get(Job, job_id)
        assert row is not None
        return {c.key: getattr(row, c.key) for c in Job.__table__.columns}


# --------------------------------------------------------------------------- claiming


def test_claim_takes_highest_priority_then_oldest(db: Database) -> None:
    t0 = utc_now()
    low_1 = add_job(db, now=t0)
    high_1 = add_job(db, now=t0, priority=5)
    low_2 = add_job(db, now=t0)
    high_2 = add_job(db, now=t0, priority=5)

    order = [claim(db, t0).job_id for _ in range(4)]

    assert order == [high_1, high_2, low_1, low_2]
    assert queue.claim(db, worker_id="w1", lease_s=LEASE_S, now=t0) is None


def test_claim_sets_the_lease_and_counts_the_attempt(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0, params={"huber_k": 0}, max_attempts=4)

    lease = claim(db, t0 + s(1), worker_id="host:1:abc")

    assert (lease.job_id, lease.attempt, lease.max_attempts) == (job_id, 1, 4)
    assert lease.params == {"huber_k": 0}
    info = job(db, job_id)
    assert info.state == JobState.RUNNING
    assert info.lease_owner == "host:1:abc"
    assert info.attempts == 1
    assert info.started_at == t0 + s(1)
    assert info.log_tail.endswith("attempt 1 of 4 started by host:1:abc\n")
    assert lease.log_tail == info.log_tail


def test_claim_respects_run_after_and_kinds(db: Database) -> None:
    t0 = utc_now()
    later = add_job(db, now=t0 + s(30))
    other_kind = add_job(db, now=t0, kind="tune")

    assert queue.claim(db, worker_id="w", lease_s=LEASE_S, kinds=("build_map",), now=t0) is None
    assert queue.claim(db, worker_id="w", lease_s=LEASE_S, now=t0 + s(29)) is not None  # "tune"
    lease = queue.claim(db, worker_id="w", lease_s=LEASE_S, kinds=("build_map",), now=t0 + s(30))
    assert lease is not None
    assert lease.job_id == later
    assert job(db, other_kind).state == JobState.RUNNING


def test_an_idle_claim_writes_nothing_and_waits_for_no_writer(db: Database) -> None:
    # Idle workers ask several times a second. With nothing runnable the answer comes from a
    # read: on SQLite, no write lock is taken from (or waited for behind) the API's writers.
    future = add_job(db, now=utc_now() + s(3600))  # runnable in an hour: not now
    before = job_row_snapshot(db, future)
    answers: list[Lease | None] = []
    with db.engine.connect() as writer:
        writer.begin()  # on SQLite, BEGIN IMMEDIATE: another writer holds the write lock
        writer.exec_driver_sql("SELECT 1")
        claimer = threading.Thread(
            target=lambda: answers.append(queue.claim(db, worker_id="idle", lease_s=LEASE_S))
        )
        claimer.start()
        # A claim that waited for the lock would wait SQLite's busy timeout (30 s) and then
        # fail; half of it leaves a slow machine room without letting such a claim pass.
        claimer.join(timeout=SQLITE_BUSY_TIMEOUT_MS / 2000)
        finished_while_locked = not claimer.is_alive()
        writer.rollback()
    claimer.join(timeout=30)
    assert finished_while_locked
    assert answers == [None]
    assert job_row_snapshot(db, future) == before


def test_concurrent_claimers_never_get_the_same_job(database_url: str) -> None:
    jobs = 60
    claimers = 6
    setup = Database(database_url)
    for _ in range(jobs):
        add_job(setup)
    setup.dispose()
    claimed: list[list[int]] = [[] for _ in range(claimers)]
    errors: list[BaseException] = []
    start = threading.Barrier(claimers)

    def claim_all(k: int) -> None:
        db = Database(database_url)  # its own connections, as a separate process would have
        try:
            start.wait()
            while (lease := queue.claim(db, worker_id=f"w{k}", lease_s=LEASE_S)) is not None:
                claimed[k].append(lease.job_id)
        except BaseException as err:
            errors.append(err)
        finally:
            db.dispose()

    threads = [threading.Thread(target=claim_all, args=(k,)) for k in range(claimers)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)

    assert not errors
    everything = [job_id for ids in claimed for job_id in ids]
    assert len(everything) == jobs
    assert len(set(everything)) == jobs
    db = Database(database_url)
    with db.read() as tx:
        owners = dict(tx.execute(select(Job.id, Job.lease_owner)).all())
        attempts = set(tx.scalars(select(Job.attempts)))
    db.dispose()
    assert attempts == {1}
    for k, ids in enumerate(claimed):
        assert all(owners[job_id] == f"w{k}" for job_id in ids)


# --------------------------------------------------------------------------- leases


def test_heartbeat_extends_the_lease(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0)
    lease = claim(db, t0)

    assert queue.heartbeat(db, lease, lease_s=LEASE_S, now=t0 + s(8)) is False
    # the lease now runs to t0 + 18 s: not reaped at 15 s, and the worker may still write
    assert queue.reap_expired(db, backoff_s=0, now=t0 + s(15)) == 0
    queue.report_progress(db, lease, progress=0.5, stage="optimize", log_tail="", now=t0 + s(15))
    assert job(db, job_id).state == JobState.RUNNING
    assert queue.reap_expired(db, backoff_s=0, now=t0 + s(18.5)) == 1
    assert job(db, job_id).state == JobState.QUEUED


def test_heartbeat_and_progress_report_a_cancel_request(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0)
    lease = claim(db, t0)
    assert (
        queue.report_progress(db, lease, progress=0.1, stage="load", log_tail="", now=t0) is False
    )

    with db.transaction() as tx:
        info = queue.request_cancel(tx, job_id, now=t0 + s(1))

    assert info.state == JobState.RUNNING
    assert info.cancel_requested
    assert queue.heartbeat(db, lease, lease_s=LEASE_S, now=t0 + s(2)) is True
    assert queue.report_progress(db, lease, progress=0.2, stage="x", log_tail="", now=t0 + s(2))
    queue.mark_canceled(db, lease, log_tail="", now=t0 + s(3))
    info = job(db, job_id)
    assert info.state == JobState.CANCELED
    assert info.finished_at == t0 + s(3)
    assert info.lease_owner is None


def stale_writes(db: Database, lease: Lease, now: datetime) -> dict[str, Any]:
    """Every fenced write a worker can make, each as a thunk."""

    def finish() -> None:
        with db.transaction() as tx:
            queue.finish(tx, lease, log_tail="", now=now)

    return {
        "heartbeat": lambda: queue.heartbeat(db, lease, lease_s=LEASE_S, now=now),
        "report_progress": lambda: queue.report_progress(
            db, lease, progress=0.9, stage="store", log_tail="stale\n", now=now
        ),
        "finish": finish,
        "fail": lambda: queue.fail(
            db, lease, error="stale", permanent=True, backoff_s=0, log_tail="", now=now
        ),
        "mark_canceled": lambda: queue.mark_canceled(db, lease, log_tail="", now=now),
        "release": lambda: queue.release(db, lease, log_tail="", now=now),
    }


def test_an_expired_lease_cannot_write(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0)
    lease = claim(db, t0)
    before = job_row_snapshot(db, job_id)

    for name, write in stale_writes(db, lease, t0 + s(LEASE_S + 1)).items():
        with pytest.raises(LeaseLost):
            write()
        assert job_row_snapshot(db, job_id) == before, name


def test_a_requeued_and_reclaimed_job_refuses_the_old_lease(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0)
    old = claim(db, t0, worker_id="old")
    assert queue.reap_expired(db, backoff_s=0, now=t0 + s(11)) == 1
    new = claim(db, t0 + s(12), worker_id="new")
    assert new.token == old.token + 1
    before = job_row_snapshot(db, job_id)

    # at t0 + 13 s the old lease's expiry has not even passed on the clock the new one uses
    for name, write in stale_writes(db, old, t0 + s(13)).items():
        with pytest.raises(LeaseLost):
            write()
        assert job_row_snapshot(db, job_id) == before, name
    info = job(db, job_id)
    assert (info.state, info.lease_owner, info.attempts) == (JobState.RUNNING, "new", 2)


def test_finish_with_a_lost_lease_rolls_back_the_callers_transaction(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0)
    lease = claim(db, t0)
    queue.reap_expired(db, backoff_s=0, now=t0 + s(11))

    def store_result_and_finish() -> None:
        with db.transaction() as tx:
            queue.enqueue(tx, kind="written_with_the_result", map_id=None, session_id=None)
            queue.finish(tx, lease, log_tail="", now=t0 + s(12))

    with pytest.raises(LeaseLost):
        store_result_and_finish()

    with db.read() as tx:
        assert tx.scalar(select(func.count()).select_from(Job)) == 1
    assert job(db, job_id).state == JobState.QUEUED


def test_finish_marks_succeeded_in_the_callers_transaction(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0)
    lease = claim(db, t0)

    with db.transaction() as tx:
        queue.finish(tx, lease, log_tail=lease.log_tail, now=t0 + s(2))
        assert job(db, job_id).state == JobState.RUNNING  # not committed yet

    info = job(db, job_id)
    assert (info.state, info.progress, info.stage, info.lease_owner) == (
        JobState.SUCCEEDED,
        1.0,
        None,
        None,
    )
    assert info.finished_at == t0 + s(2)
    assert info.log_tail.endswith("succeeded\n")


# --------------------------------------------------------------------------- the reaper


def test_reaper_requeues_expired_jobs_with_backoff(db: Database) -> None:
    t0 = utc_now()
    expired = add_job(db, now=t0)
    alive = add_job(db, now=t0)
    claim(db, t0)
    claim(db, t0 + s(5))

    assert queue.reap_expired(db, backoff_s=3, now=t0 + s(LEASE_S)) == 1

    info = job(db, expired)
    assert info.state == JobState.QUEUED
    assert info.lease_owner is None
    assert info.run_after == t0 + s(LEASE_S + 3)
    assert info.attempts == 1
    assert "lease expired (worker lost); requeued" in info.log_tail
    assert job(db, alive).state == JobState.RUNNING
    assert queue.claim(db, worker_id="w", lease_s=LEASE_S, now=t0 + s(12)) is None
    assert claim(db, t0 + s(13)).attempt == 2


def test_reaper_backoff_doubles_with_each_lost_attempt(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0, max_attempts=3)
    claim(db, t0)
    queue.reap_expired(db, backoff_s=3, now=t0 + s(LEASE_S))
    assert job(db, job_id).run_after == t0 + s(LEASE_S + 3)
    t1 = t0 + s(LEASE_S + 3)
    claim(db, t1)

    queue.reap_expired(db, backoff_s=3, now=t1 + s(LEASE_S))

    info = job(db, job_id)
    assert info.state == JobState.QUEUED
    assert info.run_after == t1 + s(LEASE_S + 6)
    assert info.log_tail.splitlines()[-1].endswith("requeued in 6 s")


def test_reaper_fails_a_job_out_of_attempts(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0, max_attempts=2)
    claim(db, t0)
    queue.reap_expired(db, backoff_s=0, now=t0 + s(11))
    claim(db, t0 + s(11))

    assert queue.reap_expired(db, backoff_s=0, now=t0 + s(22)) == 1

    info = job(db, job_id)
    assert info.state == JobState.FAILED
    assert info.attempts == 2
    assert info.error is not None
    assert "lease expired" in info.error
    assert info.finished_at == t0 + s(22)


def test_reaper_cancels_an_expired_job_whose_cancel_was_requested(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0)
    claim(db, t0)
    with db.transaction() as tx:
        queue.request_cancel(tx, job_id, now=t0 + s(1))

    assert queue.reap_expired(db, backoff_s=0, now=t0 + s(11)) == 1

    info = job(db, job_id)
    assert info.state == JobState.CANCELED
    assert info.lease_owner is None
    assert info.finished_at == t0 + s(11)


# --------------------------------------------------------------------------- failing, releasing


def test_transient_failures_back_off_doubling_then_fail(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0, max_attempts=4)
    now = t0
    for attempt, delay_s in [(1, 2), (2, 4), (3, 8)]:
        lease = claim(db, now)
        assert lease.attempt == attempt
        state = queue.fail(
            db, lease, error="boom", permanent=False, backoff_s=2, log_tail=lease.log_tail, now=now
        )
        assert state == JobState.QUEUED
        info = job(db, job_id)
        assert (info.state, info.run_after, info.error) == (
            JobState.QUEUED,
            now + s(delay_s),
            "boom",
        )
        assert info.log_tail.endswith(f"retrying in {delay_s} s\n")
        assert queue.claim(db, worker_id="w", lease_s=LEASE_S, now=now + s(delay_s - 0.5)) is None
        now += s(delay_s)

    lease = claim(db, now)
    assert lease.attempt == 4
    state = queue.fail(
        db, lease, error="boom 4", permanent=False, backoff_s=2, log_tail="", now=now
    )

    assert state == JobState.FAILED
    info = job(db, job_id)
    assert (info.state, info.attempts, info.error) == (JobState.FAILED, 4, "boom 4")
    assert info.finished_at == now


def test_permanent_failure_fails_at_once(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0, max_attempts=3)
    lease = claim(db, t0)

    state = queue.fail(
        db, lease, error="load: bad upload", permanent=True, backoff_s=2, log_tail="", now=t0
    )

    assert state == JobState.FAILED
    info = job(db, job_id)
    assert (info.state, info.attempts, info.error) == (JobState.FAILED, 1, "load: bad upload")
    assert "permanent error" in info.log_tail


def test_release_gives_the_job_back_without_counting_the_attempt(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0, max_attempts=1)
    lease = claim(db, t0, worker_id="leaving")

    queue.release(db, lease, log_tail=lease.log_tail, now=t0 + s(1))

    info = job(db, job_id)
    assert (info.state, info.attempts, info.lease_owner) == (JobState.QUEUED, 0, None)
    assert info.run_after == t0 + s(1)
    assert info.log_tail.endswith("released by leaving (shutting down)\n")
    # with max_attempts=1 the job still gets its one attempt
    again = claim(db, t0 + s(1))
    assert again.attempt == 1


# --------------------------------------------------------------------------- cancel and retry


def finished_job(db: Database, t0: datetime, state: JobState) -> int:
    job_id = add_job(db, now=t0, priority=100)  # claimed before any other queued job
    lease = claim(db, t0)
    if state == JobState.SUCCEEDED:
        with db.transaction() as tx:
            queue.finish(tx, lease, log_tail="", now=t0)
    elif state == JobState.FAILED:
        queue.fail(db, lease, error="x", permanent=True, backoff_s=0, log_tail="", now=t0)
    else:
        queue.mark_canceled(db, lease, log_tail="", now=t0)
    assert job(db, job_id).state == state
    return job_id


def test_cancel_a_queued_job_cancels_it_now(db: Database) -> None:
    t0 = utc_now()
    job_id = add_job(db, now=t0)

    with db.transaction() as tx:
        info = queue.request_cancel(tx, job_id, now=t0 + s(1))

    assert info.state == JobState.CANCELED
    assert job(db, job_id).finished_at == t0 + s(1)
    assert queue.claim(db, worker_id="w", lease_s=LEASE_S, now=t0 + s(2)) is None


@pytest.mark.parametrize("state", [JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELED])
def test_cancel_a_finished_job_is_refused(db: Database, state: JobState) -> None:
    job_id = finished_job(db, utc_now(), state)

    with (
        pytest.raises(InvalidTransition, match=f"is {state.value}: cannot cancel"),
        db.transaction() as tx,
    ):
        queue.request_cancel(tx, job_id)

    assert job(db, job_id).state == state


def test_cancel_or_retry_an_unknown_job(db: Database) -> None:
    with pytest.raises(JobNotFound), db.transaction() as tx:
        queue.request_cancel(tx, 12345)
    with pytest.raises(JobNotFound), db.transaction() as tx:
        queue.retry(tx, 12345)


@pytest.mark.parametrize("state", [JobState.FAILED, JobState.CANCELED])
def test_retry_a_failed_or_canceled_job_queues_it_afresh(db: Database, state: JobState) -> None:
    t0 = utc_now()
    job_id = finished_job(db, t0, state)

    with db.transaction() as tx:
        info = queue.retry(tx, job_id, now=t0 + s(5))

    assert info.state == JobState.QUEUED
    assert (info.attempts, info.error, info.cancel_requested, info.finished_at) == (
        0,
        None,
        False,
        None,
    )
    assert info.log_tail.endswith("retry requested\n")
    assert claim(db, t0 + s(5)).attempt == 1


def test_retry_is_refused_unless_failed_or_canceled(db: Database) -> None:
    t0 = utc_now()
    queued = add_job(db, now=t0)
    running = add_job(db, now=t0, priority=1)
    claim(db, t0)
    succeeded = finished_job(db, t0, JobState.SUCCEEDED)

    for job_id, state in [(queued, "queued"), (running, "running"), (succeeded, "succeeded")]:
        with (
            pytest.raises(InvalidTransition, match=f"is {state}: cannot retry"),
            db.transaction() as tx,
        ):
            queue.retry(tx, job_id)
        assert job(db, job_id).state == state


# --------------------------------------------------------------------------- log tail


def test_log_tail_keeps_the_last_40_lines(db: Database) -> None:
    t0 = utc_now()
    log = ""
    for k in range(100):
        log = queue.append_log(log, f"line {k}", now=t0)
    lines = log.splitlines()
    assert len(lines) == queue.LOG_TAIL_LINES == 40
    assert lines[0].endswith("line 60")
    assert lines[-1].endswith("line 99")

    job_id = add_job(db, now=t0)
    lease = claim(db, t0)
    queue.report_progress(db, lease, progress=0.5, stage="optimize", log_tail=log, now=t0)
    assert job(db, job_id).log_tail == log
    queue.release(db, lease, log_tail=log, now=t0)
    stored = job(db, job_id).log_tail.splitlines()
    assert len(stored) == 40
    assert stored[-1].endswith("(shutting down)")
    assert stored[0].endswith("line 61")


# --------------------------------------------------------------------------- workers


def test_worker_rows_register_beat_and_unregister(db: Database) -> None:
    t0 = utc_now()
    queue.register_worker(db, worker_id="h:1:a", hostname="h", pid=1, now=t0)
    queue.register_worker(db, worker_id="h:2:b", hostname="h", pid=2, now=t0)
    queue.worker_heartbeat(
        db, worker_id="h:1:a", state="busy", current_job_id=7, jobs_done=3, now=t0 + s(20)
    )

    with db.read() as tx:
        alive = queue.alive_workers(tx, within_s=10, now=t0 + s(25))
    assert [(w.id, w.state, w.current_job_id, w.jobs_done) for w in alive] == [
        ("h:1:a", "busy", 7, 3)
    ]

    queue.unregister_worker(db, worker_id="h:1:a")
    with db.read() as tx:
        assert [w.id for w in queue.alive_workers(tx, within_s=60, now=t0 + s(25))] == ["h:2:b"]

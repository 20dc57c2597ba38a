"""Worker *processes*, as deployed: ``python -m workers.main`` killed with SIGKILL mid-job, stopped
with SIGTERM mid-job (once: finish; twice: release), four processes sharing sixteen jobs on
PostgreSQL, and the embedded mode's start/stop.

The jobs that must still be running when a signal arrives are simulated sessions of 6,000 poses
(seconds of work); the signal is sent once the job's row says it is in the ``optimize``
stage. A worker that is to be killed holds a short lease (2 s, heartbeat 0.5 s) so that its job
is reaped quickly; every other worker a long one, so that a loaded machine, where gtsam keeps the
GIL from the heartbeat thread for a whole Levenberg–Marquardt iteration, cannot expire the lease of
a worker that is alive (with 2 s, a rescuer under three test processes once lost its own lease
and ran the job a third time).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import select

from app.config import Settings
from app.storage.db import Database
from app.storage.orm import Job, JobState, MapVersion, WorkerRow
from tests.service.helpers import (
    REPO_ROOT,
    get_job,
    insert_session,
    job_states,
    session_bytes,
    simulated_bytes,
    version_count,
    wait_for,
)
from workers.main import start_worker_processes, stop_worker_processes

pytestmark = pytest.mark.slow

LONG_JOB_POSES = 6_000
#: The lease of a worker the test kills (its job is reaped this long after its last heartbeat), s.
DOOMED_LEASE_S = 2.0
#: The lease of every other worker, s: the default, far longer than a stalled heartbeat.
LIVE_LEASE_S = 30.0
WORKER_ENV = {
    "INVISIBLE_MAP_HEARTBEAT_S": "0.5",
    "INVISIBLE_MAP_POLL_S": "0.1",
    "INVISIBLE_MAP_RETRY_BACKOFF_S": "0",
}
#: Signal handling does not depend on the database (the queue operations it triggers are tested on
#: both backends in test_worker.py), so those process tests run on SQLite only.
SIGNALS_ARE_BACKEND_INDEPENDENT = pytest.mark.parametrize("database_url", ["sqlite"], indirect=True)
STARTED_BY = re.compile(r"started by (\S+)$", re.MULTILINE)


class WorkerProcess:
    """``python -m workers.main`` in a subprocess, its output in a file (shown on failure)."""

    def __init__(self, database_url: str, log_path: Path, *args: str, lease_s: float) -> None:
        env = {
            **os.environ,
            **WORKER_ENV,
            "INVISIBLE_MAP_LEASE_S": str(lease_s),
            "DATABASE_URL": database_url,
        }
        self.log_path = log_path
        self._log = log_path.open("wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "workers.main", *args],
            cwd=REPO_ROOT,
            env=env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
        )

    def output(self) -> str:
        self._log.flush()
        return self.log_path.read_text(errors="replace")

    def wait(self, timeout_s: float) -> int:
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise AssertionError(
                f"worker did not exit within {timeout_s} s; its log:\n{self.output()}"
            ) from None

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self._log.close()


@pytest.fixture
def workers() -> Iterator[list[WorkerProcess]]:
    """Started worker processes; any still running at the end of the test are killed."""
    started: list[WorkerProcess] = []
    yield started
    for worker in started:
        worker.close()


def start(
    workers: list[WorkerProcess],
    database_url: str,
    tmp_path: Path,
    *args: str,
    lease_s: float = LIVE_LEASE_S,
) -> WorkerProcess:
    log_path = tmp_path / f"worker-{len(workers) + 1}.log"
    worker = WorkerProcess(database_url, log_path, *args, lease_s=lease_s)
    workers.append(worker)
    return worker


def wait_until_optimizing(db: Database, job_id: int, worker: WorkerProcess) -> None:
    def optimizing() -> bool:
        if worker.proc.poll() is not None:
            raise AssertionError(f"the worker exited early:\n{worker.output()}")
        info = get_job(db, job_id)
        assert info.state in (JobState.QUEUED, JobState.RUNNING), info
        return info.state == JobState.RUNNING and info.stage == "optimize"

    wait_for(optimizing, timeout_s=30, what=f"job {job_id} to reach its optimize stage")


def started_by(log_tail: str) -> list[str]:
    return STARTED_BY.findall(log_tail)


def test_kill_9_mid_job_the_job_is_retried_and_stored_once(
    db: Database, database_url: str, tmp_path: Path, workers: list[WorkerProcess]
) -> None:
    job_id = insert_session(db, simulated_bytes(LONG_JOB_POSES)).job_id
    doomed = start(workers, database_url, tmp_path, lease_s=DOOMED_LEASE_S)
    wait_until_optimizing(db, job_id, doomed)

    os.kill(doomed.proc.pid, signal.SIGKILL)
    assert doomed.wait(10) == -signal.SIGKILL
    assert get_job(db, job_id).state == JobState.RUNNING  # nobody has noticed yet
    rescuer = start(workers, database_url, tmp_path)

    wait_for(
        lambda: get_job(db, job_id).state not in (JobState.QUEUED, JobState.RUNNING),
        timeout_s=60,
        what="the job to end",
    )
    info = get_job(db, job_id)
    assert info.state == JobState.SUCCEEDED, f"{info}\n{rescuer.output()}"
    assert info.attempts == 2
    assert "lease expired (worker lost); requeued" in info.log_tail
    first, second = started_by(info.log_tail)
    assert first != second
    assert version_count(db) == 1
    assert version_count(db, job_id=job_id) == 1
    with db.read() as tx:  # the dead worker's row stays (its heartbeat ages); the rescuer's too
        assert tx.get(WorkerRow, first) is not None
        assert tx.get(WorkerRow, second) is not None


@SIGNALS_ARE_BACKEND_INDEPENDENT
def test_sigterm_mid_job_finishes_the_job_and_exits_0(
    db: Database, database_url: str, tmp_path: Path, workers: list[WorkerProcess]
) -> None:
    job_id = insert_session(db, simulated_bytes(LONG_JOB_POSES)).job_id
    queued_behind = insert_session(db, session_bytes("onetag")).job_id
    worker = start(workers, database_url, tmp_path)
    wait_until_optimizing(db, job_id, worker)

    worker.proc.send_signal(signal.SIGTERM)

    assert worker.wait(60) == 0, worker.output()
    info = get_job(db, job_id)
    assert (info.state, info.attempts) == (JobState.SUCCEEDED, 1)
    assert version_count(db, job_id=job_id) == 1
    assert get_job(db, queued_behind).state == JobState.QUEUED  # it stopped claiming
    with db.read() as tx:
        assert tx.scalars(select(WorkerRow)).all() == []  # it unregistered


@SIGNALS_ARE_BACKEND_INDEPENDENT
def test_second_sigterm_releases_the_job(
    db: Database, database_url: str, tmp_path: Path, workers: list[WorkerProcess]
) -> None:
    job_id = insert_session(db, simulated_bytes(LONG_JOB_POSES)).job_id
    worker = start(workers, database_url, tmp_path)
    wait_until_optimizing(db, job_id, worker)

    worker.proc.send_signal(signal.SIGTERM)
    # Two signals sent at once may reach Python's handler as one (it runs only when the main
    # thread, busy in gtsam, next runs Python code), so the second follows the first's handling.
    wait_for(
        lambda: "SIGTERM received: finishing the current job" in worker.output(),
        timeout_s=10,
        what="the worker to handle the first SIGTERM",
        every_s=0.01,
    )
    worker.proc.send_signal(signal.SIGTERM)

    assert worker.wait(60) == 0, worker.output()
    info = get_job(db, job_id)
    assert (info.state, info.attempts, info.lease_owner) == (JobState.QUEUED, 0, None), info
    assert "released by" in info.log_tail
    assert "store:" not in info.log_tail
    assert version_count(db) == 0


def test_four_processes_sixteen_jobs_each_job_succeeds_exactly_once(
    postgres_url: str, tmp_path: Path, workers: list[WorkerProcess]
) -> None:
    db = Database(postgres_url)
    try:
        raw = session_bytes("onetag")
        job_ids = {insert_session(db, raw).job_id for _ in range(16)}
        supervisor = start(workers, postgres_url, tmp_path, "--processes", "4")

        wait_for(
            lambda: all(state == JobState.SUCCEEDED for state in job_states(db).values()),
            timeout_s=90,
            what="all 16 jobs to succeed",
        )
        supervisor.proc.send_signal(signal.SIGTERM)
        assert supervisor.wait(30) == 0, supervisor.output()

        with db.read() as tx:
            versions = tx.execute(select(MapVersion.job_id, MapVersion.number)).all()
            jobs = tx.execute(select(Job.id, Job.state, Job.attempts, Job.log_tail)).all()
            worker_rows = tx.scalars(select(WorkerRow)).all()
    finally:
        db.dispose()

    assert len(versions) == 16
    assert {job_id for job_id, _ in versions} == job_ids
    assert {number for _, number in versions} == {1}
    assert {(state, attempts) for _, state, attempts, _ in jobs} == {("succeeded", 1)}
    owners = [started_by(log_tail) for _, _, _, log_tail in jobs]
    assert all(len(by) == 1 for by in owners)
    assert len({by[0] for by in owners}) >= 2  # the work really was shared
    assert worker_rows == []  # every worker unregistered on the way out


@pytest.mark.parametrize("database_url", ["sqlite"], indirect=True)
def test_embedded_mode_starts_and_stops_worker_processes(db: Database, database_url: str) -> None:
    settings = Settings(database_url=database_url, lease_s=5, heartbeat_s=0.5, poll_s=0.05)
    job_ids = [insert_session(db, session_bytes("onetag")).job_id for _ in range(4)]

    procs = start_worker_processes(settings, 2)
    try:
        wait_for(
            lambda: all(get_job(db, j).state == JobState.SUCCEEDED for j in job_ids),
            timeout_s=60,
            what="the jobs to succeed",
        )
    finally:
        stop_worker_processes(procs, timeout_s=20)

    assert [proc.exitcode for proc in procs] == [0, 0]
    assert version_count(db) == 4
    with db.read() as tx:
        assert tx.scalars(select(WorkerRow)).all() == []


@pytest.mark.parametrize("nice", [0, 7])
def test_worker_processes_run_at_lower_cpu_priority_than_the_api(
    database_url: str, nice: int
) -> None:
    """INVISIBLE_MAP_WORKER_NICE: a build must not take the CPU from phones' requests."""
    settings = Settings(database_url=database_url, poll_s=0.05, worker_nice=nice)
    own = os.getpriority(os.PRIO_PROCESS, 0)
    procs = start_worker_processes(settings, 1)
    try:
        assert procs[0].pid is not None
        wait_for(
            lambda: os.getpriority(os.PRIO_PROCESS, procs[0].pid) == min(19, own + nice),
            timeout_s=30,
            what=f"the worker process at nice {own + nice}",
        )
    finally:
        stop_worker_processes(procs, timeout_s=20)


def test_kill_9_mid_sweep_every_trial_is_stored_exactly_once(
    db: Database, database_url: str, tmp_path: Path, workers: list[WorkerProcess]
) -> None:
    """A sweep's job whose worker is killed is run again by another worker, and the sweep ends
    with each of its trials stored once (the trials of the dead attempt were never stored)."""
    from app.domain.evaluation.sweep_plan import GRID_CHUNK, SweepPlan
    from app.domain.evaluation.tuning import Axis, SearchSpace
    from app.storage import sweeps
    from app.storage.orm import SweepTrial

    inserted = insert_session(db, session_bytes("occam_room"))
    space = SearchSpace((Axis("odom_linear_var_m2_per_s", 1e-6, 1e-1, 3 * GRID_CHUNK),))
    with db.transaction() as tx:
        sweep_id = sweeps.create_sweep(
            tx,
            map_id=inserted.map_id,
            session_id=inserted.session_id,
            plan=SweepPlan(method="grid", space=space),
            base_params={},
            ground_truth=None,
            max_attempts=3,
        )
        tx.get(Job, inserted.job_id).state = JobState.CANCELED.value  # only the sweep's jobs
    doomed = start(workers, database_url, tmp_path, lease_s=DOOMED_LEASE_S)

    def running_trials() -> Job | None:
        if doomed.proc.poll() is not None:
            raise AssertionError(f"the worker exited early:\n{doomed.output()}")
        with db.read() as tx:
            return tx.scalars(
                select(Job).where(Job.sweep_id == sweep_id, Job.stage == "trials")
            ).first()

    wait_for(lambda: running_trials() is not None, timeout_s=60, what="a sweep job's trials")
    os.kill(doomed.proc.pid, signal.SIGKILL)
    assert doomed.wait(10) == -signal.SIGKILL
    start(workers, database_url, tmp_path)

    def sweep_state() -> str:
        with db.read() as tx:
            return sweeps.get_sweep(tx, sweep_id).state

    wait_for(lambda: sweep_state() != "running", timeout_s=120, what="the sweep to end")
    with db.read() as tx:
        info = sweeps.get_sweep(tx, sweep_id)
        numbers = sorted(
            tx.scalars(select(SweepTrial.number).where(SweepTrial.sweep_id == sweep_id))
        )
        attempts = sorted(tx.scalars(select(Job.attempts).where(Job.sweep_id == sweep_id)))
    assert (info.state, info.trials_done) == ("succeeded", 3 * GRID_CHUNK)
    assert numbers == list(range(3 * GRID_CHUNK))
    assert attempts[-1] == 2  # the killed job ran again

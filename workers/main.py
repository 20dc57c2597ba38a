"""The worker: a loop that claims jobs from the database queue and runs them; and the supervisor
that runs several worker processes.

    python -m workers.main [--processes N]      # settings from the environment (app.config)
    invisible-map worker [--processes N]        # the same, through the CLI

One worker process runs one job at a time:

1. every ``heartbeat_s`` (and at its first pass) it requeues jobs whose lease expired
   (``queue.reap_expired``: their worker died);
2. it claims the next job (``queue.claim``) and runs its stages (``workers.pipeline``) while a
   :class:`~workers.lease.LeaseKeeper` thread renews the lease every ``heartbeat_s``;
3. idle, it sleeps ``poll_s`` between claims; its own row in the ``worker`` table says whether it
   is idle or busy, and with which job.

Shutdown: the first SIGTERM (or SIGINT) stops claiming and lets the current job finish, then the
worker exits 0; a second one gives the current job back to the queue (``queue.release``) at its next
stage boundary. With ``--processes N`` > 1 a supervisor starts N worker processes ("spawn"
context; each builds its own :class:`~app.storage.db.Database`), forwards SIGTERM and SIGINT to
them as SIGTERM, and exits once they have all exited. A worker process whose supervisor dies
finishes its job and exits.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import multiprocessing
import os
import signal
import socket
import sys
import threading
import time
import uuid
from collections.abc import Mapping, Sequence
from multiprocessing.connection import wait
from multiprocessing.process import BaseProcess
from types import FrameType

from app.config import Settings
from app.observability import logs
from app.storage import job_metrics, queue
from app.storage.db import Database, ServerTimeouts, database_fault, first_line
from app.storage.queue import Lease
from app.storage.sweeps import SWEEP_TRIALS
from workers import incremental_builds
from workers.allocator import preloading_jemalloc
from workers.failures import log_failure
from workers.lease import JobControl, LeaseKeeper
from workers.pipeline import OUTAGE_MAX_WAIT_S, PIPELINES, JobReport, Outcome, Stage, run_job
from workers.sweep import SWEEP_STAGES

logger = logging.getLogger("workers")

#: How often a worker process checks that its supervisor is still alive, s.
PARENT_CHECK_S = 1.0
#: How long a supervisor waits between looks at its children and at pending signals, s.
SUPERVISOR_TICK_S = 0.2
#: Extra time :func:`stop_worker_processes` gives workers to release their jobs, s.
RELEASE_GRACE_S = 5.0


def new_worker_id() -> str:
    """``{hostname}:{pid}:{8 hex digits}``, unique across machines and restarts."""
    return f"{socket.gethostname()[:60]}:{os.getpid()}:{uuid.uuid4().hex[:8]}"


#: Every job kind a worker runs: building maps, and the trials of sweeps.
JOB_PIPELINES: Mapping[str, Sequence[Stage]] = {**PIPELINES, SWEEP_TRIALS: SWEEP_STAGES}


class Worker:
    """Claims and runs jobs, one at a time; see the module docstring.

    ``pipelines`` maps each job kind this worker runs to its stages (default:
    :data:`JOB_PIPELINES`); it only claims those kinds.
    """

    def __init__(
        self,
        db: Database,
        settings: Settings,
        *,
        pipelines: Mapping[str, Sequence[Stage]] | None = None,
        worker_id: str | None = None,
    ) -> None:
        self.db = db
        self.settings = settings
        self.pipelines = dict(pipelines if pipelines is not None else JOB_PIPELINES)
        self.worker_id = worker_id or new_worker_id()
        self.jobs_done = 0
        self.current_job_id: int | None = None
        self._stop_requested = False
        self._release_requested = False
        self._control: JobControl | None = None
        self._next_reap_s = 0.0
        self._next_beat_s = 0.0

    # ----------------------------------------------------------------------- one job

    def run_once(self) -> bool:
        """Reap expired leases (at most every ``heartbeat_s``), claim one job and run it.
        Returns whether a job ran."""
        now_s = time.monotonic()
        if now_s >= self._next_reap_s:
            self._next_reap_s = now_s + self.settings.heartbeat_s
            reaped = queue.reap_expired(self.db, backoff_s=self.settings.retry_backoff_s)
            if reaped:
                logger.warning(
                    "requeued or ended %d job(s) whose lease expired",
                    reaped,
                    extra={"action": "reap", "job_id": None, "session_id": None},
                )
        lease = queue.claim(
            self.db,
            worker_id=self.worker_id,
            lease_s=self.settings.lease_s,
            kinds=tuple(self.pipelines),
        )
        if lease is None:
            return False
        self._run(lease)
        return True

    def _run(self, lease: Lease) -> None:
        extra = {"job_id": lease.job_id, "map_id": lease.map_id, "session_id": lease.session_id}
        logger.info(
            "job %d (%s, attempt %d of %d) started",
            lease.job_id,
            lease.kind,
            lease.attempt,
            lease.max_attempts,
            extra={"action": "job_started", **extra},
        )
        control = JobControl()
        self._control = control  # before reading the flag: a concurrent request_stop sets one
        control.release_requested = self._release_requested
        self.current_job_id = lease.job_id
        self._beat(state="busy")
        try:
            with LeaseKeeper(
                self.db,
                lease,
                control=control,
                lease_s=self.settings.lease_s,
                heartbeat_s=self.settings.heartbeat_s,
                on_beat=lambda: self._beat(state="busy"),
            ):
                report = run_job(
                    self.db,
                    lease,
                    stages=self.pipelines[lease.kind],
                    control=control,
                    retry_backoff_s=self.settings.retry_backoff_s,
                    time_budget_s=self.settings.job_time_budget_s,
                    incremental_builds=incremental_builds.mode_of(self.settings),
                )
        except Exception as err:
            # Recording the outcome failed (the database went away for longer than the lease):
            # the lease will expire and the reaper requeue the job.
            log_failure(
                logger,
                f"job {lease.job_id}: could not record its outcome",
                err,
                level=logging.ERROR,
                extra={"action": "job_error"},
            )
            report = JobReport(outcome=Outcome.LEASE_LOST)
        finally:
            self._control = None
            self.current_job_id = None
        if report.outcome not in (Outcome.LEASE_LOST, Outcome.RELEASED):
            self.jobs_done += 1
        self._record_stages(lease, report)
        self._log_outcome(lease, report, extra)
        self._beat(state="idle")

    def _record_stages(self, lease: Lease, report: JobReport) -> None:
        """Store how long the attempt's stages took (``/metrics``); best effort."""
        try:
            job_metrics.record_stages(
                self.db,
                job_id=lease.job_id,
                kind=lease.kind,
                attempt=lease.attempt,
                durations_s=report.stage_durations_s,
            )
        except Exception as err:
            log_failure(logger, f"job {lease.job_id}: could not store its stage durations", err)

    @staticmethod
    def _log_outcome(lease: Lease, report: JobReport, extra: dict[str, int | None]) -> None:
        took = f"after {report.duration_s:.2f} s"
        level = logging.INFO
        if report.outcome == Outcome.SUCCEEDED:
            number = report.version.number if report.version is not None else "?"
            summary = f"succeeded {took}: map {lease.map_id} version {number}"
        elif report.outcome in (Outcome.FAILED, Outcome.RETRYING):
            summary, level = f"{report.outcome.value} {took}: {report.error}", logging.WARNING
        elif report.outcome == Outcome.LEASE_LOST:
            summary, level = f"abandoned {took}: lease lost, nothing written", logging.WARNING
        else:
            summary = f"{report.outcome.value} {took}"
        logger.log(
            level,
            "job %d %s",
            lease.job_id,
            summary,
            extra={"action": f"job_{report.outcome.value}", **extra},
        )

    # ----------------------------------------------------------------------- the loop

    def run(self, stop: threading.Event) -> None:
        """Claim and run jobs until ``stop`` is set (or a signal asks to stop): register the
        worker's row at the start, keep it current, remove it at the end. A database that does
        not answer (at the start or later) is waited for, with one log line per outage."""
        logger.info(
            "worker %s started", self.worker_id, extra={"action": "worker_started", "job_id": None}
        )
        registered = False
        try:
            outage_wait_s = 0.0  # > 0 while the database is unavailable
            while not (stop.is_set() or self._stop_requested):
                try:
                    if not registered:
                        queue.register_worker(
                            self.db,
                            worker_id=self.worker_id,
                            hostname=socket.gethostname(),
                            pid=os.getpid(),
                        )
                        registered = True
                    ran = self.run_once()
                except Exception as err:
                    outage_wait_s = self._loop_error(err, outage_wait_s)
                    stop.wait(outage_wait_s or self.settings.poll_s)
                    continue
                if outage_wait_s:
                    outage_wait_s = 0.0
                    logger.info(
                        "the database answers again",
                        extra={"action": "database_back", "job_id": None},
                    )
                if not ran:
                    if time.monotonic() >= self._next_beat_s:
                        self._beat(state="idle")
                    stop.wait(self.settings.poll_s)
        finally:
            try:
                if registered:
                    queue.unregister_worker(self.db, worker_id=self.worker_id)
            except Exception as err:
                log_failure(logger, f"could not remove worker row {self.worker_id}", err)
            logger.info(
                "worker %s stopped after %d job(s)",
                self.worker_id,
                self.jobs_done,
                extra={"action": "worker_stopped", "job_id": None},
            )

    def _loop_error(self, err: Exception, outage_wait_s: float) -> float:
        """Log an error of the loop; returns how long to wait before the next try if it is a
        database fault (one line when the outage starts, the wait doubling up to
        :data:`OUTAGE_MAX_WAIT_S`), else 0 (a traceback, and the next try after ``poll_s``)."""
        fault = database_fault(err)
        if fault is None:
            logger.exception(
                "worker loop error; going on in %g s",
                self.settings.poll_s,
                extra={"action": "worker_error", "job_id": None},
            )
            return 0.0
        if not outage_wait_s:
            logger.warning(
                "%s (%s): waiting for the database",
                fault.value,
                first_line(err),
                extra={"action": fault.value, "job_id": None},
            )
        return min(max(2 * outage_wait_s, self.settings.poll_s), OUTAGE_MAX_WAIT_S)

    def _beat(self, *, state: str) -> None:
        self._next_beat_s = time.monotonic() + self.settings.heartbeat_s
        try:
            queue.worker_heartbeat(
                self.db,
                worker_id=self.worker_id,
                state=state,
                current_job_id=self.current_job_id,
                jobs_done=self.jobs_done,
            )
        except Exception as err:
            log_failure(logger, "worker heartbeat failed", err)

    # ----------------------------------------------------------------------- shutdown

    def request_stop(self) -> None:
        """Stop claiming; the current job finishes. Called again: release the current job at
        its next stage boundary. Safe in a signal handler (sets flags only)."""
        if self._stop_requested:
            self._release_requested = True
            control = self._control
            if control is not None:
                control.release_requested = True
        self._stop_requested = True

    def handle_signal(self, signum: int) -> None:
        """What SIGTERM/SIGINT do: :meth:`request_stop`, and say so in the log."""
        first = not self._stop_requested
        self.request_stop()
        logger.info(
            "%s received: %s",
            signal.Signals(signum).name,
            "finishing the current job" if first else "releasing the current job",
            extra={"action": "signal", "job_id": self.current_job_id},
        )


def handle_signals(worker: Worker, signums: Sequence[int]) -> None:
    """Make each of ``signums`` call ``worker.handle_signal`` (call from the main thread).

    The work is done by a thread woken through ``signal.set_wakeup_fd``, to which the C-level
    handler writes each signal as it arrives: a Python handler would run only when the main thread
    next runs Python code (not while it is inside gtsam), would fold signals arriving meanwhile
    into one, and must not log (re-entrant writes to a stream fail).
    """
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    wanted = set(signums)
    for signum in wanted:
        signal.signal(signum, _wake_only)
    signal.set_wakeup_fd(write_fd)

    def dispatch() -> None:
        while True:
            for signum in os.read(read_fd, 64):
                if signum in wanted:
                    worker.handle_signal(signum)

    threading.Thread(target=dispatch, name="signals", daemon=True).start()


def _wake_only(_signum: int, _frame: FrameType | None) -> None:
    """The Python-level handler: nothing (the wakeup fd carries the signal to ``dispatch``)."""


# --------------------------------------------------------------------------- processes


def configure_logging(log_format: str = "text") -> None:
    """Log to stderr, one line per record (if nobody configured logging yet): as text, or with
    ``log_format="json"`` as one JSON object per line (``app.observability.logs``).

    httpx's line per request (INFO) is left out: the only client in these processes is
    ``serve --demo`` polling its own API, whose access log already has each request."""
    if log_format == "json":
        logs.configure_json_logging()
    else:
        logging.basicConfig(level=logging.INFO, format=logs.TEXT_FORMAT)
    logging.getLogger("httpx").setLevel(logging.WARNING)


def run_worker(settings: Settings, *, signums: Sequence[int]) -> int:
    """Run one worker in this process until a signal in ``signums`` stops it; returns 0."""
    lower_priority(settings)
    db = Database(settings.resolved_database_url, timeouts=ServerTimeouts.of(settings))
    try:
        worker = Worker(db, settings)
        handle_signals(worker, signums)
        worker.run(threading.Event())
    finally:
        db.dispose()
    return 0


def lower_priority(settings: Settings) -> None:
    """Lower this process's CPU priority by ``INVISIBLE_MAP_WORKER_NICE`` (best effort)."""
    if settings.worker_nice:
        try:
            os.nice(settings.worker_nice)
        except OSError as err:
            logger.warning("could not lower the worker's priority: %s", err)


def _watch_parent(parent_pid: int, worker: Worker) -> None:
    while os.getppid() == parent_pid:
        time.sleep(PARENT_CHECK_S)
    logger.warning("supervisor %d is gone: stopping", parent_pid, extra={"action": "orphaned"})
    worker.request_stop()


def _worker_process_main(settings: Settings, parent_pid: int) -> None:
    """Entry point of a worker process started by the supervisor (module level: spawn pickles
    it). SIGINT is ignored: a Ctrl-C reaches the whole process group, and the supervisor
    forwards it as SIGTERM, which must count once."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    configure_logging(settings.log_format)
    lower_priority(settings)
    db = Database(settings.resolved_database_url, timeouts=ServerTimeouts.of(settings))
    try:
        worker = Worker(db, settings)
        handle_signals(worker, [signal.SIGTERM])
        threading.Thread(
            target=_watch_parent, args=(parent_pid, worker), name="parent-watch", daemon=True
        ).start()
        worker.run(threading.Event())
    finally:
        db.dispose()


def start_worker_processes(
    settings: Settings, processes: int, *, first_number: int = 1
) -> list[BaseProcess]:
    """Start ``processes`` worker processes (spawn context, preloading jemalloc where the
    machine has it: ``workers.allocator``), named ``worker-{first_number}``, …, and return them
    (none for 0)."""
    if processes < 0:
        raise ValueError(f"processes must be at least 0, got {processes}")
    context = multiprocessing.get_context("spawn")
    procs: list[BaseProcess] = [
        context.Process(
            target=_worker_process_main,
            args=(settings, os.getpid()),
            name=f"worker-{first_number + k}",
        )
        for k in range(processes)
    ]
    with preloading_jemalloc():
        for proc in procs:
            proc.start()
    return procs


def _signal_all(procs: Sequence[BaseProcess], signum: int) -> None:
    for proc in procs:
        if proc.is_alive() and proc.pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(proc.pid, signum)


def _join_all(procs: Sequence[BaseProcess], deadline_s: float) -> None:
    for proc in procs:
        proc.join(max(0.0, deadline_s - time.monotonic()))


def stop_worker_processes(procs: Sequence[BaseProcess], timeout_s: float) -> None:
    """Stop worker processes: SIGTERM (finish the current job) and wait up to ``timeout_s``;
    then a second SIGTERM (release the job at its next stage boundary) and wait up to
    :data:`RELEASE_GRACE_S`; then SIGKILL (the job's lease expires and it is retried)."""
    _signal_all(procs, signal.SIGTERM)
    _join_all(procs, time.monotonic() + timeout_s)
    if any(proc.is_alive() for proc in procs):
        _signal_all(procs, signal.SIGTERM)
        _join_all(procs, time.monotonic() + RELEASE_GRACE_S)
    for proc in procs:
        if proc.is_alive():
            logger.warning("worker process %s did not stop: killing it", proc.pid)
            proc.kill()
            proc.join()


def run_worker_processes(settings: Settings, processes: int) -> int:
    """Run ``processes`` workers until SIGTERM or SIGINT; returns the exit status (0 when every
    worker exited cleanly). With one process the worker runs in this process; with more, this
    process supervises them: it forwards each SIGTERM/SIGINT to them as SIGTERM (so the second
    releases their jobs), and when one exits unexpectedly it stops the others and returns 1 (a
    service manager then restarts the whole)."""
    if processes < 1:
        raise ValueError(f"processes must be at least 1, got {processes}")
    # `invisible-map worker` logs like the worker processes it starts
    configure_logging(settings.log_format)
    if processes == 1:
        return run_worker(settings, signums=[signal.SIGTERM, signal.SIGINT])

    pending: list[int] = []

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        pending.append(signum)

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        procs = start_worker_processes(settings, processes)
        logger.info(
            "started %d worker processes: %s",
            processes,
            ", ".join(str(p.pid) for p in procs),
            extra={"action": "supervisor_started"},
        )
        status = 0
        stopping = False
        while any(proc.is_alive() for proc in procs):
            wait([p.sentinel for p in procs if p.is_alive()], timeout=SUPERVISOR_TICK_S)
            while pending:
                name = signal.Signals(pending.pop(0)).name
                logger.info("%s received: forwarding to the workers", name)
                _signal_all(procs, signal.SIGTERM)
                stopping = True
            crashed = [p for p in procs if not p.is_alive() and p.exitcode != 0]
            if crashed and not stopping:
                logger.error(
                    "worker process %s exited with status %s: stopping the others",
                    crashed[0].pid,
                    crashed[0].exitcode,
                    extra={"action": "worker_crashed"},
                )
                _signal_all(procs, signal.SIGTERM)
                stopping = True
        if any(proc.exitcode != 0 for proc in procs):
            status = 1
        return status
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m workers.main [--processes N]``: run workers with settings from the
    environment; returns the exit status."""
    parser = argparse.ArgumentParser(
        prog="python -m workers.main", description="Run Invisible Map job workers."
    )
    parser.add_argument(
        "--processes", type=int, default=1, help="worker processes to run (default 1)"
    )
    parser.add_argument(
        "--log-format",
        choices=["text", "json"],
        help="text (the default, INVISIBLE_MAP_LOG_FORMAT) or json: one JSON object per line",
    )
    args = parser.parse_args(argv)
    if args.processes < 1:
        parser.error("--processes must be at least 1")
    settings = Settings(**({} if args.log_format is None else {"log_format": args.log_format}))
    configure_logging(settings.log_format)
    return run_worker_processes(settings, args.processes)


if __name__ == "__main__":
    sys.exit(main())

"""The supervisor of ``serve``'s worker processes: keeps ``--workers N`` of them alive.

    supervisor = WorkerSupervisor(settings, processes=2)
    supervisor.start()          # starts the processes and a thread that watches them
    supervisor.alive            # how many are alive now (``/readyz``, ``/v1/info``)
    supervisor.stop(timeout_s=30.0)

A worker process that dies (killed, out of memory, a crash in native code) is reaped at once (no
zombie), its death is logged with its exit status or signal, and a new process takes its place
after a back-off: :data:`FIRST_RESTART_S`, doubling for each death in a row up to
:data:`MAX_RESTART_S`; a process that lived :data:`STABLE_S` or more resets the back-off. The dead
process's lease is ended at once (``queue.expire_leases_of_dead_process``), so that the reaper
of any worker (the replacement's at its first pass) requeues its job now rather than when the
lease would have run out (docs/architecture.md §1, "Lease and heartbeats"); if the database does
not answer, the lease runs out as after any worker's death.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import wait
from multiprocessing.process import BaseProcess

from app.config import Settings
from app.storage import queue
from app.storage.db import Database, first_line
from workers.main import SUPERVISOR_TICK_S, start_worker_processes, stop_worker_processes

logger = logging.getLogger("workers.supervisor")

#: The wait before the first restart of a process that died, s.
FIRST_RESTART_S = 0.5
#: The longest wait between restarts of a process that keeps dying, s.
MAX_RESTART_S = 60.0
#: A process that lived this long resets its back-off to :data:`FIRST_RESTART_S`, s.
STABLE_S = 60.0


def describe_exit(exitcode: int | None) -> str:
    """``"killed by SIGKILL"``, ``"exited with status 1"`` (multiprocessing's negative exit codes
    are signals)."""
    if exitcode is None:
        return "ended"
    if exitcode < 0:
        try:
            return f"killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exited with status {exitcode}"


@dataclass(slots=True)
class ProcessSlot:
    """One of the N places a supervised process fills (a worker process here, an API process
    in ``app.cli.api_processes``), with its restart back-off."""

    number: int  #: worker-{number}, api-{number}
    process: BaseProcess | None = None
    started_s: float = 0.0
    restart_at_s: float | None = None  # when the next process starts (after a death)
    backoff_s: float = FIRST_RESTART_S

    def schedule_restart(self, now_s: float, lived_s: float) -> float:
        """After this slot's process died, having lived ``lived_s``: when the next one starts.
        The delay, s: :data:`FIRST_RESTART_S` after a life of :data:`STABLE_S` or more, else
        doubled for each death in a row, up to :data:`MAX_RESTART_S`."""
        if lived_s >= STABLE_S:
            self.backoff_s = FIRST_RESTART_S
        delay_s = self.backoff_s
        self.restart_at_s = now_s + delay_s
        self.backoff_s = min(2 * delay_s, MAX_RESTART_S)
        return delay_s

    def restart_due(self, now_s: float) -> bool:
        """Whether a replacement is scheduled and its time has come."""
        return self.process is None and self.restart_at_s is not None and now_s >= self.restart_at_s


class WorkerSupervisor:
    """Starts ``processes`` worker processes and keeps that many alive until :meth:`stop`."""

    def __init__(self, settings: Settings, processes: int) -> None:
        if processes < 0:
            raise ValueError(f"processes must be at least 0, got {processes}")
        self.settings = settings
        self._slots = [ProcessSlot(number=k + 1) for k in range(processes)]
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._restarts = 0
        self._db: Database | None = None  # made on the first death

    # ----------------------------------------------------------------------- status

    @property
    def configured(self) -> int:
        """How many worker processes this supervisor keeps (``--workers``)."""
        return len(self._slots)

    @property
    def alive(self) -> int:
        """How many of them are alive now."""
        with self._lock:
            return sum(
                1 for slot in self._slots if slot.process is not None and slot.process.is_alive()
            )

    @property
    def restarts(self) -> int:
        """How many processes were started in place of one that died."""
        return self._restarts

    @property
    def pids(self) -> list[int]:
        """The process ids of the live worker processes."""
        with self._lock:
            return [
                slot.process.pid
                for slot in self._slots
                if slot.process is not None and slot.process.pid is not None
                if slot.process.is_alive()
            ]

    # ----------------------------------------------------------------------- life

    def start(self) -> None:
        """Start the processes and the thread that watches them."""
        procs = start_worker_processes(self.settings, len(self._slots))
        now_s = time.monotonic()
        with self._lock:
            for slot, proc in zip(self._slots, procs, strict=True):
                slot.process, slot.started_s = proc, now_s
        if self._slots:
            self._thread = threading.Thread(
                target=self._watch, name="worker-supervisor", daemon=True
            )
            self._thread.start()

    def stop(self, timeout_s: float) -> None:
        """Stop restarting, then stop the processes as :func:`stop_worker_processes` does."""
        self._stopping.set()
        if self._thread is not None:
            self._thread.join()
        with self._lock:
            procs = [slot.process for slot in self._slots if slot.process is not None]
        stop_worker_processes(procs, timeout_s=timeout_s)
        if self._db is not None:
            self._db.dispose()

    def _watch(self) -> None:
        while not self._stopping.is_set():
            with self._lock:
                sentinels = [
                    slot.process.sentinel
                    for slot in self._slots
                    if slot.process is not None and slot.process.is_alive()
                ]
            if sentinels:
                wait(sentinels, timeout=SUPERVISOR_TICK_S)
            else:
                self._stopping.wait(SUPERVISOR_TICK_S)
            if self._stopping.is_set():
                return
            try:
                self._tend(time.monotonic())
            except Exception:  # a failed start (fork refused, …): try again next tick
                logger.exception(
                    "supervising the worker processes failed; trying again",
                    extra={"action": "supervisor_error"},
                )

    def _end_leases_of(self, pid: int | None) -> None:
        """End the dead process's leases now (its job is requeued by the next reaper pass)."""
        if pid is None:
            return
        try:
            if self._db is None:
                self._db = Database(self.settings.resolved_database_url)
            ended = queue.expire_leases_of_dead_process(
                self._db, hostname=socket.gethostname(), pid=pid
            )
        except Exception as err:  # the lease runs out by itself
            logger.warning("could not end the leases of worker pid %s: %s", pid, first_line(err))
            return
        if ended:
            logger.warning(
                "ended the lease of %d job(s) of dead worker pid %s: they are requeued now",
                ended,
                pid,
                extra={"action": "dead_worker_leases", "job_id": None},
            )

    def _tend(self, now_s: float) -> None:
        """Reap the dead, schedule their replacement, start the replacements that are due."""
        for slot in self._slots:
            proc = slot.process
            if proc is not None and not proc.is_alive():  # is_alive() reaps it (waitpid)
                proc.join(0)
                lived_s = now_s - slot.started_s
                self._end_leases_of(proc.pid)
                with self._lock:
                    slot.process = None
                logger.error(
                    "worker process worker-%d (pid %s) %s after %.1f s; restarting it in %g s",
                    slot.number,
                    proc.pid,
                    describe_exit(proc.exitcode),
                    lived_s,
                    slot.schedule_restart(now_s, lived_s),
                    extra={"action": "worker_died", "job_id": None},
                )
            if slot.restart_due(now_s) and not self._stopping.is_set():
                (new,) = start_worker_processes(self.settings, 1, first_number=slot.number)
                with self._lock:
                    slot.process, slot.started_s, slot.restart_at_s = new, now_s, None
                self._restarts += 1
                logger.warning(
                    "worker process worker-%d restarted as pid %s (restart %d; supervisor pid %d)",
                    slot.number,
                    new.pid,
                    self._restarts,
                    os.getpid(),
                    extra={"action": "worker_restarted", "job_id": None},
                )

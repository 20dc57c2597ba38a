"""The API as ``serve`` runs it (:func:`uvicorn_server`), and ``serve --api-processes N``: N API
processes on ``serve``'s one listening socket.

    status = WorkerPoolStatus.publishing(supervisor)  # the worker supervisor's figures, shared
    api = ApiProcessSupervisor(settings, listener, processes=4, worker_status=status)
    api.start()
    api.run_until(stop_event, tick=lambda: status.publish(supervisor))
    api.stop(timeout_s=30.0)

``serve`` binds the socket, migrates the database and starts the worker supervisor (one per
``serve``, not one per API process) before it starts the API processes; each is a spawned
process (``multiprocessing``, spawn context) that inherits the socket and runs uvicorn on it, so
the kernel hands each new connection to one of them. The database is the only state they share;
what each keeps in memory is a cache or a per-process bound (docs/operations.md, "Several API
processes"). ``/readyz`` and ``/v1/info`` report the worker processes through
:class:`WorkerPoolStatus`, which ``serve`` refreshes every :data:`TICK_S`.

An API process that dies (killed, out of memory, a crash in native code) is logged with its exit
status or signal and replaced after the worker supervisor's back-off
(``workers.supervisor``: 0.5 s doubling up to 60 s; reset after 60 s of life). One that exits
with :data:`STARTUP_FAILED` could not start at all (its log says why): ``serve`` then stops.
Each process answers with ``X-Api-Process: <number>`` (1…N), so an operator can see which one
answered. An API process whose ``serve`` is gone (killed with SIGKILL) stops by itself.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import gc
import logging
import multiprocessing
import os
import signal
import socket
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import wait
from multiprocessing.process import BaseProcess
from typing import TYPE_CHECKING, Any

from app.config import Settings
from app.services.system import WorkerPool
from workers.supervisor import ProcessSlot, describe_exit

if TYPE_CHECKING:
    import uvicorn

logger = logging.getLogger("app.cli.api_processes")

#: How often ``serve`` looks at its API processes and publishes the workers' figures, s.
TICK_S = 0.2
#: An API process's exit status when uvicorn could not start (its own ``sys.exit(3)``).
STARTUP_FAILED = 3
#: How often an API process checks that its ``serve`` is still alive, s.
PARENT_WATCH_S = 0.5


class WorkerPoolStatus:
    """The worker supervisor's figures (configured, alive, restarts) in shared memory: ``serve``
    writes them, its API processes read them as their :class:`WorkerPool` (``/readyz``,
    ``/v1/info``), at most :data:`TICK_S` old."""

    def __init__(self) -> None:
        context = multiprocessing.get_context("spawn")
        # three aligned 64-bit integers, one writer: no lock needed
        self._values: Any = context.RawArray(ctypes.c_longlong, 3)

    def publish(self, pool: WorkerPool) -> None:
        self._values[0], self._values[1], self._values[2] = (
            pool.configured,
            pool.alive,
            pool.restarts,
        )

    @property
    def configured(self) -> int:
        return int(self._values[0])

    @property
    def alive(self) -> int:
        return int(self._values[1])

    @property
    def restarts(self) -> int:
        return int(self._values[2])


class ApiProcessSupervisor:
    """Starts ``processes`` API processes on ``listener`` and keeps that many alive."""

    def __init__(
        self,
        settings: Settings,
        listener: socket.socket,
        *,
        processes: int,
        worker_status: WorkerPoolStatus | None,
    ) -> None:
        if processes < 1:
            raise ValueError(f"processes must be at least 1, got {processes}")
        self.settings = settings
        self.listener = listener
        self.worker_status = worker_status
        self._slots = [ProcessSlot(number=k + 1) for k in range(processes)]
        self.restarts = 0
        #: Why serving cannot go on (an API process could not start), or None.
        self.failure: str | None = None

    @property
    def pids(self) -> list[int]:
        """The live API processes' ids, by number."""
        return [
            slot.process.pid
            for slot in self._slots
            if slot.process is not None and slot.process.pid is not None
            if slot.process.is_alive()
        ]

    def start(self) -> None:
        for slot in self._slots:
            self._start(slot, time.monotonic())

    def _start(self, slot: ProcessSlot, now_s: float) -> BaseProcess:
        context = multiprocessing.get_context("spawn")
        process = context.Process(
            target=api_process_main,
            args=(self.settings, self.listener, self.worker_status, slot.number, os.getpid()),
            name=f"api-{slot.number}",
        )
        process.start()
        slot.process, slot.started_s, slot.restart_at_s = process, now_s, None
        logger.info(
            "API process api-%d started as pid %s",
            slot.number,
            process.pid,
            extra={"action": "api_process_started"},
        )
        return process

    def run_until(self, stop: threading.Event, tick: Callable[[], None] | None = None) -> None:
        """Watch the processes (replace the dead) until ``stop`` is set or one cannot start."""
        while not stop.is_set() and self.failure is None:
            sentinels = [
                slot.process.sentinel
                for slot in self._slots
                if slot.process is not None and slot.process.is_alive()
            ]
            if sentinels:
                wait(sentinels, timeout=TICK_S)
            else:
                stop.wait(TICK_S)
            if tick is not None:
                tick()
            if stop.is_set():
                return
            self.tend(time.monotonic())

    def tend(self, now_s: float) -> None:
        """Reap the dead, schedule their replacement, start the replacements that are due."""
        for slot in self._slots:
            process = slot.process
            if process is not None and not process.is_alive():  # is_alive() reaps it
                process.join(0)
                lived_s = now_s - slot.started_s
                slot.process = None
                if process.exitcode == STARTUP_FAILED:
                    self.failure = (
                        f"API process api-{slot.number} (pid {process.pid}) could not start "
                        "(see the log above)"
                    )
                    logger.error(self.failure, extra={"action": "api_process_failed"})
                    return
                logger.error(
                    "API process api-%d (pid %s) %s after %.1f s; restarting it in %g s",
                    slot.number,
                    process.pid,
                    describe_exit(process.exitcode),
                    lived_s,
                    slot.schedule_restart(now_s, lived_s),
                    extra={"action": "api_process_died"},
                )
            if slot.restart_due(now_s):
                new = self._start(slot, now_s)
                self.restarts += 1
                logger.warning(
                    "API process api-%d restarted as pid %s (restart %d)",
                    slot.number,
                    new.pid,
                    self.restarts,
                    extra={"action": "api_process_restarted"},
                )

    def stop(self, timeout_s: float) -> None:
        """SIGTERM to every API process (uvicorn's graceful shutdown: it stops accepting and
        finishes the requests in flight), wait up to ``timeout_s``, then SIGKILL."""
        processes = [slot.process for slot in self._slots if slot.process is not None]
        for process in processes:
            if process.is_alive() and process.pid is not None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(process.pid, signal.SIGTERM)
        deadline_s = time.monotonic() + timeout_s
        for process in processes:
            process.join(max(0.0, deadline_s - time.monotonic()))
        for process in processes:
            if process.is_alive():
                logger.warning("API process %s did not stop: killing it", process.pid)
                process.kill()
                process.join()


def api_process_main(
    settings: Settings,
    listener: socket.socket,
    worker_status: WorkerPoolStatus | None,
    number: int,
    parent_pid: int,
) -> None:
    """Entry point of an API process (module level: spawn pickles it): uvicorn on the inherited
    socket until SIGTERM or SIGINT; exits with :data:`STARTUP_FAILED` if it could not start."""
    server = uvicorn_server(
        settings, worker_pool=worker_status, headers=[("X-Api-Process", str(number))]
    )
    # A Ctrl-C reaches the whole process group and serve passes it on as SIGTERM: one
    # graceful shutdown, not a forced one. uvicorn re-raises the signal that stopped it for the
    # previous handler after its shutdown: these make that a no-op (exit status 0).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: setattr(server, "should_exit", True))

    def watch_parent() -> None:
        while not server.should_exit:
            if os.getppid() != parent_pid:  # serve is gone (SIGKILL): do not serve on alone
                server.should_exit = True
                return
            time.sleep(PARENT_WATCH_S)

    threading.Thread(target=watch_parent, name="parent-watch", daemon=True).start()
    try:
        with asyncio.Runner(loop_factory=server.config.get_loop_factory()) as runner:
            runner.run(serve_with_threads(server, settings.api_threads, listener))
    except SystemExit:
        if server.started:
            raise
    if not server.started:
        raise SystemExit(STARTUP_FAILED)


def uvicorn_server(
    settings: Settings,
    *,
    worker_pool: WorkerPool | None,
    headers: list[tuple[str, str]] | None = None,
) -> uvicorn.Server:
    """The API as ``serve`` runs it (in its own process, or in each of its API processes):
    uvicorn with the connection guard, the proxy settings and keys kept out of the access log.
    ``headers``: extra headers of every answer."""
    import uvicorn

    from app.api import access_log
    from app.api.connection_guard import guarded_protocol
    from app.main import create_app
    from app.observability.logs import uvicorn_log_options

    config = uvicorn.Config(
        create_app(settings, worker_pool=worker_pool),
        log_level="info",
        timeout_keep_alive=settings.keep_alive_s,
        http=guarded_protocol(settings),  # header/body timeouts, connections per address
        headers=headers,
        **proxy_options(settings),
        **uvicorn_log_options(settings.log_format),  # --log-format json: JSON lines
    )
    access_log.install()  # after uvicorn configured its loggers: no key in the access log
    return uvicorn.Server(config)


def proxy_options(settings: Settings) -> dict[str, Any]:
    """uvicorn's options for forwarded headers: believed only from
    ``INVISIBLE_MAP_TRUSTED_PROXIES`` (uvicorn's own default believes any from 127.0.0.1, so
    anything on the machine, or a proxy passing a client's header on, could choose the client
    address the server sees)."""
    if not settings.trusted_proxies:
        return {"proxy_headers": False}
    return {"proxy_headers": True, "forwarded_allow_ips": settings.trusted_proxies}


async def serve_with_threads(server: uvicorn.Server, threads: int, listener: socket.socket) -> None:
    """Serve on ``listener`` with ``threads`` threads for the routes (``Settings.api_threads``).

    Before serving, everything made so far (the modules of numpy, gtsam, FastAPI, SQLAlchemy, …
    and the app: most of the process's objects) is moved out of the garbage collector's reach
    (``gc.freeze``): a full collection then looks at what requests made since, ~20,000 objects
    under ``bench/load.py`` instead of ~200,000. (Such collections still take up to ~100 ms of
    CPU there, spent on the garbage itself, not on the frozen heap.)"""
    from anyio import to_thread

    to_thread.current_default_thread_limiter().total_tokens = threads
    gc.collect()
    gc.freeze()
    await server.serve(sockets=[listener])

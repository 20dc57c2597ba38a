"""Run the server as separate processes, as a user would: for end-to-end tests and benchmarks.

    with ServerProcess(database_url, workers=0) as server:      # `invisible-map serve`
        with WorkerProcess(database_url):                        # `invisible-map worker`
            httpx.get(server.url + "/healthz")

Both run the installed ``invisible-map`` command of this interpreter in a new process group and
stop it with SIGTERM (then SIGKILL after a grace period).
"""

from __future__ import annotations

import os
import secrets
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import TracebackType
from typing import IO, Self

import httpx

READY_TIMEOUT_S = 60.0


def free_port() -> int:
    """A TCP port nobody listens on now (on the loopback interface)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class _Process:
    """A child running ``invisible-map ARGS`` with a given environment."""

    def __init__(self, args: list[str], env: dict[str, str], log_path: Path | None = None) -> None:
        self.args = args
        self.env = env
        self.log_path = log_path
        self.process: subprocess.Popen[bytes] | None = None
        self._log: IO[bytes] | None = None

    def start(self) -> None:
        command = [sys.executable, "-m", "app.cli", *self.args]
        if self.log_path is not None:
            self._log = self.log_path.open("ab")
        self.process = subprocess.Popen(
            command,
            env=self.env,
            stdout=self._log or subprocess.DEVNULL,
            stderr=subprocess.STDOUT if self._log else subprocess.DEVNULL,
            start_new_session=True,
        )

    @property
    def pid(self) -> int:
        assert self.process is not None, "not started"
        return self.process.pid

    def log_tail(self, lines: int = 20) -> str:
        """The last ``lines`` lines of the log file ("" without one)."""
        if self.log_path is None or not self.log_path.exists():
            return ""
        return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])

    def kill(self, sig: int = signal.SIGKILL) -> None:
        """Send ``sig`` to the whole process group (the command and any worker children)."""
        if self.process is not None and self.process.poll() is None:
            os.killpg(self.process.pid, sig)

    def stop(self, timeout_s: float = 30.0) -> int | None:
        """SIGTERM to the command (as a service manager sends it: the command passes it on to
        its worker processes), wait, then SIGKILL to the whole group; returns the exit status."""
        if self.process is None:
            return None
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.kill(signal.SIGKILL)
                self.process.wait()
        if self._log is not None:
            self._log.close()
        return self.process.returncode


def _environment(database_url: str, extra: dict[str, str] | None) -> dict[str, str]:
    env = {**os.environ, "DATABASE_URL": database_url, "PYTHONUNBUFFERED": "1"}
    env.update(extra or {})
    return env


class ServerProcess(_Process):
    """``invisible-map serve`` on ``port`` (default: a free one); waits until ``/readyz``
    answers 200. ``api_processes``: ``--api-processes`` (1 unless given: tests and benchmarks
    choose; None leaves serve's default)."""

    def __init__(
        self,
        database_url: str,
        *,
        workers: int = 0,
        admin_key: str | None = None,
        env: dict[str, str] | None = None,
        log_path: Path | None = None,
        migrate: bool = True,
        port: int | None = None,
        api_processes: int | None = 1,
    ) -> None:
        self.port = port or free_port()
        self.admin_key = admin_key or "im_test_admin_" + secrets.token_urlsafe(16)
        args = ["serve", "--port", str(self.port), "--workers", str(workers)]
        if api_processes is not None:  # None: serve's default (INVISIBLE_MAP_API_PROCESSES, cores)
            args += ["--api-processes", str(api_processes)]
        if not migrate:
            args.append("--no-migrate")
        environment = _environment(database_url, env)
        environment["INVISIBLE_MAP_ADMIN_KEY"] = self.admin_key
        super().__init__(args, environment, log_path)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            assert self.process is not None
            if self.process.poll() is not None:
                raise RuntimeError(
                    f"the server exited with status {self.process.returncode} before it was ready"
                    + (f"; the end of {self.log_path}:\n{self.log_tail()}" if self.log_path else "")
                )
            try:
                if httpx.get(self.url + "/readyz", timeout=1.0).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.1)
        raise TimeoutError(f"the server at {self.url} was not ready within {timeout_s:g} s")

    def __enter__(self) -> Self:
        self.start()
        try:
            self.wait_ready()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()


class WorkerProcess(_Process):
    """``invisible-map worker --processes N`` against a database."""

    def __init__(
        self,
        database_url: str,
        *,
        processes: int = 1,
        env: dict[str, str] | None = None,
        log_path: Path | None = None,
    ) -> None:
        super().__init__(
            ["worker", "--processes", str(processes)], _environment(database_url, env), log_path
        )

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()

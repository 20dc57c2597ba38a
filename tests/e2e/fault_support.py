"""Real faults for the fault tests: a PostgreSQL server of the test's own that it may stop and
start, a small disk that fills up, and a proxy that loses a response after the server sent it.

Each needs something of the machine — PostgreSQL's server binaries (``initdb``, ``pg_ctl``), the
right to mount a tmpfs (root) — and skips with the reason where that is missing, unless
``INVISIBLE_MAP_REQUIRE_FAULTS=1`` (CI sets it), which makes the skip a failure.
"""

from __future__ import annotations

import contextlib
import glob
import os
import shutil
import socket
import subprocess
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from app.cli.server_process import free_port

REQUIRE_FAULTS = os.environ.get("INVISIBLE_MAP_REQUIRE_FAULTS") == "1"


def unavailable(reason: str) -> None:
    """Skip the test for ``reason`` (fail instead where CI requires the fault tests)."""
    if REQUIRE_FAULTS:
        pytest.fail(f"INVISIBLE_MAP_REQUIRE_FAULTS=1 but {reason}")
    pytest.skip(reason)


def _postgres_bin_dir() -> Path | None:
    found = shutil.which("pg_ctl")
    if found:
        return Path(found).resolve().parent
    candidates = sorted(glob.glob("/usr/lib/postgresql/*/bin/pg_ctl"))
    return Path(candidates[-1]).parent if candidates else None


class PrivatePostgres:
    """A PostgreSQL server in a folder of the test's own, on a free port.

    Unlike the machine's shared server, it may be stopped and started by the test without
    harming any other test. As root (PostgreSQL refuses to run as root) it runs as the
    ``postgres`` user, which owns the folder. Trust authentication, user ``postgres``.
    """

    def __init__(self, folder: Path) -> None:
        bin_dir = _postgres_bin_dir()
        if bin_dir is None:
            unavailable("PostgreSQL's server binaries (initdb, pg_ctl) are not installed")
        assert bin_dir is not None
        self.bin_dir = bin_dir
        self.folder = folder
        self.data_dir = folder / "data"
        self.port = free_port()
        self._as_postgres: list[str] = []
        if os.geteuid() == 0:
            if shutil.which("runuser") is None:
                unavailable("running PostgreSQL as root needs runuser to switch to postgres")
            self._as_postgres = ["runuser", "-u", "postgres", "--"]
            folder.chmod(0o755)
            shutil.chown(folder, "postgres", "postgres")
        self._run(
            "initdb", "-D", str(self.data_dir), "-A", "trust", "-U", "postgres", "-E", "UTF8",
            "--no-sync",
        )  # fmt: skip

    def _run(self, program: str, *args: str) -> None:
        command = [*self._as_postgres, str(self.bin_dir / program), *args]
        result = subprocess.run(command, capture_output=True, text=True, timeout=60)
        if result.returncode != 0:
            raise RuntimeError(f"{program} failed: {result.stderr.strip() or result.stdout}")

    def url(self, database: str = "postgres") -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/{database}"

    def start(self) -> None:
        options = (
            f"-p {self.port} -k {self.folder} -c listen_addresses=127.0.0.1 -c fsync=off "
            "-c full_page_writes=off"
        )
        self._run(
            "pg_ctl", "-D", str(self.data_dir), "-o", options, "-l", str(self.folder / "log"),
            "-w", "-t", "60", "start",
        )  # fmt: skip

    def stop(self, mode: str = "fast") -> None:
        """Stop the server: ``fast`` ends every connection and rolls back open transactions."""
        self._run("pg_ctl", "-D", str(self.data_dir), "-m", mode, "-w", "-t", "60", "stop")

    def create_database(self, name: str) -> str:
        """``CREATE DATABASE name``; returns its URL."""
        subprocess.run(
            ["psql", "-h", "127.0.0.1", "-p", str(self.port), "-U", "postgres", "-q", "-c",
             f'CREATE DATABASE "{name}"'],
            check=True, capture_output=True, timeout=60,
        )  # fmt: skip
        return self.url(name)


@contextlib.contextmanager
def private_postgres(log_dir: Path) -> Iterator[PrivatePostgres]:
    """A started :class:`PrivatePostgres` in a new folder under the system's temporary folder
    (the postgres user must reach it: pytest's own are private to their owner); stopped and
    removed at the end, its log copied to ``log_dir/postgres.log``."""
    folder = Path(tempfile.mkdtemp(prefix="invisible-map-postgres-"))
    try:
        server = PrivatePostgres(folder)
        server.start()
        try:
            yield server
        finally:
            with contextlib.suppress(RuntimeError):
                server.stop("immediate")
            with contextlib.suppress(OSError):
                shutil.copyfile(folder / "log", log_dir / "postgres.log")
    finally:
        shutil.rmtree(folder, ignore_errors=True)


class SmallDisk:
    """A tmpfs of ``size_bytes`` mounted on ``mount_point``: a disk that fills up for real.
    :meth:`grow` makes it bigger while files on it are open (as freeing space would)."""

    def __init__(self, mount_point: Path, size_bytes: int) -> None:
        self.mount_point = mount_point
        mount_point.mkdir(parents=True, exist_ok=True)
        if os.geteuid() != 0:
            unavailable("mounting a small file system for the full-disk test needs root")
        result = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size_bytes},mode=0755", "tmpfs",
             str(mount_point)],
            capture_output=True, text=True,
        )  # fmt: skip
        if result.returncode != 0:
            unavailable(f"cannot mount a tmpfs here: {result.stderr.strip()}")

    def grow(self, size_bytes: int) -> None:
        subprocess.run(
            ["mount", "-o", f"remount,size={size_bytes}", str(self.mount_point)], check=True
        )

    def free_bytes(self) -> int:
        return shutil.disk_usage(self.mount_point).free

    def unmount(self) -> None:
        subprocess.run(["umount", "--lazy", str(self.mount_point)], check=False)


class ResponseDroppingProxy:
    """A TCP proxy on a free loopback port to ``127.0.0.1:target_port``.

    For the first connection whose server starts answering, it calls ``on_first_response`` (the
    test kills the server there) and closes the client's connection without passing on a byte
    of the answer: the request was carried out, the client never hears of it. Every later
    connection is passed through both ways.
    """

    def __init__(self, target_port: int, on_first_response: Callable[[], None]) -> None:
        self.target_port = target_port
        self.on_first_response = on_first_response
        self.dropped = threading.Event()
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = int(self._listener.getsockname()[1])
        self._closed = False
        threading.Thread(target=self._accept, name="proxy", daemon=True).start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def close(self) -> None:
        self._closed = True
        self._listener.close()

    def _accept(self) -> None:
        while not self._closed:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(client,), daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        try:
            upstream = socket.create_connection(("127.0.0.1", self.target_port), timeout=60)
        except OSError:
            client.close()  # the server is down: the client sees its connection closed
            return
        threading.Thread(target=_pump, args=(client, upstream), daemon=True).start()
        with client, upstream:
            while True:
                try:
                    data = upstream.recv(65536)
                except OSError:
                    return
                if not data:
                    return
                if not self.dropped.is_set():
                    self.dropped.set()
                    self.on_first_response()
                    for end in (client, upstream):  # (a close alone would wait for _pump)
                        with contextlib.suppress(OSError):
                            end.shutdown(socket.SHUT_RDWR)
                    return  # the answer is lost
                client.sendall(data)


def _pump(source: socket.socket, sink: socket.socket) -> None:
    """Copy ``source`` to ``sink`` until ``source`` ends, then pass the end on (so that the
    server sees the client hang up and does not wait for it at shutdown)."""
    with contextlib.suppress(OSError):
        while data := source.recv(65536):
            sink.sendall(data)
        sink.shutdown(socket.SHUT_WR)

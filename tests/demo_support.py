"""One ``invisible-map serve --demo``, as ``scripts/demo`` runs it, for the tests that need it.

The demo boots the API and a worker, uploads the eight demo sessions and builds them, then
rebuilds the five with ground truth: some 15 s on an idle 2-core machine. Two tests need it (the
README's quick start, ``tests/e2e/test_quickstart.py``, and ``serve --demo``'s own test in
``tests/cli/test_server_cli.py``), so it is started once per test process by the session-scoped
``demo`` fixture (``tests/conftest.py``), and both are marked ``xdist_group("demo")`` so that
``scripts/test`` (``--dist loadgroup``) runs them in the same process.

The quick start needs the demo as a reader finds it (its answers show session 9, job 14): it is
the one user that changes the demo's database; the other only reads it, and restarts the demo on
a copy.
"""

from __future__ import annotations

import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import httpx

from app.cli.server_process import free_port

REPO_ROOT = Path(__file__).resolve().parents[1]
#: The console script of this interpreter's environment (what ``.venv/bin/invisible-map`` is).
INVISIBLE_MAP = Path(sys.executable).with_name("invisible-map")
DEMO_MAPS = 8
#: The demo's builds: one per map, and one more for each of the five with ground truth (it
#: rebuilds them with it, so their versions carry the ground-truth metric).
DEMO_JOBS = DEMO_MAPS + 5
#: The demo's last line, once every map is built (and those with ground truth rebuilt).
FINAL_LINE = re.compile(r"^demo: \d+ of \d+ maps ready", re.MULTILINE)


@dataclass
class Demo:
    """A running demo: its URL, the admin key it printed, its log and its SQLite file."""

    url: str
    admin_key: str
    log_path: Path
    database_path: Path

    @property
    def log(self) -> str:
        return self.log_path.read_text()

    def database_copy(self, path: Path) -> Path:
        """A consistent copy of the demo's database at ``path`` (SQLite's backup, safe while
        the demo runs)."""
        with sqlite3.connect(self.database_path) as source, sqlite3.connect(path) as copy:
            source.backup(copy)
        return path


def wait_for(condition: Callable[[], bool], *, timeout_s: float, what: str, log: Path) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}; the server's log:\n{log.read_text()}")


@contextmanager
def running_demo(folder: Path) -> Iterator[Demo]:
    """``invisible-map serve --demo`` with the embedded defaults (SQLite in ``folder/var``, a
    generated admin key), once every demo map is built; stopped with SIGTERM at the end, which
    it must obey with exit status 0."""
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = {
        name: value
        for name, value in os.environ.items()
        if name != "DATABASE_URL" and not name.startswith("INVISIBLE_MAP_")
    }
    env.update(INVISIBLE_MAP_DATA_DIR=str(folder / "var"), PYTHONUNBUFFERED="1")
    log_path = folder / "demo.log"
    log: IO[bytes] = log_path.open("wb")
    process = subprocess.Popen(
        [str(INVISIBLE_MAP), "serve", "--demo", "--port", str(port)],
        cwd=REPO_ROOT,
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    stopped_cleanly = False
    try:
        key: list[str] = []

        def key_printed() -> bool:
            assert process.poll() is None, f"the demo exited:\n{log_path.read_text()}"
            key.extend(re.findall(r"^admin key for this run: (\S+)$", log_path.read_text(), re.M))
            return bool(key)

        wait_for(key_printed, timeout_s=60, what="the admin key", log=log_path)

        def maps_built() -> bool:
            assert process.poll() is None, f"the demo exited:\n{log_path.read_text()}"
            try:
                info = httpx.get(
                    f"{url}/v1/info", headers={"Authorization": f"Bearer {key[0]}"}, timeout=5
                )
            except httpx.TransportError:
                return False
            # … and the demo has said so (its last line, which the README shows)
            return (
                info.status_code == 200
                and info.json()["jobs_by_state"]["succeeded"] == DEMO_JOBS
                and FINAL_LINE.search(log_path.read_text()) is not None
            )

        wait_for(maps_built, timeout_s=180, what="the demo's maps", log=log_path)
        yield Demo(
            url=url,
            admin_key=key[0],
            log_path=log_path,
            database_path=folder / "var" / "invisible-map.sqlite3",
        )
        process.send_signal(signal.SIGTERM)
        status = process.wait(timeout=30)
        assert status == 0, f"the demo exited with {status} on SIGTERM:\n{log_path.read_text()}"
        stopped_cleanly = True
    finally:
        if not stopped_cleanly and process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
        log.close()

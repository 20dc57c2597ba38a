"""The server's subcommands of ``invisible-map`` (``serve``, ``worker``, ``migrate``, ``keys``), run
as a user runs them: real subprocesses with an explicit environment, and ``main([...])`` in this
process with a monkeypatched one (the commands read ``Settings`` afresh each time).

Every failure must be one line on stderr, ``invisible-map: error: …``, exit status 1, and no
traceback; argparse misuse exits 2.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import timedelta
from pathlib import Path
from typing import IO, Any

import httpx
import pytest
from cli_support import assert_one_line_error

from app import cli
from app.cli.common import DEMO_SESSIONS
from app.cli.server_process import ServerProcess, free_port
from app.storage import keys
from app.storage.db import Database
from app.storage.migrate import current_revision, head_revision, is_current
from app.storage.orm import JobState, Role, utc_now
from tests.demo_support import Demo
from tests.service.helpers import get_job, insert_session, wait_for

REPO_ROOT = Path(__file__).resolve().parents[2]
SESSIONS_DIR = REPO_ROOT / "data" / "sessions"
ADMIN_KEY = "im_test_admin_0123456789abcdef"
#: The demo sessions ``serve --demo`` uploads (data/sessions and data/demo).
DEMO_SESSION_COUNT = 8
#: The demo's maps with ground truth in data/ground_truth, rebuilt with it (a job each).
DEMO_TRUTH_MAPS = ("occam_room", "floor_2_straight", "straight_209_occam", "desnat_straight_once",
                   "floor_2_pois")  # fmt: skip
KEY_LINE = re.compile(r"^im_[0-9a-f]{8}_[A-Za-z0-9_-]+$")


# --------------------------------------------------------------------------- helpers


def server_env(database_url: str, data_dir: Path, **extra: str) -> dict[str, str]:
    """This process's environment without any Invisible Map setting, then ``DATABASE_URL``, a
    private data directory and ``extra``."""
    env = {
        name: value
        for name, value in os.environ.items()
        if name != "DATABASE_URL" and not name.startswith("INVISIBLE_MAP_")
    }
    env.update(
        DATABASE_URL=database_url,
        INVISIBLE_MAP_DATA_DIR=str(data_dir),
        PYTHONUNBUFFERED="1",
        PYTHONDONTWRITEBYTECODE="1",
    )
    env.update(extra)
    return env


def run_cli(env: dict[str, str], *args: Any) -> subprocess.CompletedProcess[str]:
    """``python -m app.cli ARGS`` from the repository root, to the end (60 s at most)."""
    return subprocess.run(
        [sys.executable, "-m", "app.cli", *(str(a) for a in args)],
        cwd=REPO_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


RunMain = Callable[..., tuple[int, str, str]]


@pytest.fixture
def run_main(capsys: pytest.CaptureFixture[str]) -> RunMain:
    """``cli.main(ARGS)`` in this process: (status, stdout, stderr)."""

    def run(*args: Any) -> tuple[int, str, str]:
        capsys.readouterr()
        status = cli.main([str(a) for a in args])
        out, err = capsys.readouterr()
        return status, out, err

    return run


@contextmanager
def open_database(url: str) -> Iterator[Database]:
    database = Database(url)
    try:
        yield database
    finally:
        database.dispose()


@pytest.fixture
def db(database_url: str, env: pytest.MonkeyPatch) -> Iterator[Database]:
    """The fresh migrated database (SQLite, PostgreSQL), also in ``DATABASE_URL``."""
    env.setenv("DATABASE_URL", database_url)
    with open_database(database_url) as database:
        yield database


@pytest.fixture
def empty_sqlite_url(tmp_path: Path) -> str:
    """An empty (zero-byte, unmigrated) SQLite file."""
    path = tmp_path / "empty.sqlite3"
    path.touch()
    return f"sqlite:///{path}"


def authenticate(database: Database, key: str, **kwargs: Any) -> keys.Principal | None:
    with database.read() as db_session:
        return keys.authenticate(db_session, key, **kwargs)


def create_key(run_main: RunMain, *args: Any) -> str:
    status, out, err = run_main("keys", "create", *args)
    assert status == 0, err
    return out.strip()


def unreachable_postgres_url() -> str:
    return f"postgresql://postgres:s3cret@127.0.0.1:{free_port()}/nothing"


# --------------------------------------------------------------------------- migrate


def test_migrate_creates_the_schema_in_an_empty_sqlite_file_and_can_run_again(
    tmp_path: Path, empty_sqlite_url: str
) -> None:
    environment = server_env(empty_sqlite_url, tmp_path / "var")
    first = run_cli(environment, "migrate")
    assert first.returncode == 0, first.stderr
    assert "Traceback" not in first.stderr
    assert first.stdout.splitlines() == [
        f"database {empty_sqlite_url} at revision {head_revision()}"
    ]
    assert (tmp_path / "empty.sqlite3").stat().st_size > 0
    with open_database(empty_sqlite_url) as database:
        assert is_current(database)

    again = run_cli(environment, "migrate")
    assert again.returncode == 0, again.stderr
    assert again.stdout == first.stdout


def test_migrate_on_a_migrated_database_changes_nothing(db: Database, run_main: RunMain) -> None:
    key = create_key(run_main, "--role", "admin", "--name", "before")
    status, out, err = run_main("migrate")
    assert status == 0, err
    assert out.splitlines() == [
        f"database {db.url.render_as_string(hide_password=True)} at revision {head_revision()}"
    ]
    assert current_revision(db) == head_revision()
    principal = authenticate(db, key)  # the data survived
    assert principal is not None
    assert principal.role is Role.ADMIN


# --------------------------------------------------------------------------- keys


def test_keys_create_prints_the_key_alone_on_stdout(db: Database, tmp_path: Path) -> None:
    result = run_cli(
        server_env(db.url.render_as_string(hide_password=False), tmp_path),
        "keys",
        "create",
        "--role",
        "device",
        "--name",
        "phone",
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert len(lines) == 1, result.stdout
    key = lines[0]
    assert key.startswith("im_")
    assert KEY_LINE.match(key), key
    assert "device key" in result.stderr
    assert "phone" in result.stderr
    assert key not in result.stderr
    principal = authenticate(db, key)
    assert principal is not None
    assert principal.role is Role.DEVICE
    assert principal.subject == f"key:{principal.key_id}"
    assert f"key {principal.key_id} " in result.stderr


def test_keys_create_admin_key_that_expires(db: Database, run_main: RunMain) -> None:
    key = create_key(run_main, "--role", "admin", "--expires-in-days", "1.5")
    principal = authenticate(db, key)
    assert principal is not None
    assert principal.role is Role.ADMIN
    assert authenticate(db, key, now=utc_now() + timedelta(days=1.4)) is not None
    assert authenticate(db, key, now=utc_now() + timedelta(days=1.6)) is None


@pytest.mark.parametrize("days", ["0", "-3", "nan", "inf", "1e9"])
def test_keys_create_rejects_a_bad_expiry(db: Database, run_main: RunMain, days: str) -> None:
    status, out, err = run_main("keys", "create", "--role", "device", f"--expires-in-days={days}")
    assert_one_line_error(status, err, "--expires-in-days must be > 0")
    assert out == ""
    with db.read() as db_session:
        assert keys.list_keys(db_session) == []


def test_keys_create_rejects_a_name_that_is_no_text(db: Database, tmp_path: Path) -> None:
    """A name of bytes that are no UTF-8 reaches Python as lone surrogates (issue 28, finding 1:
    the one rule of stored text)."""
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "app.cli",
            "keys",
            "create",
            "--role",
            "device",
            "--name",
            b"lab \xff",
        ],
        cwd=REPO_ROOT,
        env=server_env(db.url.render_as_string(hide_password=False), tmp_path),
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert_one_line_error(result.returncode, result.stderr, "--name holds a lone surrogate")
    with db.read() as db_session:
        assert keys.list_keys(db_session) == []


def test_keys_create_rejects_an_unknown_role(
    db: Database, run_main: RunMain, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        run_main("keys", "create", "--role", "root")
    assert exit_info.value.code == 2
    assert "invalid choice: 'root'" in capsys.readouterr().err
    with db.read() as db_session:
        assert keys.list_keys(db_session) == []


def test_keys_list_shows_ids_roles_and_prefixes_never_secrets(
    db: Database, run_main: RunMain
) -> None:
    status, out, err = run_main("keys", "list")
    assert (status, out) == (0, "")
    assert "no API keys" in err

    phone = create_key(run_main, "--role", "device", "--name", "phone")
    admin = create_key(run_main, "--role", "admin")
    status, out, _ = run_main("keys", "list")
    assert status == 0
    with db.read() as db_session:
        infos = keys.list_keys(db_session)
    assert [info.role for info in infos] == [Role.DEVICE, Role.ADMIN]
    rows = [line.split("\t") for line in out.splitlines()]
    assert rows == [
        [str(infos[0].id), "device", f"im_{infos[0].prefix}_…", "active", "phone"],
        [str(infos[1].id), "admin", f"im_{infos[1].prefix}_…", "active", ""],
    ]
    assert [info.prefix for info in infos] == [key.split("_")[1] for key in (phone, admin)]
    for key in (phone, admin):
        assert key.split("_", 2)[2] not in out  # the secret part

    assert run_main("keys", "revoke", infos[0].id)[0] == 0
    _, out, _ = run_main("keys", "list")
    assert out.splitlines()[0].split("\t")[3] == "revoked"
    assert out.splitlines()[1].split("\t")[3] == "active"


def test_keys_revoke_makes_the_key_fail(db: Database, run_main: RunMain) -> None:
    key = create_key(run_main, "--role", "device", "--name", "lost phone")
    principal = authenticate(db, key)
    assert principal is not None
    assert principal.key_id is not None
    status, out, err = run_main("keys", "revoke", principal.key_id)
    assert status == 0, err
    assert out.strip() == f"revoked key {principal.key_id} (im_{key.split('_')[1]}_…)"
    assert authenticate(db, key) is None
    status, _, err = run_main("keys", "revoke", principal.key_id)  # again: still revoked
    assert status == 0, err
    assert authenticate(db, key) is None


@pytest.mark.usefixtures("db")
@pytest.mark.parametrize("key_id", ["999", "0", "99999999999999999999"])
def test_keys_revoke_an_unknown_id(run_main: RunMain, key_id: str) -> None:
    status, out, err = run_main("keys", "revoke", key_id)
    assert_one_line_error(status, err, f"API key {key_id} not found")
    assert out == ""


@pytest.mark.parametrize(
    "args",
    [
        ["keys", "list"],
        ["keys", "create", "--role", "admin"],
        ["keys", "revoke", "1"],
    ],
    ids=["list", "create", "revoke"],
)
def test_keys_on_an_unmigrated_database(
    env: pytest.MonkeyPatch, run_main: RunMain, empty_sqlite_url: str, args: list[str]
) -> None:
    env.setenv("DATABASE_URL", empty_sqlite_url)
    status, out, err = run_main(*args)
    assert_one_line_error(status, err, "not migrated", "run `invisible-map migrate`")
    assert out == ""
    with open_database(empty_sqlite_url) as database:
        assert current_revision(database) is None  # nothing was created


def test_keys_on_an_unmigrated_database_in_a_subprocess(
    tmp_path: Path, empty_sqlite_url: str
) -> None:
    result = run_cli(server_env(empty_sqlite_url, tmp_path), "keys", "create", "--role", "device")
    assert_one_line_error(result.returncode, result.stderr, "invisible-map migrate")
    assert result.stdout == ""


# --------------------------------------------------------------------------- bad settings


@pytest.mark.parametrize(
    "url",
    ["nonsense://user:s3cret@x", unreachable_postgres_url()],
    ids=["unknown-scheme", "unreachable-postgres"],
)
@pytest.mark.parametrize(
    "args",
    [["migrate"], ["keys", "list"], ["keys", "create", "--role", "admin"], ["keys", "revoke", "1"]],
    ids=["migrate", "keys-list", "keys-create", "keys-revoke"],
)
def test_a_bad_database_url(
    env: pytest.MonkeyPatch, run_main: RunMain, url: str, args: list[str]
) -> None:
    env.setenv("DATABASE_URL", url)
    status, out, err = run_main(*args)
    line = assert_one_line_error(status, err, "cannot use the database")
    assert "s3cret" not in line
    assert out == ""


@pytest.mark.parametrize(
    ("url", "args"),
    [
        ("nonsense://x", ["migrate"]),
        ("nonsense://x", ["serve", "--port", str(free_port()), "--workers", "0"]),
        (unreachable_postgres_url(), ["worker"]),
        (unreachable_postgres_url(), ["keys", "list"]),
    ],
    ids=["migrate", "serve", "worker", "keys-list"],
)
def test_a_bad_database_url_in_a_subprocess(tmp_path: Path, url: str, args: list[str]) -> None:
    result = run_cli(server_env(url, tmp_path), *args)
    line = assert_one_line_error(result.returncode, result.stderr, "cannot use the database")
    assert "s3cret" not in line
    assert result.stdout == ""


@pytest.mark.usefixtures("db")
def test_an_admin_key_too_short(env: pytest.MonkeyPatch, run_main: RunMain) -> None:
    env.setenv("INVISIBLE_MAP_ADMIN_KEY", "short")
    status, out, err = run_main("migrate")
    assert_one_line_error(status, err, "INVISIBLE_MAP_ADMIN_KEY", "16")
    assert out == ""


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["serve", "--port", "70000", "--workers", "0"], "--port must be 1–65535, got 70000"),
        (["serve", "--workers", "65"], "--workers must be 0–64, got 65"),
        (["worker", "--processes", "0"], "--processes must be 1–64, got 0"),
        (["serve"], "INVISIBLE_MAP_ADMIN_KEY"),
    ],
    ids=["port-70000", "workers-65", "processes-0", "short-admin-key"],
)
def test_serve_and_worker_refuse_bad_options(
    tmp_path: Path, empty_sqlite_url: str, args: list[str], message: str
) -> None:
    """As subprocesses: a command that wrongly went on would serve or work until the timeout."""
    environment = server_env(empty_sqlite_url, tmp_path / "var", INVISIBLE_MAP_ADMIN_KEY="short")
    if "INVISIBLE_MAP_ADMIN_KEY" not in message:
        environment.pop("INVISIBLE_MAP_ADMIN_KEY")
    result = run_cli(environment, *args)
    assert_one_line_error(result.returncode, result.stderr, message)
    assert result.stdout == ""
    assert (tmp_path / "empty.sqlite3").stat().st_size == 0  # not even migrated


@pytest.mark.parametrize("args", [["serve", "--workers", "0"], ["worker", "--processes", "1"]])
def test_serve_and_worker_refuse_a_jemalloc_that_is_no_file(
    tmp_path: Path, empty_sqlite_url: str, args: list[str]
) -> None:
    """Even a single in-process worker, which would preload nothing, checks the setting."""
    missing = tmp_path / "no-such-libjemalloc.so.2"
    environment = server_env(
        empty_sqlite_url, tmp_path / "var", INVISIBLE_MAP_JEMALLOC=str(missing)
    )
    environment.pop("INVISIBLE_MAP_ADMIN_KEY", None)
    result = run_cli(environment, *args)
    assert_one_line_error(
        result.returncode, result.stderr, f"INVISIBLE_MAP_JEMALLOC={missing}: no such file"
    )
    assert (tmp_path / "empty.sqlite3").stat().st_size == 0  # not even migrated


# --------------------------------------------------------------------------- serve


@pytest.mark.slow
def test_serve_answers_health_readiness_and_info(
    tmp_path: Path, env: pytest.MonkeyPatch, run_main: RunMain
) -> None:
    url = f"sqlite:///{tmp_path / 'serve' / 'db.sqlite3'}"  # no file yet: serve migrates it
    env.setenv("DATABASE_URL", url)
    server = ServerProcess(
        url,
        workers=0,
        admin_key=ADMIN_KEY,
        # a key revoked by another process (the CLI) is refused within this bound
        env={"INVISIBLE_MAP_DATA_DIR": str(tmp_path / "var"), "INVISIBLE_MAP_KEY_CACHE_S": "1"},
        log_path=tmp_path / "serve.log",
    )
    with server, httpx.Client(base_url=server.url, timeout=10.0) as client:
        assert client.get("/healthz").status_code == 200
        ready = client.get("/readyz")
        assert ready.status_code == 200, ready.text
        assert ready.json()["schema_revision"] == head_revision()
        assert client.get("/v1/info").status_code == 401

        info = client.get("/v1/info", headers={"Authorization": f"Bearer {ADMIN_KEY}"})
        assert info.status_code == 200, info.text
        body = info.json()
        assert body["database"] == "sqlite"
        assert body["principal"]["role"] == "admin"
        assert body["workers"] == []
        assert body["queue_depth"] == 0

        # a key made with `keys create` against the running server's database works at once
        device_key = create_key(run_main, "--role", "device", "--name", "phone")
        as_device = client.get("/v1/info", headers={"Authorization": f"Bearer {device_key}"})
        assert as_device.status_code == 200, as_device.text
        assert as_device.json()["principal"]["role"] == "device"
        key_id = as_device.json()["principal"]["subject"].removeprefix("key:")
        assert run_main("keys", "revoke", key_id)[0] == 0
        revoked_at_s = time.monotonic()
        while True:  # refused within INVISIBLE_MAP_KEY_CACHE_S (1 s; 2 s more for a slow machine)
            revoked = client.get("/v1/info", headers={"Authorization": f"Bearer {device_key}"})
            if revoked.status_code != 200 or time.monotonic() - revoked_at_s > 3.0:
                break
            time.sleep(0.05)
        assert revoked.status_code == 401

        assert server.stop() == 0
    log = (tmp_path / "serve.log").read_text()
    assert f"at revision {head_revision()}" in log
    assert "worker processes: 0" in log
    assert ADMIN_KEY not in log
    assert "Traceback" not in log


@pytest.mark.slow
def test_serve_on_a_port_in_use(tmp_path: Path, empty_sqlite_url: str) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = run_cli(
            server_env(empty_sqlite_url, tmp_path / "var", INVISIBLE_MAP_ADMIN_KEY=ADMIN_KEY),
            *("serve", "--port", port, "--workers", "0"),
        )
    # Checked before anything else: no URL, no admin key, no migration, no "startup complete".
    assert result.stdout == ""
    assert_one_line_error(
        result.returncode,
        result.stderr,
        f"cannot listen on 127.0.0.1:{port}: Address already in use; stop what uses it",
    )


class DemoServer:
    """``invisible-map serve --demo --workers 1`` in its own process group, logging to a file."""

    def __init__(self, database_url: str, tmp_path: Path, run: int) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_path = tmp_path / f"demo-{run}.log"
        self._log: IO[bytes] = self.log_path.open("wb")
        self.process = subprocess.Popen(
            [
                *(sys.executable, "-m", "app.cli", "serve", "--demo"),
                *("--port", str(self.port), "--workers", "1"),
            ],
            cwd=REPO_ROOT,
            env=server_env(
                database_url,
                tmp_path / "var",
                INVISIBLE_MAP_ADMIN_KEY=ADMIN_KEY,
                INVISIBLE_MAP_POLL_S="0.05",
            ),
            stdout=self._log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        self.client = httpx.Client(
            base_url=self.url, timeout=10.0, headers={"Authorization": f"Bearer {ADMIN_KEY}"}
        )

    def log(self) -> str:
        return self.log_path.read_text()

    def count(self, path: str, **params: Any) -> int | None:
        """The ``count`` of a listing, or None while the server is not answering."""
        if self.process.poll() is not None:
            raise AssertionError(
                f"the server exited with {self.process.returncode}:\n{self.log()[-3000:]}"
            )
        try:
            response = self.client.get(path, params=params)
        except httpx.TransportError:
            return None
        return int(response.json()["count"]) if response.status_code == 200 else None

    def terminate(self, *, group: bool = True, timeout_s: float = 60.0) -> int:
        """SIGTERM to the process group (the server and its worker) or to the server alone;
        its exit status."""
        if group:
            os.killpg(self.process.pid, signal.SIGTERM)
        else:
            self.process.send_signal(signal.SIGTERM)
        return self.process.wait(timeout=timeout_s)

    def close(self) -> None:
        self.client.close()
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait()
        self._log.close()


def demo_uploads(log: str) -> dict[str, int]:
    """Session id of each demo session, from the ``demo: NAME: session ID, …`` lines."""
    return {
        name: int(session_id)
        for name, session_id in re.findall(r"^demo: (\w+): session (\d+),", log, re.MULTILINE)
    }


@pytest.mark.slow
@pytest.mark.xdist_group("demo")  # the demo is shared with the quick start's test
def test_serve_demo_uploads_and_builds_the_demo_sessions_once(demo: Demo, tmp_path: Path) -> None:
    """The demo (``tests/demo_support.py``, as scripts/demo runs it): every demo session
    uploaded and built, each map announced as it becomes ready, those with ground truth rebuilt
    with it, then the final count; restarted on (a copy of) its database, it finds them all and
    queues nothing. The quick start's test may have added to the demo's database: only the
    demo's own sessions and jobs are counted."""
    log = demo.log
    final = f"demo: {DEMO_SESSION_COUNT} of {DEMO_SESSION_COUNT} maps ready"
    assert final in log
    uploads = demo_uploads(log)
    assert sorted(uploads) == sorted([*(name for name, _ in DEMO_SESSIONS), "floor_2_pois"])
    assert "not uploaded" not in log
    assert "Traceback" not in log
    # Each map is announced as it becomes ready, before the final count.
    announced = re.findall(r"^demo: map (\d+) \((\w+)\) ready: ", log, re.MULTILINE)
    assert sorted(name for _, name in announced) == sorted(uploads)
    assert log.index("ready: ") < log.index(final)
    # The maps with ground truth were rebuilt with it: their figures are said.
    with_truth = re.findall(r"^demo: map \d+ \((\w+)\) with ground truth \(\S+\): ", log, re.M)
    assert sorted(with_truth) == sorted(DEMO_TRUTH_MAPS)
    jobs = [
        int(job) for job in re.findall(r"^demo: \w+: session \d+, map \d+, job (\d+)$", log, re.M)
    ]
    with httpx.Client(
        base_url=demo.url, headers={"Authorization": f"Bearer {demo.admin_key}"}
    ) as client:
        states = {job: client.get(f"/v1/jobs/{job}").json()["state"] for job in jobs}
    assert set(states.values()) == {"succeeded"}, states

    copy = demo.database_copy(tmp_path / "demo-copy.sqlite3")
    before = rows_in(copy)
    second = DemoServer(f"sqlite:///{copy}", tmp_path, run=2)
    try:
        wait_for(lambda: final in second.log(), timeout_s=60, what="the demo upload")
        assert second.count("/v1/sessions", limit=50) == before["session"]
        assert second.count("/v1/jobs") == before["job"]  # no job queued again
        wait_for(
            lambda: re.search(r"worker \S+ started", second.log()),
            timeout_s=30,
            what="the worker to start",
        )
        # `kill PID` of the server alone: it stops its worker itself (not left orphaned)
        assert second.terminate(group=False) == 0
    finally:
        second.close()
    log = second.log()
    assert demo_uploads(log) == uploads  # the same sessions, found again
    assert "with ground truth" not in log  # their versions have it already
    assert "SIGTERM received: finishing the current job" in log
    assert "is gone" not in log
    assert "Traceback" not in log


def rows_in(sqlite_path: Path) -> dict[str, int]:
    with sqlite3.connect(sqlite_path) as connection:
        return {
            table: connection.execute(f"SELECT count(*) FROM {table}").fetchone()[0]
            for table in ("session", "job")
        }


# --------------------------------------------------------------------------- worker


@pytest.mark.slow
def test_worker_runs_a_queued_job_and_stops_on_sigterm(db: Database, tmp_path: Path) -> None:
    inserted = insert_session(db, SESSIONS_DIR / "onetag.json")
    assert get_job(db, inserted.job_id).state is JobState.QUEUED
    log_path = tmp_path / "worker.log"
    with log_path.open("wb") as log:
        process = subprocess.Popen(
            [sys.executable, "-m", "app.cli", "worker", "--processes", "1"],
            cwd=REPO_ROOT,
            env=server_env(
                db.url.render_as_string(hide_password=False), tmp_path, INVISIBLE_MAP_POLL_S="0.05"
            ),
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:

            def succeeded() -> bool:
                if process.poll() is not None:
                    raise AssertionError(
                        f"the worker exited with {process.returncode}:\n{log_path.read_text()}"
                    )
                return get_job(db, inserted.job_id).state is JobState.SUCCEEDED

            wait_for(succeeded, timeout_s=60, what="the job to succeed", every_s=0.1)
            time.sleep(0.2)  # idle again, polling
            os.killpg(process.pid, signal.SIGTERM)
            assert process.wait(timeout=30) == 0, log_path.read_text()
        finally:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
    # One process (the default, and what the compose file runs) logs like several do.
    log = log_path.read_text()
    assert "started" in log, log
    assert f"job {inserted.job_id}" in log, log
    assert "Traceback" not in log_path.read_text()


@pytest.mark.slow
@pytest.mark.parametrize(("trusted", "seen"), [("", "127.0.0.1"), ("127.0.0.1", "203.0.113.7")])
def test_serve_believes_forwarded_headers_only_from_configured_proxies(
    tmp_path: Path, trusted: str, seen: str
) -> None:
    url = f"sqlite:///{tmp_path / 'db.sqlite3'}"
    env = {
        "INVISIBLE_MAP_DATA_DIR": str(tmp_path / "var"),
        "INVISIBLE_MAP_TRUSTED_PROXIES": trusted,
    }
    log = tmp_path / "serve.log"
    with ServerProcess(url, workers=0, env=env, log_path=log) as server:
        answer = httpx.get(server.url + "/healthz", headers={"X-Forwarded-For": "203.0.113.7"})
        assert answer.status_code == 200
        # a key in the query string is refused, and never written to the access log
        leaked = httpx.get(server.url + "/v1/info?api_key=im_0a1b2c3d_query-secret")
        assert leaked.status_code == 401
        server.stop()
    text = log.read_text()
    lines = [line for line in text.splitlines() if "GET /healthz" in line]
    assert lines, text
    assert all(f"{seen}:" in line for line in lines), lines
    assert "query-secret" not in text
    assert "GET /v1/info?api_key=*** " in text


def test_a_trusted_proxy_must_be_an_address(env: pytest.MonkeyPatch, run_main: RunMain) -> None:
    env.setenv("INVISIBLE_MAP_TRUSTED_PROXIES", "127.0.0.1, proxy.example")
    status, _, err = run_main("serve", "--port", "1")
    assert_one_line_error(status, err, "'proxy.example' is no IP address or network")


def test_the_listening_socket_gives_connections_tcp_nodelay() -> None:
    """serve's own socket must be IPPROTO_TCP: asyncio turns on TCP_NODELAY only for such
    sockets, and without it every answer waited ~40 ms for a delayed ACK (bench/http.py)."""
    import asyncio

    from app.cli.server import listening_socket

    listener = listening_socket("127.0.0.1", 0)
    assert listener.proto == socket.IPPROTO_TCP
    nodelay: list[int] = []

    async def serve_once() -> None:
        def accepted(_reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            sock = writer.get_extra_info("socket")
            nodelay.append(sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY))
            writer.close()

        server = await asyncio.start_server(accepted, sock=listener)
        port = listener.getsockname()[1]
        _reader, writer = await asyncio.open_connection("127.0.0.1", port)
        for _ in range(100):
            if nodelay:
                break
            await asyncio.sleep(0.01)
        writer.close()
        server.close()
        await server.wait_closed()

    asyncio.run(serve_once())
    assert nodelay
    assert nodelay[0] != 0


def test_the_logging_setup_leaves_out_the_http_clients_own_line_per_request() -> None:
    """``serve --demo`` polls its own API with httpx, in the process whose logging
    ``configure_logging`` sets up: the server's access line says each request already, so the
    client's INFO line ("HTTP Request: GET …") must not say it a second time. Its warnings stay."""
    script = (
        "import httpx, logging\n"
        "from workers.main import configure_logging\n"
        "configure_logging()\n"
        "transport = httpx.MockTransport(lambda request: httpx.Response(200))\n"
        "httpx.Client(transport=transport).get('http://127.0.0.1:9/v1/jobs/1')\n"
        "logging.getLogger('httpx').warning('a warning stays')\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True
    )
    assert "HTTP Request" not in done.stderr
    assert "a warning stays" in done.stderr

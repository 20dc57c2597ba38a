"""``serve --api-processes N``: several API processes on one port, on SQLite and PostgreSQL, as
real processes (``app.cli.api_processes``): both answer, the upload limit holds across them, a
killed one is replaced, SIGTERM stops them all; bad values are one-line errors."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from cli_support import assert_one_line_error

from app.cli.server_process import ServerProcess
from app.config import DEFAULT_API_PROCESSES_CAP, Settings, default_api_processes
from tests.conftest import fresh_database_url
from tests.service.helpers import wait_for

REPO_ROOT = Path(__file__).resolve().parents[2]
ONETAG = REPO_ROOT / "data" / "sessions" / "onetag.json"
STARTED = re.compile(r"API process api-(\d) started as pid (\d+)")
#: New connections sent to see every API process answer at least once (the kernel picks).
ATTEMPTS = 200


def started_pids(server: ServerProcess) -> dict[int, int]:
    """The latest pid of each API process number, from serve's log."""
    assert server.log_path is not None
    return {int(number): int(pid) for number, pid in STARTED.findall(server.log_path.read_text())}


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie (exited, not yet reaped) is not alive
    with open(f"/proc/{pid}/stat") as stat:
        return stat.read().rsplit(")", 1)[1].split()[0] != "Z"


def answered_by(server: ServerProcess, path: str = "/healthz") -> int:
    """Which API process answered ``path`` on a new connection."""
    with httpx.Client(base_url=server.url, timeout=60.0) as client:
        response = client.get(path)
    assert response.status_code == 200, response.text
    return int(response.headers["X-Api-Process"])


@pytest.fixture(
    scope="module",
    params=[pytest.param(b, marks=pytest.mark.db) for b in ("sqlite", "postgresql")],
)
def two_api_processes(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[ServerProcess]:
    """One server with two API processes per database, for the two tests below, in order: the
    first only reads and uploads, the second kills its processes and stops it (starting it
    cost ~7 s a test)."""
    tmp_path = tmp_path_factory.mktemp("two-api-processes")
    for database_url in fresh_database_url(request.param, request, tmp_path):
        yield from _two_api_processes(database_url, tmp_path)


def _two_api_processes(database_url: str, tmp_path: Path) -> Iterator[ServerProcess]:
    server = ServerProcess(
        database_url,
        workers=1,
        api_processes=2,
        env={
            "INVISIBLE_MAP_DATA_DIR": str(tmp_path / "var"),
            "INVISIBLE_MAP_UPLOADS_PER_MINUTE": "2",
        },
        log_path=tmp_path / "serve.log",
    )
    with server:
        yield server


@pytest.mark.slow
@pytest.mark.xdist_group("two_api_processes")
def test_two_api_processes_answer_and_share_the_upload_limit(
    two_api_processes: ServerProcess,
) -> None:
    server = two_api_processes
    pids = started_pids(server)
    assert sorted(pids) == [1, 2]
    assert len(set(pids.values())) == 2
    seen = set()
    for _ in range(ATTEMPTS):
        seen.add(answered_by(server))
        if seen == {1, 2}:
            break
    assert seen == {1, 2}
    admin = {"Authorization": f"Bearer {server.admin_key}"}
    with httpx.Client(base_url=server.url, timeout=30.0) as client:
        assert client.get("/readyz").status_code == 200
        info = client.get("/v1/info", headers=admin).json()
        assert info["worker_processes"]["configured"] == 1
        assert info["worker_processes"]["alive"] == 1
        created = client.post("/v1/keys", headers=admin, json={"name": "phone", "role": "device"})
        phone = {"Authorization": f"Bearer {created.json()['key']}"}

    def upload(name: str) -> httpx.Response:
        body = json.loads(ONETAG.read_bytes())
        body["map_id"] = name
        with httpx.Client(base_url=server.url, timeout=30.0) as client:  # a new connection
            return client.post("/v1/sessions", headers=phone, json=body)

    for name in ("first", "second"):
        assert upload(name).status_code == 202
    # Per process, one of the two would still take an upload; counted from the database,
    # neither does.
    refused_by = set()
    for k in range(ATTEMPTS):
        refused = upload(f"refused {k}")
        assert refused.status_code == 429, refused.text
        refused_by.add(int(refused.headers["X-Api-Process"]))
        if refused_by == {1, 2}:
            break
    assert refused_by == {1, 2}


@pytest.mark.slow
@pytest.mark.xdist_group("two_api_processes")
def test_a_killed_api_process_is_replaced_and_sigterm_stops_them_all(
    two_api_processes: ServerProcess,
) -> None:
    server = two_api_processes
    first = started_pids(server)
    os.kill(first[1], 9)
    # the other one answers meanwhile, and the dead one comes back under a new pid
    assert server.log_path is not None
    log_path = server.log_path
    # serve logs "started as pid" and then "restarted as pid": wait for the second line
    wait_for(
        lambda: (
            started_pids(server)[1] != first[1]
            and "API process api-1 restarted as pid" in log_path.read_text()
        ),
        timeout_s=30,
        what="api-1 restarted",
    )
    log = log_path.read_text()
    assert f"API process api-1 (pid {first[1]}) killed by SIGKILL" in log
    assert "API process api-1 restarted as pid" in log
    second = started_pids(server)
    assert alive(second[1])
    assert alive(second[2])
    assert not alive(first[1])
    # once the new api-1 serves, kill api-2: api-1 answers alone (api-2's replacement comes
    # only after its back-off and start-up)
    wait_for(lambda: answered_by(server) == 1, timeout_s=60, what="the new api-1 answering")
    os.kill(second[2], 9)
    assert answered_by(server, "/readyz") == 1

    assert server.stop() == 0
    final = started_pids(server)
    assert not any(alive(pid) for pid in final.values())
    log = server.log_path.read_text()
    assert "Traceback" not in log
    assert log.count("Finished server process") >= 1


@pytest.mark.parametrize(
    ("args", "env", "message"),
    [
        (["--api-processes", "0"], {}, "--api-processes must be 1–64, got 0"),
        (["--api-processes", "1000"], {}, "--api-processes must be 1–64, got 1000"),
        ([], {"INVISIBLE_MAP_API_PROCESSES": "0"}, "api_processes: Input should be greater"),
    ],
    ids=["zero", "thousand", "setting-zero"],
)
def test_serve_refuses_a_bad_number_of_api_processes(
    tmp_path: Path, args: list[str], env: dict[str, str], message: str
) -> None:
    environment = {
        name: value
        for name, value in os.environ.items()
        if name != "DATABASE_URL" and not name.startswith("INVISIBLE_MAP_")
    }
    environment.update(
        DATABASE_URL=f"sqlite:///{tmp_path / 'db.sqlite3'}",
        INVISIBLE_MAP_DATA_DIR=str(tmp_path / "var"),
        **env,
    )
    result = subprocess.run(
        [sys.executable, "-m", "app.cli", "serve", "--port", "1", *args],
        cwd=REPO_ROOT,
        env=environment,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert_one_line_error(result.returncode, result.stderr, message)
    assert result.stdout == ""
    assert not (tmp_path / "db.sqlite3").exists()  # nothing started, nothing migrated


def test_the_default_follows_the_cores_and_the_setting_wins(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: set(range(3)))
    assert default_api_processes() == 3
    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: set(range(64)))
    assert default_api_processes() == DEFAULT_API_PROCESSES_CAP
    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: set())
    assert default_api_processes() == 1
    monkeypatch.setenv("INVISIBLE_MAP_API_PROCESSES", "5")
    assert Settings().api_processes == 5


@pytest.mark.slow
def test_api_processes_stop_when_serve_is_killed(tmp_path: Path) -> None:
    server = ServerProcess(
        f"sqlite:///{tmp_path / 'db.sqlite3'}",
        workers=0,
        api_processes=2,
        env={"INVISIBLE_MAP_DATA_DIR": str(tmp_path / "var")},
        log_path=tmp_path / "serve.log",
    )
    with server:
        pids = started_pids(server)
        assert len(pids) == 2
        os.kill(server.pid, 9)  # serve alone, not its process group
        wait_for(
            lambda: not any(alive(pid) for pid in pids.values()),
            timeout_s=30,
            what="the API processes to stop without their serve",
        )

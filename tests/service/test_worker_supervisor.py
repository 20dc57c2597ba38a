"""The supervisor of ``serve``'s worker processes (``workers/supervisor.py``): a worker process
that dies is reaped, logged and replaced with back-off; ``/readyz`` and ``/v1/info`` say when
none is alive; and ``invisible-map serve`` itself, its only worker killed with SIGKILL, goes on
building maps.
"""

from __future__ import annotations

import itertools
import logging
import os
import signal
import time
from pathlib import Path

import httpx
import pytest
from api_support import ADMIN, ADMIN_KEY
from fastapi.testclient import TestClient

from app.cli.server_process import ServerProcess
from app.config import Settings
from app.main import create_app
from app.storage import queue
from app.storage.db import Database
from app.storage.orm import JobState
from tests.service.helpers import (
    get_job,
    insert_session,
    session_bytes,
    simulated_bytes,
    wait_for,
)
from workers import supervisor as supervisor_module
from workers.supervisor import WorkerSupervisor, describe_exit

pytestmark = pytest.mark.slow

FAST = {"lease_s": 2.0, "heartbeat_s": 0.5, "poll_s": 0.05, "retry_backoff_s": 0.0}


def worker_pids(db: Database) -> set[int]:
    with db.read() as db_session:
        return {w.pid for w in queue.alive_workers(db_session, within_s=1.5)}


def is_zombie(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False  # reaped
    return status.rsplit(")", 1)[1].split()[0] == "Z"


def test_describe_exit() -> None:
    assert describe_exit(-signal.SIGKILL) == "killed by SIGKILL"
    assert describe_exit(1) == "exited with status 1"


def test_a_killed_worker_process_is_reaped_logged_and_replaced(
    db: Database, database_url: str, caplog: pytest.LogCaptureFixture
) -> None:
    settings = Settings(database_url=database_url, **FAST)
    supervisor = WorkerSupervisor(settings, 1)
    caplog.set_level(logging.INFO, logger="workers.supervisor")
    supervisor.start()
    try:
        wait_for(lambda: len(worker_pids(db)) == 1, timeout_s=60, what="the worker to register")
        (first,) = supervisor.pids
        assert worker_pids(db) == {first}

        killed_s = time.monotonic()
        os.kill(first, signal.SIGKILL)
        wait_for(lambda: bool(worker_pids(db) - {first}), timeout_s=30, what="a replacement worker")
        replaced_s = time.monotonic() - killed_s
        print(f"worker death to its replacement's first heartbeat: {replaced_s:.2f} s")

        assert not is_zombie(first)
        assert supervisor.alive == 1
        assert supervisor.restarts == 1
        assert first not in supervisor.pids
        assert any(
            f"(pid {first}) killed by SIGKILL" in r.getMessage()
            and "restarting it in 0.5 s" in r.getMessage()
            for r in caplog.records
        ), caplog.text
        assert replaced_s < 10

        # and the replacement builds maps
        job_id = insert_session(db, session_bytes("onetag")).job_id
        wait_for(
            lambda: get_job(db, job_id).state == JobState.SUCCEEDED,
            timeout_s=60,
            what="the job to succeed on the replacement",
        )
    finally:
        supervisor.stop(timeout_s=20)
    assert supervisor.alive == 0


def test_the_job_of_a_killed_worker_process_is_requeued_at_once(
    db: Database, database_url: str
) -> None:
    """Not after its lease (30 s here) runs out: the supervisor ends the dead process's lease."""
    settings = Settings(database_url=database_url, **{**FAST, "lease_s": 30.0, "heartbeat_s": 0.5})
    job_id = insert_session(db, simulated_bytes(6_000)).job_id  # long enough to be killed mid-way
    supervisor = WorkerSupervisor(settings, 1)
    supervisor.start()
    try:
        wait_for(
            lambda: get_job(db, job_id).stage == "optimize", timeout_s=60, what="the optimization"
        )
        (pid,) = supervisor.pids
        os.kill(pid, signal.SIGKILL)
        killed_s = time.monotonic()
        wait_for(
            lambda: get_job(db, job_id).attempts == 2,
            timeout_s=25,  # < the 30 s lease
            what="the replacement to take the job again",
        )
        print(f"killed mid-job: taken again {time.monotonic() - killed_s:.1f} s after the kill")
        # the build itself may take longer than the lease on a loaded machine: its heartbeat
        # keeps it
        wait_for(
            lambda: get_job(db, job_id).state == JobState.SUCCEEDED,
            timeout_s=120,
            what="the replacement to build the job",
        )
        info = get_job(db, job_id)
        assert info.attempts == 2
        assert "lease expired (worker lost); requeued" in info.log_tail
        # the dead one's row is gone, the replacement's alive (a row counts as alive for 1.5 s
        # after its last beat, which a loaded machine can make late)
        wait_for(
            lambda: worker_pids(db) == set(supervisor.pids),
            timeout_s=20,
            what="the worker rows to be the live processes'",
        )
    finally:
        supervisor.stop(timeout_s=20)


@pytest.mark.parametrize("database_url", ["sqlite"], indirect=True)
def test_a_worker_that_keeps_dying_is_restarted_with_growing_waits(
    database_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(supervisor_module, "FIRST_RESTART_S", 0.2)
    settings = Settings(database_url=database_url, **FAST)
    supervisor = WorkerSupervisor(settings, 1)
    supervisor.start()
    try:
        starts: list[float] = []
        for _ in range(3):
            wait_for(lambda: supervisor.alive == 1, timeout_s=30, what="a live worker")
            starts.append(time.monotonic())
            (pid,) = supervisor.pids
            os.kill(pid, signal.SIGKILL)
            wait_for(lambda pid=pid: pid not in supervisor.pids, timeout_s=10, what="death")
        wait_for(lambda: supervisor.alive == 1, timeout_s=30, what="the third restart")
        assert supervisor.restarts == 3
        gaps = [b - a for a, b in itertools.pairwise(starts)]
        assert gaps[1] > gaps[0] + 0.15  # 0.2 s, then 0.4 s (and so on up to 60 s)
    finally:
        supervisor.stop(timeout_s=20)


class FakePool:
    def __init__(self, configured: int, alive: int, restarts: int = 0) -> None:
        self.configured, self.alive, self.restarts = configured, alive, restarts


@pytest.mark.parametrize(
    ("pool", "ready", "processes"),
    [
        (None, 200, None),
        (FakePool(2, 1, 3), 200, {"configured": 2, "alive": 1, "restarts": 3}),
        (FakePool(2, 0, 5), 503, {"configured": 2, "alive": 0, "restarts": 5}),
    ],
)
def test_readyz_and_info_say_when_no_worker_process_is_alive(
    database_url: str, pool: FakePool | None, ready: int, processes: dict[str, int] | None
) -> None:
    app = create_app(
        Settings(database_url=database_url, admin_key=ADMIN_KEY),
        worker_pool=pool,
    )
    with TestClient(app) as client:
        readyz = client.get("/readyz")
        assert readyz.status_code == ready, readyz.text
        info = client.get("/v1/info", headers=ADMIN)
        assert info.status_code == 200, info.text
        assert info.json()["worker_processes"] == processes
        if ready == 503:
            assert readyz.json()["code"] == "no_worker"
            assert "no worker process is alive (0 of 2" in readyz.json()["detail"]
            assert info.json()["warnings"] == [readyz.json()["detail"]]
        else:
            assert info.json()["warnings"] == []


@pytest.mark.parametrize("database_url", ["sqlite"], indirect=True)
def test_serve_replaces_its_only_worker_killed_with_sigkill(
    db: Database, database_url: str, tmp_path: Path
) -> None:
    """The probe's case: ``kill -9`` of ``serve``'s only worker. Its job is requeued once the
    lease expires and built by the replacement, and jobs queued meanwhile run."""
    env = {
        "INVISIBLE_MAP_LEASE_S": "2",
        "INVISIBLE_MAP_HEARTBEAT_S": "0.5",
        "INVISIBLE_MAP_POLL_S": "0.05",
        "INVISIBLE_MAP_DATA_DIR": str(tmp_path / "var"),
    }
    log = tmp_path / "serve.log"
    with (
        ServerProcess(database_url, workers=1, env=env, log_path=log) as server,
        httpx.Client(base_url=server.url, timeout=10) as client,
    ):
        auth = {"Authorization": f"Bearer {server.admin_key}"}
        wait_for(lambda: len(worker_pids(db)) == 1, timeout_s=60, what="the worker")
        (first,) = worker_pids(db)
        os.kill(first, signal.SIGKILL)
        killed_s = time.monotonic()
        queued = [insert_session(db, session_bytes("onetag")).job_id for _ in range(2)]
        wait_for(lambda: bool(worker_pids(db) - {first}), timeout_s=30, what="a new worker")
        replaced_s = time.monotonic() - killed_s
        print(f"serve: worker death to its replacement's heartbeat {replaced_s:.2f} s")
        wait_for(
            lambda: all(get_job(db, j).state == JobState.SUCCEEDED for j in queued),
            timeout_s=60,
            what="the queued jobs to succeed",
        )
        assert not is_zombie(first)
        info = client.get("/v1/info", headers=auth).json()
        assert info["worker_processes"] == {"configured": 1, "alive": 1, "restarts": 1}
        assert client.get("/readyz").status_code == 200
        assert server.stop() == 0
    text = log.read_text()
    assert f"(pid {first}) killed by SIGKILL" in text
    assert "restarted as pid" in text

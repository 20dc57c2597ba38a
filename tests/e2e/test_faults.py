"""Faults, with real processes: PostgreSQL stopped for 10 s under a running API and workers, the
API killed in the middle of an upload and after storing one, a disk that fills up, a read-only
data directory. In each: no 500, nothing acknowledged is lost, nothing is stored or run twice.

(A worker killed with SIGKILL mid-job and mid-sweep is in tests/service/test_worker_processes.py;
a corrupt or truncated stored upload in tests/service/test_worker.py.)
"""

from __future__ import annotations

import re
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import func, select

from app.cli.server_process import ServerProcess, WorkerProcess, free_port
from app.client import ApiError, Client
from app.storage.db import Database
from app.storage.migrate import upgrade_to_head
from app.storage.orm import Job, MapVersion, SessionRow
from tests.e2e.fault_support import (
    ResponseDroppingProxy,
    SmallDisk,
    private_postgres,
    unavailable,
)
from tests.service.helpers import wait_for

pytestmark = [pytest.mark.slow]

SESSIONS = ("occam_room", "floor_2_straight", "straight_209_occam", "desnat_straight_once")
OUTAGE_S = 10.0
#: Uploads accepted before the outage (two worker processes are still busy with them when it
#: starts) and after it: enough to have jobs queued, running and finished across it.
UPLOADS_BEFORE = 6
UPLOADS_AFTER = 2


def counts(url: str) -> dict[str, int]:
    """Rows of the tables that must not gain or lose anything."""
    database = Database(url)
    try:
        with database.read() as tx:
            return {
                table.__tablename__: tx.scalar(select(func.count()).select_from(table)) or 0
                for table in (SessionRow, MapVersion, Job)
            }
    finally:
        database.dispose()


def jobs_of(url: str) -> dict[int, tuple[str, int]]:
    """job id → (state, attempts)."""
    database = Database(url)
    try:
        with database.read() as tx:
            rows = tx.execute(select(Job.id, Job.state, Job.attempts)).all()
        return {job_id: (state, attempts) for job_id, state, attempts in rows}
    finally:
        database.dispose()


def no_tracebacks(*logs: Path) -> None:
    for log in logs:
        text = log.read_text(errors="replace")
        assert "Traceback" not in text, f"{log.name} has a traceback:\n{text[-3000:]}"


def status_of(call: Callable[[], Any]) -> tuple[int, str | None]:
    """(status, error code) of an API call: 200 if it returned."""
    try:
        call()
    except ApiError as err:
        return err.status_code, err.code
    return 200, None


# --------------------------------------------------------------------------- PostgreSQL down


@pytest.mark.db
def test_postgres_stopped_for_10_s_under_load_loses_nothing_and_runs_nothing_twice(
    tmp_path: Path, data_dir: Path
) -> None:
    paths = [data_dir / "sessions" / f"{name}.json" for name in SESSIONS]
    env = {"INVISIBLE_MAP_HEARTBEAT_S": "2", "INVISIBLE_MAP_POLL_S": "0.1"}
    api_log, worker_log = tmp_path / "api.log", tmp_path / "worker.log"
    with private_postgres(tmp_path) as postgres:
        url = postgres.create_database("invisible_map")
        with (
            ServerProcess(url, workers=0, env=env, log_path=api_log) as server,
            WorkerProcess(url, processes=2, env=env, log_path=worker_log),
            Client(server.url, api_key=server.admin_key, timeout_s=60) as client,
        ):
            accepted = [
                client.upload_session(paths[k % len(paths)], idempotency_key=f"before-{k}")
                for k in range(UPLOADS_BEFORE)
            ]
            wait_for(
                lambda: client.list_jobs(state="running")["count"] > 0,
                timeout_s=60,
                what="a job running",
            )
            postgres.stop("fast")
            seen: dict[str, set[tuple[int, str | None]]] = {}
            refused_uploads = 0
            outage_end = time.monotonic() + OUTAGE_S
            while time.monotonic() < outage_end:
                for what, call in {
                    "GET /v1/maps": client.list_maps,
                    "GET /v1/jobs/{id}": lambda: client.get_job(accepted[0]["job_id"]),
                    "GET /readyz": client.ready,
                    "GET /healthz": client.health,
                    "POST /v1/sessions": lambda: client.upload_session(paths[0]),
                }.items():
                    answer = status_of(call)
                    seen.setdefault(what, set()).add(answer)
                    refused_uploads += what == "POST /v1/sessions" and answer[0] == 503
                time.sleep(0.5)
            postgres.start()
            restarted_s = time.monotonic()
            wait_for(lambda: status_of(client.info)[0] == 200, timeout_s=60, what="the API back")
            recovery_s = time.monotonic() - restarted_s
            accepted += [
                client.upload_session(path, idempotency_key=f"after-{k}")
                for k, path in enumerate(paths[:UPLOADS_AFTER])
            ]
            for answer in accepted:
                client.wait_for_job(answer["job_id"], timeout_s=180)
        after = counts(url)
        jobs = jobs_of(url)

    assert seen["GET /healthz"] == {(200, None)}
    assert seen["GET /readyz"] == {(503, "not_ready")}
    for what in ("GET /v1/maps", "GET /v1/jobs/{id}", "POST /v1/sessions"):
        assert seen[what] == {(503, "database_unavailable")}, what
    assert refused_uploads > 0
    assert recovery_s < 15
    print(f"PostgreSQL outage: API answering {recovery_s:.1f} s after the restart")  # README
    # nothing acknowledged lost, nothing refused stored, nothing stored or run twice
    stored = UPLOADS_BEFORE + UPLOADS_AFTER
    assert after == {"session": stored, "map_version": stored, "job": stored}
    assert {job_id: state for job_id, (state, _) in jobs.items()} == dict.fromkeys(
        [a["job_id"] for a in accepted], "succeeded"
    )
    assert {attempts for _, attempts in jobs.values()} == {1}
    worker_text = worker_log.read_text()
    assert "waiting for the database" in worker_text or "trying again" in worker_text
    no_tracebacks(api_log, worker_log)


# --------------------------------------------------------------------------- API killed


def raw_post_start(port: int, key: str, body: bytes, *, idempotency_key: str) -> socket.socket:
    """Send an upload's headers and the first half of its body, and leave it there."""
    connection = socket.create_connection(("127.0.0.1", port))
    head = (
        "POST /v1/sessions HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        f"Authorization: Bearer {key}\r\nContent-Type: application/json\r\n"
        f"Idempotency-Key: {idempotency_key}\r\nContent-Length: {len(body)}\r\n\r\n"
    )
    connection.sendall(head.encode() + body[: len(body) // 2])
    return connection


@pytest.mark.db
def test_api_killed_mid_upload_then_the_retry_with_the_same_key_is_stored_once(
    database_url: str, tmp_path: Path, data_dir: Path
) -> None:
    body = (data_dir / "sessions" / "floor_2_straight.json").read_bytes()
    first = ServerProcess(database_url, log_path=tmp_path / "api-1.log")
    with first:
        connection = raw_post_start(first.port, first.admin_key, body, idempotency_key="walk-1")
        time.sleep(0.5)  # the server is reading the body
        first.kill(signal.SIGKILL)
        first.stop()
        connection.close()
    assert counts(database_url)["session"] == 0

    restarted = ServerProcess(
        database_url, admin_key=first.admin_key, log_path=tmp_path / "api-2.log"
    )
    with restarted, Client(restarted.url, api_key=restarted.admin_key) as client:
        accepted = client.upload_session(body, idempotency_key="walk-1", retries=3)
        replay = client.request(
            "POST",
            "/v1/sessions",
            content=body,
            headers={"Content-Type": "application/json", "Idempotency-Key": "walk-1"},
        )
        raw = client.raw_session(accepted["session_id"])

    assert replay.status_code == 202
    assert replay.headers["Idempotent-Replayed"] == "true"
    assert replay.json()["session_id"] == accepted["session_id"]
    assert raw == body
    assert counts(database_url) == {"session": 1, "map_version": 0, "job": 1}


@pytest.mark.db
def test_an_upload_whose_answer_was_lost_when_the_api_died_is_answered_by_the_retry(
    database_url: str, tmp_path: Path, data_dir: Path
) -> None:
    """The upload was stored, then the API was killed before the phone got the answer: the
    phone's retry (same Idempotency-Key) gets the first upload's ids, and nothing is stored
    twice."""
    body = (data_dir / "sessions" / "occam_room.json").read_bytes()
    port = free_port()
    first = ServerProcess(database_url, port=port, log_path=tmp_path / "api-1.log")
    second = ServerProcess(
        database_url, port=port, admin_key=first.admin_key, log_path=tmp_path / "api-2.log"
    )

    def kill_and_restart() -> None:
        first.kill(signal.SIGKILL)
        threading.Thread(target=lambda: (first.stop(), second.start()), daemon=True).start()

    with first:
        proxy = ResponseDroppingProxy(port, on_first_response=kill_and_restart)
        try:
            with Client(proxy.url, api_key=first.admin_key) as client:
                accepted = client.upload_session(
                    body, idempotency_key="walk-2", retries=60, retry_wait_s=0.25
                )
                jobs = client.list_jobs()
        finally:
            proxy.close()
            second.stop()

    assert proxy.dropped.is_set()
    assert counts(database_url) == {"session": 1, "map_version": 0, "job": 1}
    assert jobs["count"] == 1
    assert jobs["data"][0]["id"] == accepted["job_id"]


# --------------------------------------------------------------------------- the disk


DISK_BYTES = 3 * 2**20


def test_a_full_disk_gives_clear_503s_and_leaves_no_corrupt_state(
    tmp_path: Path, data_dir: Path
) -> None:
    disk = SmallDisk(tmp_path / "disk", DISK_BYTES)
    try:
        database_file = disk.mount_point / "invisible-map.sqlite3"
        url = f"sqlite:///{database_file}"
        env = {
            "INVISIBLE_MAP_DATA_DIR": str(disk.mount_point),
            "INVISIBLE_MAP_LEASE_S": "4",
            "INVISIBLE_MAP_HEARTBEAT_S": "1",
            "INVISIBLE_MAP_POLL_S": "0.1",
            "INVISIBLE_MAP_RETRY_BACKOFF_S": "0.5",
            "INVISIBLE_MAP_MAX_ATTEMPTS": "10",
        }
        bodies = [(data_dir / "sessions" / f"{name}.json").read_bytes() for name in SESSIONS]
        log = tmp_path / "serve.log"
        with (
            ServerProcess(url, workers=1, env=env, log_path=log) as server,
            Client(server.url, api_key=server.admin_key, timeout_s=60) as client,
        ):
            wait_for(lambda: client.info()["workers"], timeout_s=60, what="the worker up")
            accepted: list[tuple[bytes, dict[str, Any]]] = []
            refusal: ApiError | None = None
            for k in range(100):
                body = bodies[k % len(bodies)]
                try:
                    accepted.append((body, client.upload_session(body, idempotency_key=f"u{k}")))
                except ApiError as err:
                    refusal = err
                    break
            assert refusal is not None, "the disk never filled"
            full_free_bytes = disk.free_bytes()
            map_answer = status_of(lambda: client.get_map(accepted[0][1]["map_id"]))
            # the disk stays full until the worker (jobs are still queued) has met it too
            wait_for(
                lambda: re.search(r"worker-\d.*storage_full", log.read_text()),
                timeout_s=60,
                what="the worker meeting the full disk",
            )
            disk.grow(64 * 2**20)  # room again
            last = bodies[0]
            accepted.append((last, client.upload_session(last, idempotency_key="after")))
            for _, answer in accepted:
                client.wait_for_job(answer["job_id"], timeout_s=180)
            raw = [client.raw_session(answer["session_id"]) for _, answer in accepted]
        integrity = sqlite3.connect(database_file).execute("PRAGMA integrity_check").fetchall()
        after = counts(url)
    finally:
        disk.unmount()

    assert (refusal.status_code, refusal.code) == (503, "storage_full")
    assert refusal.detail == "the server's storage is full; nothing was stored; try again later"
    assert full_free_bytes < 512 * 2**10
    assert map_answer == (200, None)  # reads go on while the disk is full
    assert len(accepted) >= 3
    assert integrity == [("ok",)]
    assert after == {"session": len(accepted), "map_version": len(accepted), "job": len(accepted)}
    assert raw == [body for body, _ in accepted]
    no_tracebacks(log)  # the worker said it met the full disk in one line


def test_a_read_only_data_dir_is_refused_in_one_line_and_left_as_it_was(tmp_path: Path) -> None:
    """``serve`` (with or without migrating) and ``worker`` on a data directory that cannot be
    written (a read-only mount, as after a disk error) stop at once with one line saying so,
    and the database file is left byte for byte as it was. (A disk that turns read-only under a
    running server cannot be made here: Linux refuses to remount a file system read-only while
    files on it are open for writing. What the API answers then — 503 storage_read_only or
    storage_unavailable — is checked in tests/service/test_database_faults.py.)"""
    data = tmp_path / "data"
    database_file = data / "invisible-map.sqlite3"
    database = Database(f"sqlite:///{database_file}")
    upgrade_to_head(database)
    database.dispose()
    before = database_file.read_bytes()
    read_only = tmp_path / "read-only"
    read_only.mkdir()
    mounted = subprocess.run(
        f"mount --bind {data} {read_only} && mount -o remount,ro,bind {read_only}",
        shell=True,
        capture_output=True,
        text=True,
    )
    if mounted.returncode != 0:
        unavailable(f"cannot make a read-only bind mount here: {mounted.stderr.strip()}")
    env = {
        "PATH": "/usr/bin:/bin",
        "DATABASE_URL": f"sqlite:///{read_only / 'invisible-map.sqlite3'}",
        "INVISIBLE_MAP_DATA_DIR": str(read_only),
        "INVISIBLE_MAP_ADMIN_KEY": "im_test_admin_read_only_dir",
    }
    commands = {
        "serve": ["serve", "--port", str(free_port())],
        "serve --no-migrate": ["serve", "--port", str(free_port()), "--no-migrate"],
        "worker": ["worker"],
    }
    try:
        results = {
            name: subprocess.run(
                [sys.executable, "-m", "app.cli", *args],
                env=env,
                capture_output=True,
                text=True,
                timeout=60,
            )
            for name, args in commands.items()
        }
    finally:
        subprocess.run(["umount", str(read_only)], check=False)

    for name, result in results.items():
        lines = result.stderr.strip().splitlines()
        assert result.returncode == 1, (name, result.stderr)
        assert len(lines) == 1, (name, result.stderr)
        assert lines[0].startswith("invisible-map: error: cannot "), name
        assert "read-only" in lines[0] or "readonly" in lines[0] or "unable to open" in lines[0]
    assert database_file.read_bytes() == before

"""A worker stalled inside its transaction (stopped with SIGSTOP, say) stops nobody on PostgreSQL
(issue 19, finding 4): requests wait at most ``INVISIBLE_MAP_DB_LOCK_TIMEOUT_S`` for its row
locks and are answered 503 ``database_unavailable`` with Retry-After instead of hanging (30 such
requests used to hold the whole pool), and the server ends the stalled transaction after
``INVISIBLE_MAP_DB_IDLE_IN_TRANSACTION_TIMEOUT_S``, releasing its locks. (SQLite: one writer at
a time, so a writer stalled inside a transaction holds every other for SQLite's 30 s busy
timeout, then 503; the worker's transactions are therefore all short, its bulk data written in
chunks outside the fenced one: ``test_version_blobs.py`` stalls a worker there, on both
databases.)"""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Any

import pytest
from api_support import ADMIN, ONETAG, running_api
from sqlalchemy import select

from app.config import Settings
from app.storage import queue
from app.storage.db import Database, ServerTimeouts
from app.storage.orm import Job

pytestmark = pytest.mark.db


def stalled_worker(url: str, job_id: int, *, idle_s: float) -> tuple[Any, Database]:
    """A connection that locks the job's row, as a worker storing its result does, and then
    stalls (does nothing more) with the server's idle-in-transaction limit ``idle_s``."""
    settings = Settings(database_url=url, db_idle_in_transaction_timeout_s=idle_s)
    worker_db = Database(url, timeouts=ServerTimeouts.of(settings))
    transaction = worker_db.transaction()
    db_session = transaction.__enter__()
    db_session.execute(select(Job).where(Job.id == job_id).with_for_update()).one()
    return transaction, worker_db


def test_a_stalled_transaction_holds_no_request_and_is_ended(postgres_url: str) -> None:
    with running_api(postgres_url, db_lock_timeout_s=1.0) as api:
        job_id = api.uploaded(ONETAG)["job_id"]
        lease = queue.claim(api.db, worker_id="stalled", lease_s=600)
        assert lease is not None
        transaction, worker_db = stalled_worker(postgres_url, job_id, idle_s=4.0)
        started_s = time.monotonic()
        answers: list[Any] = []
        threads = [
            threading.Thread(
                target=lambda: answers.append(
                    api.client.post(f"/v1/jobs/{job_id}/cancel", headers=ADMIN)
                )
            )
            for _ in range(12)
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(30)
        waited_s = time.monotonic() - started_s
        assert len(answers) == 12
        assert {a.status_code for a in answers} == {503}, [a.text for a in answers]
        assert answers[0].json()["code"] == "database_unavailable"
        assert "retry-after" in answers[0].headers
        assert waited_s < 10  # each waited its second, not forever
        assert api.client.get("/v1/maps", headers=ADMIN).status_code == 200  # others go on

        time.sleep(4.5)  # the server ends the stalled transaction (idle in transaction 4 s)
        canceled = api.client.post(f"/v1/jobs/{job_id}/cancel", headers=ADMIN)
        assert canceled.status_code == 200, canceled.text
        assert canceled.json()["cancel_requested"] is True
        # its connection was closed by the server: that is the point
        with contextlib.suppress(Exception):
            transaction.__exit__(None, None, None)
        worker_db.dispose()

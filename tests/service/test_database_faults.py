"""Database faults, in process: what ``app.storage.db.database_fault`` calls each real driver
error, the 503 the API answers with (nothing stored), and the worker riding out an outage
shorter than its lease (the job goes on in the same attempt and stores one version).

The faults with real processes — PostgreSQL stopped and restarted, a disk filling up, the API
killed mid-upload — are in ``tests/e2e/test_faults.py``.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator

import pytest
from sqlalchemy import create_engine, make_url, text
from sqlalchemy.exc import DBAPIError, IntegrityError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout

from app.storage.db import Database, DatabaseFault, database_fault
from app.storage.orm import JobState, SessionRow
from tests.service.api_support import ADMIN, ONETAG, running_api
from tests.service.helpers import get_job, insert_session, session_bytes, version_count
from tests.service.test_worker import action, settings_for, with_stage_before, worker_with
from workers import pipeline
from workers.main import Worker
from workers.pipeline import JobContext, Stage

UNREACHABLE_POSTGRES = "postgresql+psycopg://postgres@127.0.0.1:1/none?connect_timeout=2"


def raised_by(database: Database, statement: str) -> BaseException:
    """The error ``statement`` raises in a write transaction of ``database``."""
    with pytest.raises(DBAPIError) as raised, database.transaction() as tx:
        tx.execute(text(statement))
    return raised.value


# --------------------------------------------------------------------------- classification


def test_an_unreachable_server_is_unavailable() -> None:
    database = Database(UNREACHABLE_POSTGRES)
    with pytest.raises(OperationalError) as raised:
        database.ping()
    database.dispose()
    assert database_fault(raised.value) == DatabaseFault.UNAVAILABLE


def test_a_full_sqlite_file_is_storage_full(tmp_path) -> None:
    database = Database(f"sqlite:///{tmp_path / 'full.sqlite3'}")
    with database.transaction() as tx:
        tx.execute(text("CREATE TABLE filler (data BLOB)"))
    # max_page_count is the file size SQLite may grow to: what a full disk looks like to it.
    with database.engine.connect() as connection:
        connection.exec_driver_sql("PRAGMA max_page_count = 20")
        with pytest.raises(OperationalError) as raised:
            connection.exec_driver_sql(
                "WITH RECURSIVE n(k) AS (SELECT 1 UNION ALL SELECT k + 1 FROM n WHERE k < 100) "
                "INSERT INTO filler SELECT zeroblob(4096) FROM n"
            )
    database.dispose()
    assert database_fault(raised.value) == DatabaseFault.STORAGE_FULL


def test_a_read_only_sqlite_file_is_read_only(tmp_path) -> None:
    path = tmp_path / "ro.sqlite3"
    writable = Database(f"sqlite:///{path}")
    with writable.transaction() as tx:
        tx.execute(text("CREATE TABLE t (x INTEGER)"))
    writable.dispose()
    read_only = create_engine(f"sqlite:///file:{path}?mode=ro&uri=true")
    with pytest.raises(OperationalError) as raised, read_only.begin() as connection:
        connection.exec_driver_sql("INSERT INTO t VALUES (1)")
    read_only.dispose()
    assert database_fault(raised.value) == DatabaseFault.READ_ONLY


def test_a_sqlite_file_that_cannot_be_opened_is_storage_unavailable(tmp_path) -> None:
    engine = create_engine(f"sqlite:///file:{tmp_path / 'absent.sqlite3'}?mode=ro&uri=true")
    with pytest.raises(OperationalError) as raised, engine.connect():
        pass
    engine.dispose()
    assert database_fault(raised.value) == DatabaseFault.CANNOT_OPEN


def test_a_read_only_postgres_is_read_only(postgres_url: str) -> None:
    database = Database(postgres_url)
    with database.transaction() as tx:
        tx.execute(text("SET TRANSACTION READ ONLY"))
        with pytest.raises(DBAPIError) as raised:
            tx.execute(text("CREATE TABLE t (x integer)"))
    database.dispose()
    assert database_fault(raised.value) == DatabaseFault.READ_ONLY


def test_a_terminated_postgres_connection_is_unavailable(postgres_url: str) -> None:
    database = Database(postgres_url)
    with database.engine.connect() as connection:
        pid = connection.exec_driver_sql("SELECT pg_backend_pid()").scalar_one()
        admin = create_engine(make_url(postgres_url), isolation_level="AUTOCOMMIT")
        with admin.connect() as other:
            other.execute(text("SELECT pg_terminate_backend(:pid)"), {"pid": pid})
        admin.dispose()
        with pytest.raises(DBAPIError) as raised:
            connection.exec_driver_sql("SELECT 1")
    database.dispose()
    assert database_fault(raised.value) == DatabaseFault.UNAVAILABLE


def test_errors_of_the_request_or_the_code_are_not_faults(db: Database) -> None:
    integrity = raised_by(db, "INSERT INTO api_key (id) VALUES (NULL)")
    assert isinstance(integrity, IntegrityError)
    assert database_fault(integrity) is None
    syntax = raised_by(db, "SELEC 1")  # an OperationalError on SQLite, but the request's fault
    assert database_fault(syntax) is None
    missing = raised_by(db, "SELECT * FROM no_such_table")
    assert database_fault(missing) is None
    assert database_fault(ValueError("not a database error")) is None
    assert database_fault(PoolTimeout("QueuePool limit reached")) == DatabaseFault.UNAVAILABLE


# --------------------------------------------------------------------------- the API


def set_read_only(url: str, read_only: bool) -> None:
    """Make the PostgreSQL database at ``url`` refuse writes in new connections (as a standby
    does), or accept them again."""
    name = make_url(url).database
    value = "on" if read_only else "off"
    admin = create_engine(make_url(url), isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text("SET default_transaction_read_only = off"))
        connection.execute(
            text(f'ALTER DATABASE "{name}" SET default_transaction_read_only = {value}')
        )
    admin.dispose()


def test_an_upload_to_a_read_only_database_is_503_and_stores_nothing(postgres_url: str) -> None:
    with running_api(postgres_url) as api:
        before = api.count(SessionRow)
        set_read_only(postgres_url, True)
        api.db.engine.dispose()  # new connections take the setting
        response = api.upload(ONETAG)
        maps_status = api.client.get("/v1/maps", headers=ADMIN).status_code
        set_read_only(postgres_url, False)
        api.db.engine.dispose()
        after = api.count(SessionRow)
        again = api.upload(ONETAG)

    assert maps_status == 200  # reads go on
    assert response.status_code == 503
    assert response.headers["Retry-After"] == "60"
    assert response.json() == {
        "detail": "the server's storage is read-only; nothing was stored; try again later",
        "code": "storage_read_only",
        "field": None,
    }
    assert after == before
    assert again.status_code == 202


# --------------------------------------------------------------------------- the worker


@pytest.fixture
def unreachable() -> Iterator[Database]:
    database = Database(UNREACHABLE_POSTGRES)
    yield database
    database.dispose()


def store_during_outage(calls: int, unreachable: Database) -> tuple[list[Stage], list[str]]:
    """The build-map stages, whose ``store`` meets a database that does not answer in its first
    ``calls`` runs (it runs against ``unreachable``); and the list of what each run met."""
    store = next(stage for stage in pipeline.BUILD_MAP_STAGES if stage.name == "store")
    flaky_store, met = outage_for(calls, unreachable, store)
    stages = [flaky_store if s.name == "store" else s for s in pipeline.BUILD_MAP_STAGES]
    return stages, met


def outage_for(calls: int, unreachable: Database, run: Stage) -> tuple[Stage, list[str]]:
    """``run`` as a stage whose first ``calls`` runs meet a database that does not answer (the
    stage runs against ``unreachable``); returns the stage and a list of what each run met."""
    met: list[str] = []

    def flaky(ctx: JobContext) -> None:
        if len(met) < calls:
            met.append("outage")
            real, ctx.db = ctx.db, unreachable
            try:
                run.run(ctx)
            finally:
                ctx.db = real
            return
        met.append("database")
        run.run(ctx)

    return Stage(name=run.name, weight=run.weight, run=flaky), met


def test_an_outage_shorter_than_the_lease_is_waited_out_in_the_same_attempt(
    db: Database, unreachable: Database, caplog: pytest.LogCaptureFixture, monkeypatch
) -> None:
    monkeypatch.setattr(pipeline.runner, "OUTAGE_FIRST_WAIT_S", 0.05)
    inserted = insert_session(db, session_bytes("onetag"))
    stages, met = store_during_outage(3, unreachable)

    with caplog.at_level(logging.WARNING, logger="workers.pipeline"):
        assert worker_with(db, stages).run_once()

    info = get_job(db, inserted.job_id)
    assert (info.state, info.attempts, info.error) == (JobState.SUCCEEDED, 1, None)
    assert met == ["outage", "outage", "outage", "database"]
    assert version_count(db, job_id=inserted.job_id) == 1
    waits = [r for r in caplog.records if getattr(r, "action", None) == "database_fault"]
    assert len(waits) == 3
    assert "stage store: database_unavailable" in waits[0].getMessage()


def test_an_outage_longer_than_the_lease_ends_the_attempt_and_stores_nothing(
    db: Database, unreachable: Database, monkeypatch
) -> None:
    monkeypatch.setattr(pipeline.runner, "OUTAGE_FIRST_WAIT_S", 0.05)
    inserted = insert_session(db, session_bytes("onetag"))
    stages, met = store_during_outage(10_000, unreachable)
    # lease 1.5 s less the 1 s margin: the store is given up after about 0.5 s of waiting
    worker = worker_with(db, stages, lease_s=1.5, heartbeat_s=0.2)

    assert worker.run_once()

    info = get_job(db, inserted.job_id)
    assert info.state == JobState.QUEUED  # a transient error: tried again later
    assert info.attempts == 1
    assert "OperationalError" in (info.error or "")
    assert 2 <= len(met) <= 6
    assert version_count(db, job_id=inserted.job_id) == 0


def test_a_stage_error_that_is_not_a_fault_is_not_waited_for(db: Database) -> None:
    inserted = insert_session(db, session_bytes("onetag"))
    runs: list[int] = []

    def broken(_ctx: JobContext) -> None:
        runs.append(1)
        raise RuntimeError("a bug")

    report_stages = with_stage_before("store", action("broken", broken))
    assert worker_with(db, report_stages).run_once()
    assert runs == [1]
    assert get_job(db, inserted.job_id).error == "broken: RuntimeError: a bug"


def test_an_idle_worker_logs_an_outage_once_and_backs_off(
    unreachable: Database, caplog: pytest.LogCaptureFixture
) -> None:
    worker = Worker(unreachable, settings_for(unreachable, poll_s=0.05))
    stop = threading.Event()
    with caplog.at_level(logging.INFO, logger="workers"):
        thread = threading.Thread(target=worker.run, args=(stop,))
        thread.start()
        stop.wait(2.0)
        stop.set()
        thread.join(timeout=30)

    assert not thread.is_alive()
    loop = [r for r in caplog.records if r.name == "workers"]
    waiting = [r for r in loop if getattr(r, "action", None) == "database_unavailable"]
    assert len(waiting) == 1
    assert waiting[0].getMessage().endswith("waiting for the database")
    assert not [r for r in loop if r.exc_info]  # no traceback per poll
    assert worker.jobs_done == 0

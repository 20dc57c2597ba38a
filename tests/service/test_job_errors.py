"""A job's error as devices and operators see it (``app.services.jobs``): a device reading the job
of its own upload never gets SQL, bound parameters or a driver's message, in ``error`` or in the
log tail; an admin gets the whole error; the core's own refusals reach the device in full. On
SQLite and PostgreSQL."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from api_support import ADMIN, ONETAG, Api, running_api
from sqlalchemy.exc import IntegrityError

from app.config import Settings
from app.domain.errors import ParameterError
from app.services.jobs import public_job_error
from workers.main import Worker
from workers.pipeline import JobContext, Stage

pytestmark = pytest.mark.db

INTERNAL = "an internal error of the server stopped this build; it is logged for its operators"
SQL = "INSERT INTO map_version (map_id, job_id) VALUES (%(map_id)s, %(job_id)s)"


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url) as running:
        yield running


def worker(api: Api, stages: list[Stage]) -> Worker:
    settings = Settings(database_url="sqlite://", retry_backoff_s=0.0)
    return Worker(api.db, settings, pipelines={"build_map": tuple(stages)})


def store_fails_with_sql(_ctx: JobContext) -> None:
    raise IntegrityError(SQL, {"map_id": 4, "job_id": 7}, Exception("violates foreign key"))


def test_a_device_sees_no_sql_in_its_jobs_error_and_an_admin_sees_all(api: Api) -> None:
    device = api.device()
    job_id = api.uploaded(ONETAG, auth=device)["job_id"]
    stages = [Stage(name="store", weight=1.0, run=store_fails_with_sql)]
    assert worker(api, stages).run_once()

    as_device: dict[str, Any] = api.client.get(f"/v1/jobs/{job_id}", headers=device).json()
    as_admin: dict[str, Any] = api.client.get(f"/v1/jobs/{job_id}", headers=ADMIN).json()
    for secret_part in ("INSERT", "map_version", "job_id", "violates", "parameters"):
        assert secret_part not in as_device["error"], as_device["error"]
        assert secret_part not in as_device["log_tail"], as_device["log_tail"]
    assert as_device["error"] == f"store: {INTERNAL}"
    assert "INSERT INTO map_version" in as_admin["error"]
    assert as_admin["error"].startswith("store: IntegrityError: ")
    assert "transient error in store: IntegrityError" in as_admin["log_tail"]


def test_the_cores_refusal_reaches_the_device_in_full(api: Api) -> None:
    device = api.device()
    job_id = api.uploaded(ONETAG, auth=device)["job_id"]

    def refuse(_ctx: JobContext) -> None:
        raise ParameterError("huber_k must be > 0, got -1")

    assert worker(api, [Stage(name="load", weight=1.0, run=refuse)]).run_once()
    as_device = api.client.get(f"/v1/jobs/{job_id}", headers=device).json()
    assert as_device["state"] == "failed"
    assert as_device["error"] == "load: huber_k must be > 0, got -1"
    assert "huber_k must be > 0" in as_device["log_tail"]


@pytest.mark.parametrize(
    ("stored", "public"),
    [
        (None, None),
        ("lease expired on the last attempt", "lease expired on the last attempt"),
        ("load: SessionFormatError: pose_data[3]: NaN", "load: pose_data[3]: NaN"),
        ("load: PermanentJobError: the upload is corrupt", "load: the upload is corrupt"),
        ("optimize: RuntimeError: boom\n[SQL: SELECT 1]", f"optimize: {INTERNAL}"),
    ],
)  # fmt: skip
def test_public_job_error(stored: str | None, public: str | None) -> None:
    assert public_job_error(stored) == public

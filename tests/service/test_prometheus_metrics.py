"""``/metrics`` (``app.observability.metrics``) on SQLite and PostgreSQL: an upload followed from
queued through running to done in the queue's series, its job's duration and stages, request
latency by route template, refused uploads by reason, a failed build, and the admin key it needs.
"""

from __future__ import annotations

import gzip
import os
import socket
from collections.abc import Sequence

import pytest
from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy import delete, func, select

from app.config import Settings
from app.storage import queue
from app.storage.db import Database
from app.storage.job_metrics import record_stages, stage_durations
from app.storage.orm import Job, JobStageRun, Role
from tests.service.api_support import ADMIN, JSON, ONETAG, Api, bearer, running_api
from tests.service.helpers import insert_session
from workers.main import Worker
from workers.pipeline import BUILD_MAP_STAGES, JobContext, PermanentJobError, Stage

Samples = dict[tuple[str, frozenset[tuple[str, str]]], float]

QUEUED = ("invisible_map_queue_jobs", {"kind": "build_map", "state": "queued"})
RUNNING = ("invisible_map_queue_jobs", {"kind": "build_map", "state": "running"})


def scrape(api: Api) -> Samples:
    """Every sample of ``/metrics``, by (name, labels)."""
    response = api.client.get("/metrics", headers=ADMIN)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("text/plain")
    return {
        (sample.name, frozenset(sample.labels.items())): sample.value
        for family in text_string_to_metric_families(response.text)
        for sample in family.samples
    }


def value(samples: Samples, name: str, labels: dict[str, str] | None = None) -> float | None:
    return samples.get((name, frozenset((labels or {}).items())))


def worker_for(api: Api, stages: Sequence[Stage]) -> Worker:
    settings = Settings(
        database_url=api.settings.database_url,
        lease_s=30.0,
        heartbeat_s=5.0,
        poll_s=0.05,
        retry_backoff_s=0.0,
    )
    worker = Worker(api.db, settings, pipelines={"build_map": tuple(stages)})
    queue.register_worker(
        api.db, worker_id=worker.worker_id, hostname=socket.gethostname(), pid=os.getpid()
    )
    return worker


def test_an_upload_is_followed_from_queued_to_done(database_url: str) -> None:
    with running_api(database_url) as api:
        before = scrape(api)
        assert value(before, "invisible_map_database_up") == 1
        assert value(before, *QUEUED) == 0
        assert value(before, *RUNNING) == 0
        done = {"kind": "build_map", "state": "succeeded"}
        assert value(before, "invisible_map_jobs_finished_total", done) == 0
        assert value(before, "invisible_map_job_duration_seconds_count", done) is None
        assert value(before, "invisible_map_builds_failed_total") == 0

        accepted = api.uploaded(ONETAG)
        queued = scrape(api)
        assert value(queued, *QUEUED) == 1
        assert value(queued, *RUNNING) == 0
        age_s = value(queued, "invisible_map_queue_oldest_job_age_seconds", {"kind": "build_map"})
        assert age_s is not None
        assert 0 <= age_s < 60

        seen_running: list[Samples] = []

        def scrape_while_running(_ctx: JobContext) -> None:
            seen_running.append(scrape(api))

        stages = [*BUILD_MAP_STAGES[:-1], Stage(name="look", weight=0.0, run=scrape_while_running)]
        worker = worker_for(api, [*stages, BUILD_MAP_STAGES[-1]])
        assert worker.run_once() is True

        (running,) = seen_running
        assert value(running, *QUEUED) == 0
        assert value(running, *RUNNING) == 1
        assert value(running, "invisible_map_workers_alive", {"state": "busy"}) == 1
        assert value(running, "invisible_map_jobs_finished_total", done) == 0

        after = scrape(api)
        assert value(after, *QUEUED) == 0
        assert value(after, *RUNNING) == 0
        assert (
            value(after, "invisible_map_queue_oldest_job_age_seconds", {"kind": "build_map"}) == 0
        )
        assert value(after, "invisible_map_workers_alive", {"state": "idle"}) == 1
        assert value(after, "invisible_map_jobs_finished_total", done) == 1
        assert value(after, "invisible_map_job_duration_seconds_count", done) == 1
        took_s = value(after, "invisible_map_job_duration_seconds_sum", done)
        assert took_s is not None
        assert 0 < took_s < 600
        assert (
            value(after, "invisible_map_job_duration_seconds_bucket", {**done, "le": "+Inf"}) == 1
        )
        assert value(after, "invisible_map_builds_failed_total") == 0
        for stage in [*stages, BUILD_MAP_STAGES[-1]]:
            labels = {"kind": "build_map", "stage": stage.name}
            assert value(after, "invisible_map_job_stage_duration_seconds_count", labels) == 1, (
                stage.name
            )
        stage_sum_s = sum(
            v
            for (name, _), v in after.items()
            if name == "invisible_map_job_stage_duration_seconds_sum"
        )
        assert 0 < stage_sum_s <= took_s + 0.01  # the stages are within the job

        map_id = accepted["map_id"]
        assert api.client.get(f"/v1/maps/{map_id}", headers=ADMIN).status_code == 200
        assert api.client.get("/v1/maps/999999", headers=ADMIN).status_code == 404
        assert api.client.get("/no/such/path", headers=ADMIN).status_code == 404
        latency = scrape(api)
    count = "invisible_map_http_request_duration_seconds_count"
    upload = {"method": "POST", "route": "/v1/sessions", "status_class": "2xx"}
    assert value(latency, count, upload) == 1
    one_map = {"method": "GET", "route": "/v1/maps/{map_id}"}
    assert value(latency, count, {**one_map, "status_class": "2xx"}) == 1
    assert value(latency, count, {**one_map, "status_class": "4xx"}) == 1
    assert (
        value(latency, count, {"method": "GET", "route": "unmatched", "status_class": "4xx"}) == 1
    )
    scrapes = {"method": "GET", "route": "/metrics", "status_class": "2xx"}
    assert value(latency, count, scrapes) == 4  # before, queued, running, after
    routes = {dict(labels)["route"] for (name, labels) in latency if name == count}
    # templates, never the ids asked for
    assert routes == {"/metrics", "/v1/sessions", "/v1/maps/{map_id}", "unmatched"}


def test_refused_uploads_count_under_their_reason(database_url: str) -> None:
    with running_api(database_url) as api:
        raw = ONETAG.read_bytes()
        bad_gzip = {**JSON, "Content-Encoding": "gzip"}
        assert api.upload(raw, headers=bad_gzip).status_code == 400  # not gzip at all
        assert api.upload(raw, headers={"Content-Type": "text/plain"}).status_code == 415
        assert api.upload(raw, auth={}).status_code == 401
        assert api.upload(raw, auth={}).status_code == 401
        assert api.upload(gzip.compress(raw), headers=bad_gzip).status_code == 202
        samples = scrape(api)
    refusals = "invisible_map_upload_refusals_total"
    assert value(samples, refusals, {"upload": "session", "reason": "invalid_gzip"}) == 1
    assert value(samples, refusals, {"upload": "session", "reason": "unsupported_media_type"}) == 1
    assert value(samples, refusals, {"upload": "session", "reason": "unauthorized"}) == 2
    assert sum(v for (name, _), v in samples.items() if name == refusals) == 4  # not the 202
    count = "invisible_map_http_request_duration_seconds_count"
    upload = {"method": "POST", "route": "/v1/sessions"}
    assert value(samples, count, {**upload, "status_class": "4xx"}) == 4
    assert value(samples, count, {**upload, "status_class": "2xx"}) == 1


def test_a_failed_build_counts_as_failed(database_url: str) -> None:
    def refuse(_ctx: JobContext) -> None:
        raise PermanentJobError("this walk cannot be built")

    with running_api(database_url) as api:
        api.uploaded(ONETAG)
        worker = worker_for(api, [Stage(name="refuse", weight=1.0, run=refuse)])
        assert worker.run_once() is True
        samples = scrape(api)
    failed = {"kind": "build_map", "state": "failed"}
    assert value(samples, "invisible_map_builds_failed_total") == 1
    assert value(samples, "invisible_map_jobs_finished_total", failed) == 1
    assert value(samples, "invisible_map_job_duration_seconds_count", failed) == 1
    assert value(samples, *QUEUED) == 0
    # a stage that did not run to its end has no duration
    refused = {"kind": "build_map", "stage": "refuse"}
    assert value(samples, "invisible_map_job_stage_duration_seconds_count", refused) is None


@pytest.mark.parametrize(
    ("key", "status"),
    [(None, 401), ("wrong", 401), ("device", 403)],
)
def test_metrics_needs_an_admin_key(database_url: str, key: str | None, status: int) -> None:
    with running_api(database_url) as api:
        headers = {}
        if key == "device":
            headers = bearer(api.create_key(Role.DEVICE)[1])
        elif key is not None:
            headers = bearer("im_deadbeef_" + key * 8)
        response = api.client.get("/metrics", headers=headers)
        assert response.status_code == status, response.text
        assert "invisible_map" not in response.text
        assert response.json()["code"] in ("unauthorized", "forbidden")


def test_stage_durations_go_with_their_job(db: Database) -> None:
    inserted = insert_session(db, ONETAG)
    stages = [("load", 0.5), ("optimize", 2.5)]
    written = record_stages(
        db, job_id=inserted.job_id, kind="build_map", attempt=1, durations_s=stages
    )
    assert written == 2
    assert record_stages(db, job_id=10**6, kind="build_map", attempt=1, durations_s=stages) == 0
    with db.read() as tx:
        durations = stage_durations(tx, (1.0, 2.0))
    load = durations[("build_map", "load")]
    assert (load.below, load.count, load.sum_s) == ((1, 1), 1, 0.5)
    optimize = durations[("build_map", "optimize")]
    assert (optimize.below, optimize.count, optimize.sum_s) == ((0, 0), 1, 2.5)
    with db.transaction() as tx:
        tx.execute(delete(Job).where(Job.id == inserted.job_id))
    with db.read() as tx:
        assert tx.scalar(select(func.count()).select_from(JobStageRun)) == 0
        assert stage_durations(tx, (1.0,)) == {}

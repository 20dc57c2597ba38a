"""What an operator sees of a running ``invisible-map serve --log-format json``: a log of JSON
lines, the job's lines carrying its ids, and ``/metrics`` summed over its API processes
(prometheus-client's multiprocess mode)."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families

from app.cli.server_process import ServerProcess
from app.client import Client

pytestmark = [pytest.mark.slow]

REQUESTS = "invisible_map_http_request_duration_seconds_count"


def request_count(text: str, method: str, route: str, status_class: str) -> float:
    """The count of requests with these labels in a scrape (0 when none)."""
    wanted = {"method": method, "route": route, "status_class": status_class}
    return sum(
        sample.value
        for family in text_string_to_metric_families(text)
        for sample in family.samples
        if sample.name == REQUESTS and sample.labels == wanted
    )


def upload_and_scrape(server: ServerProcess, data_dir: Path) -> dict[str, int]:
    """Upload a session, wait for its map, and scrape ``/metrics`` a dozen times; the ids of
    what the upload made."""
    admin = {"Authorization": f"Bearer {server.admin_key}"}
    assert httpx.get(server.url + "/metrics").status_code == 401
    with Client(server.url, api_key=server.admin_key) as client:
        accepted: dict[str, int] = client.upload_session(
            data_dir / "sessions" / "onetag.json", compress=True
        )
        job = client.wait_for_job(accepted["job_id"], timeout_s=180)
    assert job["state"] == "succeeded"
    # Each scrape, whichever API process answers it (a new connection each), counts the upload
    # once and every scrape before it: the processes' counts are summed.
    answered_by = set()
    for scrapes_before in range(12):
        response = httpx.get(server.url + "/metrics", headers=admin, timeout=30)
        assert response.status_code == 200, response.text
        answered_by.add(response.headers["x-api-process"])
        assert request_count(response.text, "POST", "/v1/sessions", "2xx") == 1
        assert request_count(response.text, "GET", "/metrics", "4xx") == 1
        # (the scrape just before is counted once its answer is sent: it may not be yet)
        counted = request_count(response.text, "GET", "/metrics", "2xx")
        assert scrapes_before - 1 <= counted <= scrapes_before
    assert answered_by <= {"1", "2"}
    return accepted


def test_serve_logs_json_lines_and_sums_metrics_over_its_api_processes(
    tmp_path: Path, data_dir: Path
) -> None:
    log_path = tmp_path / "serve.log"
    server = ServerProcess(
        f"sqlite:///{tmp_path / 'observed.sqlite3'}",
        workers=1,
        api_processes=2,
        log_path=log_path,
    )
    server.args += ["--log-format", "json"]
    server.start()
    try:
        server.wait_ready(timeout_s=240)  # three processes starting on a busy machine
        accepted = upload_and_scrape(server, data_dir)
    finally:
        server.stop()

    lines = [line for line in log_path.read_text().splitlines() if line.strip()]
    assert len(lines) > 10
    records = []
    for number, line in enumerate(lines, 1):
        try:
            record = json.loads(line)
        except ValueError:
            pytest.fail(f"line {number} of the log is no JSON: {line!r}")
        assert isinstance(record, dict), line
        assert {"time", "level", "logger", "message"} <= set(record), line
        records.append(record)

    (succeeded,) = [r for r in records if r.get("action") == "job_succeeded"]
    assert succeeded["job_id"] == accepted["job_id"]
    assert succeeded["map_id"] == accepted["map_id"]
    assert succeeded["session_id"] == accepted["session_id"]
    assert succeeded["logger"] == "workers"
    assert f"job {accepted['job_id']} succeeded" in succeeded["message"]
    started = [r for r in records if r.get("action") == "job_started"]
    assert [r["job_id"] for r in started] == [accepted["job_id"]]
    # uvicorn's own lines are JSON too: its access lines with the request's fields
    uploads = [
        r for r in records if r["logger"] == "uvicorn.access" and r.get("path") == "/v1/sessions"
    ]
    assert [(r["method"], r["status"]) for r in uploads] == [("POST", 202)]
    assert any(r["message"].startswith("Invisible Map server at") for r in records)
    assert not any(r["logger"].startswith("alembic") for r in records)  # as in the text log

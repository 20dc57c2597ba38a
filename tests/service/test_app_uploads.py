"""Every upload the real app can make becomes a map or a clear, stored refusal (issue 14):
empty and repeated point-of-interest names, an empty map_id, plane and cloud-anchor data, the
earlier format, and a walk with no tag. The raw upload is kept byte for byte. SQLite and
PostgreSQL."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from api_support import ADMIN, Api, onetag, running_api

from app.config import Settings
from app.storage.orm import Job, JobState, MapRow, MapVersion, SessionRow, SessionUpload
from tests.service.helpers import get_job
from workers.main import Worker
from workers.pipeline import BUILD_MAP_STAGES

pytestmark = pytest.mark.db

ARCHIVE = Path(__file__).resolve().parents[2] / "data" / "archive"
IDENTITY = [1.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url) as running:
        yield running


def location(name: str, pose_id: int) -> dict[str, Any]:
    return {"name": name, "pose_id": pose_id, "timestamp": 0.0, "transform": IDENTITY}


def run_worker_once(api: Api) -> None:
    settings = Settings(
        database_url=api.settings.database_url, lease_s=30.0, poll_s=0.05, retry_backoff_s=0.0
    )
    assert Worker(api.db, settings, pipelines={"build_map": BUILD_MAP_STAGES}).run_once()


def raw_of(api: Api, session_id: int) -> bytes:
    response = api.client.get(f"/v1/sessions/{session_id}/raw", headers=ADMIN)
    assert response.status_code == 200, response.text
    return response.content


APP_UPLOADS = [
    pytest.param(
        onetag(location_data=[location("", 3), location("  ", 5), location("Desk", 7)]),
        ["location_data[0].name was empty: named 'Point 1'", "named 'Point 2'"],
        id="empty-poi-names",
    ),
    pytest.param(
        onetag(location_data=[location("Desk", 3), location("Desk", 5)]),
        ["2 points of interest are named 'Desk'"],
        id="repeated-poi-names",
    ),
    pytest.param(onetag(map_id=""), ["map_id was empty: named 'unnamed-"], id="empty-map-id"),
    pytest.param(
        onetag(
            plane_data=[{"id": 1, "transform": IDENTITY, "alignment": "horizontal"}],
            cloud_data=[{"cloudIdentifier": "ua-3f9", "anchorTransform": IDENTITY}],
        ),
        [],
        id="plane-and-cloud-anchor-data",
    ),
]


@pytest.mark.parametrize(("document", "warnings"), APP_UPLOADS)
def test_what_the_app_sends_is_taken_reported_and_kept_byte_for_byte(
    api: Api, document: dict[str, Any], warnings: list[str]
) -> None:
    sent = json.dumps(document, indent=1).encode()
    body = api.uploaded(sent, auth=api.device())

    reported = body["statistics"]["warnings"]
    for expected in warnings:
        assert any(expected in w for w in reported), reported
    assert body["map_name"]
    assert raw_of(api, body["session_id"]) == sent

    run_worker_once(api)
    assert get_job(api.db, body["job_id"]).state == JobState.SUCCEEDED
    app_map = api.client.get(f"/v1/maps/{body['map_id']}/app-map", headers=ADMIN).json()
    names = [w["id"] for w in app_map["waypoints_vertices"]]
    assert all(names), names
    if any("Point 1" in w for w in warnings):
        assert {"Point 1", "Point 2", "Desk"} <= set(names)


def test_an_empty_map_id_names_the_map_from_the_upload_stably(api: Api) -> None:
    sent = json.dumps(onetag(map_id="")).encode()
    first = api.uploaded(sent)
    again = api.uploaded(sent)
    assert first["map_name"].startswith("unnamed-")
    assert again["map_name"] == first["map_name"]
    other = api.uploaded(json.dumps({**onetag(map_id=""), "pose_data": onetag()["pose_data"][1:]}))
    assert other["map_name"] != first["map_name"]


def test_a_walk_with_no_tag_is_stored_and_its_job_fails_saying_why(api: Api) -> None:
    sent = json.dumps(onetag(tag_data=[])).encode()
    body = api.uploaded(sent, auth=api.device())

    assert "no tags were recorded: a map needs at least one tag" in body["statistics"]["warnings"]
    assert [api.count(t) for t in (SessionRow, SessionUpload, MapRow, Job)] == [1, 1, 1, 1]
    assert raw_of(api, body["session_id"]) == sent

    run_worker_once(api)

    job = api.client.get(f"/v1/jobs/{body['job_id']}", headers=ADMIN).json()
    assert job["state"] == "failed"
    assert job["attempts"] == 1  # permanent: never retried
    assert "no tags were recorded: a map needs at least one tag" in job["error"]
    assert api.count(MapVersion) == 0
    response = api.client.get(f"/v1/maps/{body['map_id']}/app-map", headers=ADMIN)
    assert response.status_code == 409
    assert response.json()["code"] == "map_not_ready"
    assert "failed" in response.json()["detail"]


def test_an_earlier_format_session_becomes_a_map(api: Api) -> None:
    sent = (ARCHIVE / "round2.json").read_bytes()
    body = api.uploaded(sent, compress=True)
    assert body["statistics"]["pose_count"] == 1361
    assert body["statistics"]["tag_count"] == 6
    assert any("earlier format" in w for w in body["statistics"]["warnings"])
    assert raw_of(api, body["session_id"]) == sent
    run_worker_once(api)
    assert get_job(api.db, body["job_id"]).state == JobState.SUCCEEDED


def test_an_earlier_format_session_whose_frames_do_not_hold_is_refused(api: Api) -> None:
    document = json.loads((ARCHIVE / "round2.json").read_bytes())
    for row in document["tag_data"]:
        row[12] = -abs(row[12])  # every tag behind the camera
    response = api.upload(json.dumps(document).encode())
    assert response.status_code == 422, response.text
    error = response.json()
    assert error["field"] == "tag_data"
    assert "earlier format" in error["detail"]
    assert api.count(SessionRow) == 0

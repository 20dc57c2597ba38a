"""Names that once made a map never build, through the whole pipeline (issue 19, finding 6):
matplotlib mathtext, markup, quotes, format strings, right-to-left marks and emoji, as a map's
name and as points of interest, are uploaded, built by the worker's real stages in one attempt
and served literally (the app's map, GeoJSON, the plot, the dashboard). Names no storage can
hold are refused at the door (``test_door_checks.py``). On SQLite and PostgreSQL."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from admin_support import logged_in
from api_support import ADMIN, ONETAG, Api, running_api

from app.config import Settings
from app.storage.orm import JobState
from tests.service.helpers import get_job
from workers.main import Worker

pytestmark = [pytest.mark.db, pytest.mark.slow]

POIS = ONETAG.parents[1] / "demo" / "floor_2_pois.json"
HOSTILE_NAMES = [
    "Budget_$_2024_$",
    "Lab $x^$ room",
    r"$\frac{1}{0}$ \left(",
    '<a href="https://example.com">exit</a>',
    "Room '1'; DROP TABLE map; --",
    "%s %d {0} {name}",
    "\u202eroom 12\u202c",
    "Café 🚪 門口",
    "back\\slash\ttab",
]


@pytest.fixture
def api(database_url: str, tmp_path: Path) -> Iterator[Api]:
    with running_api(database_url, data_dir=tmp_path) as running:
        yield running


def hostile_session(map_name: str) -> bytes:
    document: dict[str, Any] = json.loads(POIS.read_bytes())
    document["map_id"] = map_name
    template = document["location_data"][0]
    document["location_data"] = [{**template, "name": name} for name in HOSTILE_NAMES]
    return json.dumps(document).encode()


def test_hostile_names_build_in_one_attempt_and_are_served_literally(api: Api) -> None:
    url = api.db.url.render_as_string(hide_password=False)
    worker = Worker(api.db, Settings(database_url=url, retry_backoff_s=0.0))
    accepted = [api.uploaded(hostile_session(name)) for name in HOSTILE_NAMES[:2]]
    for _ in accepted:
        assert worker.run_once()
    logged_in(api.client)
    for name, upload in zip(HOSTILE_NAMES[:2], accepted, strict=True):
        job = get_job(api.db, upload["job_id"])
        assert (job.state, job.attempts) == (JobState.SUCCEEDED, 1), job.error
        map_id = upload["map_id"]
        plot = api.client.get(f"/v1/maps/{map_id}/plot.png", headers=ADMIN)
        assert plot.status_code == 200
        assert plot.content.startswith(b"\x89PNG")
        app_map = api.client.get(f"/v1/maps/{map_id}/app-map", headers=ADMIN)
        assert app_map.status_code == 200, app_map.text
        geojson = api.client.get(f"/v1/maps/{map_id}/geojson", headers=ADMIN)
        assert geojson.status_code == 200, geojson.text
        pois = api.client.get(f"/v1/maps/{map_id}/pois", headers=ADMIN)
        assert pois.status_code == 200, pois.text
        served = json.dumps([app_map.json(), geojson.json(), pois.json()])
        for hostile in HOSTILE_NAMES:
            assert json.dumps(hostile)[1:-1] in served, hostile
        page = api.client.get(f"/admin/maps/{map_id}")
        assert page.status_code == 200
        assert "&lt;a href=" in page.text  # escaped by the template, drawn literally
        assert api.client.get(f"/v1/maps/{map_id}", headers=ADMIN).json()["name"] == name

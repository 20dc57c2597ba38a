"""The dashboard's pages of a long walk (20,000 poses) ship a bounded, downsampled figure and say
so; its session page and raw trajectory are parsed from the database a piece at a time.
SQLite and PostgreSQL."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from typing import Any

import pytest
from admin_support import logged_in
from api_support import Api, run_next_job, running_api

from app.domain.formats.map_figure import MAX_TRAJECTORY_POINTS, trajectory_rows
from app.storage import sessions
from tests.service.helpers import simulated_bytes

pytestmark = pytest.mark.db

POSES = 20_000
_FIGURE = re.compile(r'<script type="application/json" id="map-figure">(.*?)</script>', re.S)


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url) as running:
        yield running


def built(api: Api, poses: int, monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """A simulated walk uploaded and built (with its path graph); from then on, reading a
    stored upload whole fails the test."""
    created = api.uploaded(simulated_bytes(poses), compress=True)
    assert run_next_job(api.db, path_graph=True) is not None

    def whole_file(*_: object) -> bytes:
        raise AssertionError("the whole stored upload was read")

    monkeypatch.setattr(sessions, "raw_upload", whole_file)
    logged_in(api.client)
    return created


def points(line: dict[str, Any] | None) -> int:
    return 0 if line is None else sum(x is not None for x in line["x"])


def test_a_long_walks_map_page_draws_a_bounded_downsampled_figure(
    api: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    created = built(api, POSES, monkeypatch)

    page = api.client.get(f"/admin/maps/{created['map_id']}")
    assert page.status_code == 200, page.text
    match = _FIGURE.search(page.text)
    assert match is not None
    figure = json.loads(match.group(1))
    assert figure["downsampled"] == {"poses": POSES, "shown": len(trajectory_rows(POSES))}
    for floor in figure["floors"]:
        assert 0 < points(floor["optimized"]) <= MAX_TRAJECTORY_POINTS
        assert 0 < points(floor["raw"]) <= MAX_TRAJECTORY_POINTS
    assert "The trajectories are downsampled" in page.text
    assert len(page.content) < 1_500_000  # drawn whole, the two trajectories alone are ~2 MB

    session_page = api.client.get(f"/admin/sessions/{created['session_id']}")
    assert session_page.status_code == 200
    assert f"{POSES:,}" in session_page.text or str(POSES) in session_page.text


def test_a_short_walk_is_drawn_whole(api: Api, monkeypatch: pytest.MonkeyPatch) -> None:
    created = built(api, 1_000, monkeypatch)
    page = api.client.get(f"/admin/maps/{created['map_id']}")
    match = _FIGURE.search(page.text)
    assert match is not None
    figure = json.loads(match.group(1))
    assert figure["downsampled"] is None
    assert sum(points(floor["optimized"]) for floor in figure["floors"]) == 1_000
    assert "The trajectories are downsampled" not in page.text


def test_the_rows_drawn_keep_each_sessions_ends() -> None:
    starts = [7_001, 12_345]
    rows = trajectory_rows(POSES, keep=[*starts, *(s - 1 for s in starts)])
    assert {0, POSES - 1, 7_000, 7_001, 12_344, 12_345} <= set(rows)
    assert len(rows) <= MAX_TRAJECTORY_POINTS + 4
    assert trajectory_rows(MAX_TRAJECTORY_POINTS) == list(range(MAX_TRAJECTORY_POINTS))

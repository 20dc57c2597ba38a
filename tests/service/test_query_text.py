"""NUL and lone surrogates in path ids and query strings (issue 19, finding 7), on SQLite and
PostgreSQL: each is a 422 naming the parameter, never a 500 (a NUL in the dashboard's session
search reached PostgreSQL's ILIKE and failed there)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from admin_support import logged_in
from api_support import ADMIN, ONETAG, Api, run_next_job, running_api

from tests.conftest import PreparedDatabases

pytestmark = pytest.mark.db


def _onetag_built(url: str) -> None:
    with running_api(url) as running:
        running.uploaded(ONETAG)
        run_next_job(running.db, path_graph=True)


@pytest.fixture
def api(database_url: str, prepared_databases: PreparedDatabases) -> Iterator[Api]:
    """onetag uploaded and built with its path graph (once per test process and database kind;
    each test on its own copy)."""
    prepared_databases.copy_into(database_url, "onetag_built", _onetag_built)
    with running_api(database_url) as running:
        yield running


NUL, SURROGATE = "%00", "%ED%A0%80"  # a lone surrogate (U+D800) as UTF-8 would spell it


@pytest.mark.parametrize("bad", [NUL, SURROGATE, f"1{NUL}"])
@pytest.mark.parametrize(
    ("path", "field"),
    [
        ("/v1/maps/{}", "map_id"),
        ("/v1/maps/{}/app-map", "map_id"),
        ("/v1/maps/1/versions/{}", "number"),
        ("/v1/jobs/{}", "job_id"),
        ("/v1/sessions/{}", "session_id"),
        ("/v1/sweeps/{}", "sweep_id"),
        ("/v1/localizations/{}", "localization_id"),
        ("/v1/maps?tag_id={}", "tag_id"),
        ("/v1/maps/1/app-map?version={}", "version"),
        ("/v1/jobs?state={}", "state"),
        ("/v1/sweeps?map_id={}", "map_id"),
    ],
)
def test_a_nul_or_a_lone_surrogate_in_an_id_is_422_naming_it(
    api: Api, path: str, field: str, bad: str
) -> None:
    answer = api.client.get(path.format(bad), headers=ADMIN)
    assert answer.status_code == 422, answer.text
    assert answer.json()["field"] == field


@pytest.mark.parametrize(
    ("path", "field"),
    [
        ("/v1/maps/1/pois?q=a%00b", "q"),
        ("/v1/maps/1/image?v=%00", "v"),
        ("/v1/maps?%00=1", "\x00"),
    ],
)
def test_a_nul_in_a_text_query_parameter_is_422_naming_it(api: Api, path: str, field: str) -> None:
    answer = api.client.get(path, headers=ADMIN)
    assert answer.status_code == 422, answer.text
    body = answer.json()
    assert (body["code"], body["field"]) == ("validation_error", field)
    assert "NUL" in body["detail"]


def test_the_dashboards_search_refuses_a_nul_and_reads_a_bad_byte_as_text(api: Api) -> None:
    logged_in(api.client)
    refused = api.client.get("/admin/sessions?q=a%00b")
    assert refused.status_code == 422, refused.text[:300]
    assert "NUL" in refused.text
    # invalid UTF-8 (a lone surrogate's bytes) is decoded as U+FFFD: a search that finds nothing
    searched = api.client.get(f"/admin/sessions?q={SURROGATE}")
    assert searched.status_code == 200, searched.text[:300]
    assert api.client.get("/admin/sessions?q=onetag").status_code == 200

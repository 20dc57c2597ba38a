"""The dashboard keeps the API's id rule (issue 40's leftovers), on SQLite and PostgreSQL.

1. Every dashboard route with an integer path or query parameter (map, session, job, key, sweep
   and edit ids, version numbers, page numbers): a number beyond 2^31 - 1 is answered as one that
   names nothing (the page of a missing one), or as a malformed parameter (422), never with a 5xx
   (PostgreSQL's columns are 32-bit; a version of 2^31 was a 500 there). :func:`int_cases` walks
   the dashboard's router, so a new route is covered without a line here.
2. The corridor editor's JSON errors show a huge number compactly, as the API's do.
3. A rebuild's SLAM parameters (``POST /v1/maps/{id}/rebuild``, the dashboard's rebuild form) lie
   in their ranges (``params.PARAM_RANGES``): ``{"huber_k": 1e308}`` was queued with a 202.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from fastapi.routing import APIRoute

from app.admin.router import router as admin_router
from app.web.errors import MAX_DIGITS_SHOWN, MAX_ERROR_TEXT
from tests.conftest import fresh_database_url
from tests.service.admin_support import csrf_token, logged_in
from tests.service.api_support import ADMIN, JSON, ONETAG, Api, run_next_job, running_api

pytestmark = pytest.mark.db

#: The largest id (the columns are 32-bit INTEGER).
MAX_ID = 2**31 - 1
#: The first number that overflows, the largest 64-bit one, and one beyond any integer type.
OUT_OF_RANGE = [2**31, 2**63 - 1, 10**30]


@dataclass(frozen=True)
class IntCase:
    """One integer parameter (``where``: path or query) of one dashboard route."""

    method: str
    path: str
    where: str
    name: str

    def __str__(self) -> str:
        return f"{self.method} {self.path} {self.where}:{self.name}"


def _is_int(annotation: Any) -> bool:
    return annotation is int or int in getattr(annotation, "__args__", ())


def _parameters(dependant: Any) -> list[tuple[str, Any]]:
    """(where, parameter) of a route's path and query parameters, its dependencies' too."""
    found = [("path", p) for p in dependant.path_params]
    found += [("query", p) for p in dependant.query_params]
    for sub in dependant.dependencies:
        found += _parameters(sub)
    return found


def int_cases() -> list[IntCase]:
    """Every integer path or query parameter of every dashboard route."""
    routes: list[tuple[str, APIRoute]] = []

    def walk(router: Any, prefix: str) -> None:
        for route in router.routes:
            if hasattr(route, "original_router"):  # an included router (FastAPI ≥ 0.16x)
                walk(route.original_router, prefix + (route.include_context.prefix or ""))
            elif isinstance(route, APIRoute):
                routes.append((prefix + route.path, route))

    walk(admin_router, "")
    cases = []
    for path, route in routes:
        for where, parameter in _parameters(route.dependant):
            if _is_int(parameter.field_info.annotation):
                alias = parameter.alias or parameter.name
                cases.extend(IntCase(method, path, where, alias) for method in route.methods)
    return sorted(set(cases), key=str)


INT_CASES = int_cases()


@dataclass
class Dashboard:
    """A logged-in dashboard with one built map (its path graph too) and its rows' ids."""

    api: Api
    ids: dict[str, int]


@pytest.fixture(
    scope="module",
    params=[pytest.param(b, marks=pytest.mark.db) for b in ("sqlite", "postgresql")],
)
def dashboard(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Dashboard]:
    urls = fresh_database_url(request.param, request, tmp_path_factory.mktemp("dashboard"))
    url = next(urls)
    try:
        with running_api(url) as api:
            created = api.uploaded(ONETAG)
            assert run_next_job(api.db, path_graph=True) == created["job_id"]
            logged_in(api.client)
            yield Dashboard(
                api=api,
                ids={
                    "map_id": created["map_id"],
                    "session_id": created["session_id"],
                    "job_id": created["job_id"],
                },
            )
    finally:
        for _ in urls:
            pass


def _request(dashboard: Dashboard, case: IntCase, value: int, token: str) -> Any:
    """``case``'s route with ``value`` as its parameter and real rows as its other ids (an id
    that names nothing for kinds the database has none of); a form's CSRF token with it."""
    ids = {**dashboard.ids, case.name: value} if case.where == "path" else dict(dashboard.ids)
    path = re.sub(r"\{([a-z_]+)\}", lambda m: str(ids.get(m.group(1), MAX_ID)), case.path)
    params = {case.name: value} if case.where == "query" else {}
    headers = {"X-CSRF-Token": token}
    data = {"csrf_token": token} if case.method == "POST" else None
    return dashboard.api.client.request(
        case.method, path, params=params, data=data, headers=headers, follow_redirects=False
    )


@pytest.mark.parametrize("value", OUT_OF_RANGE, ids=["2^31", "2^63-1", "10^30"])
@pytest.mark.parametrize("case", INT_CASES, ids=str)
def test_a_number_out_of_range_is_answered_as_one_that_names_nothing(
    dashboard: Dashboard, case: IntCase, value: int
) -> None:
    token = csrf_token(dashboard.api.client)
    out_of_range = _request(dashboard, case, value, token)
    assert out_of_range.status_code < 500, out_of_range.text
    missing = _request(dashboard, case, MAX_ID, token)
    assert out_of_range.status_code in {missing.status_code, 404, 422}, out_of_range.text
    if case.where == "path" and case.method == "GET":
        assert out_of_range.status_code == 404, out_of_range.text


def test_the_walk_finds_the_dashboards_numbers() -> None:
    found = {(case.where, case.name) for case in INT_CASES}
    assert {
        ("path", "map_id"),
        ("path", "session_id"),
        ("path", "job_id"),
        ("path", "key_id"),
        ("path", "sweep_id"),
        ("path", "edit_id"),
        ("query", "version"),
        ("query", "page"),
        ("query", "map_id"),
        ("query", "current"),
    } <= found
    assert len({(case.method, case.path) for case in INT_CASES}) >= 25


@pytest.mark.parametrize("map_id", ["2147483648", "999999999999999999", "1" + "0" * 30])
def test_the_sweep_form_refuses_a_map_beyond_the_ids(dashboard: Dashboard, map_id: str) -> None:
    token = csrf_token(dashboard.api.client, "/admin/sweeps")
    response = dashboard.api.client.post(
        "/admin/sweeps",
        data={
            "csrf_token": token,
            "map_id": map_id,
            "method": "grid",
            "objective": "shift",
            "sweep": "odom_linear_var_m2_per_s",
            "odom_linear_var_m2_per_s_low": "1e-6",
            "odom_linear_var_m2_per_s_high": "1e-2",
            "odom_linear_var_m2_per_s_num": "2",
        },
        follow_redirects=False,
    )
    assert response.status_code in {404, 422}, response.text  # the form again, saying why
    assert "not found" in response.text or "choose the map" in response.text


@pytest.mark.parametrize("form_field", ["session_id", "map_id"])
def test_the_map_forms_refuse_an_id_beyond_the_ids(dashboard: Dashboard, form_field: str) -> None:
    map_id = dashboard.ids["map_id"]
    action = "sessions/add" if form_field == "session_id" else "merge"
    token = csrf_token(dashboard.api.client, f"/admin/maps/{map_id}")
    for value in OUT_OF_RANGE:
        response = dashboard.api.client.post(
            f"/admin/maps/{map_id}/{action}",
            data={"csrf_token": token, form_field: str(value)},
            follow_redirects=False,
        )
        assert response.status_code == 303, response.text  # back to the map, with why


# --------------------------------------------------------------------------- numbers echoed


def test_the_editors_errors_show_a_huge_number_compactly(dashboard: Dashboard) -> None:
    client = dashboard.api.client
    map_id = dashboard.ids["map_id"]
    token = csrf_token(client, f"/admin/maps/{map_id}/editor")
    headers = {"X-CSRF-Token": token, "Content-Type": "application/json"}
    huge = "1" + "0" * 308
    bodies = [
        '{"op": "quiet", "at": [' + huge + ", 0, 0]}",
        '{"op": "quiet", "at": [1e308, 0, 0]}',
        '{"op": "remove_edge", "from": ' + huge + ', "to": 1}',
        '{"op": "' + "x" * 10_000 + '"}',
    ]
    for body in bodies:
        response = client.post(f"/admin/maps/{map_id}/editor/edits", content=body, headers=headers)
        assert 400 <= response.status_code < 500, response.text
        document = response.json()
        assert set(document) == {"detail", "code", "field"}
        detail = document["detail"]
        assert len(detail) <= MAX_ERROR_TEXT, detail
        assert not re.search(rf"\d{{{MAX_DIGITS_SHOWN + 1},}}", detail), detail
        assert not re.search(rf"\d{{{MAX_DIGITS_SHOWN + 1},}}", document["field"] or ""), document
    route = client.get(
        f"/admin/maps/{map_id}/editor/route", params={"from": "tag:" + huge[:280], "to": "tag:1"}
    )
    assert 400 <= route.status_code < 500, route.text
    assert not re.search(rf"\d{{{MAX_DIGITS_SHOWN + 1},}}", route.json()["detail"]), route.text


# --------------------------------------------------------------------------- SLAM parameters

#: (params, the field at fault, words of the range the detail must name).
BAD_PARAMS = [
    ({"huber_k": 1e308}, "params.huber_k", "0 (off) or 0.1 to 100 σ"),
    ({"huber_k": "NaN"}, "params.huber_k", "0.1 to 100"),
    ({"huber_k": math.nan}, "params.huber_k", "0.1 to 100"),
    ({"huber_k": -1}, "params.huber_k", "0.1 to 100"),
    ({"tag_position_var_m2": 0}, "params.tag_position_var_m2", "1e-12 to 1e+06 m²"),
    ({"odom_linear_var_m2_per_s": -1e-3}, "params.odom_linear_var_m2_per_s", "1e-12 to 1e+06"),
    ({"gravity_var_rad2": 1e308}, "params.gravity_var_rad2", "1e-12 to 1e+06 rad²"),
    ({"max_distance_m": 1e308}, "params.max_distance_m", "0.01 to 1000 m"),
    ({"tag_size_m": 0}, "params.tag_size_m", "0.001 to 10 m"),
    ({"tag_sizes_m": {"300": 1e308}}, "params.tag_sizes_m", "0.001 to 10 m"),
    ({"max_iterations": 10**400}, "params.max_iterations", "1 to 10000"),
]
BAD_IDS = [
    "huge-huber",
    "nan-text",
    "nan-json",
    "negative-huber",
    "zero-variance",
    "negative-variance",
    "huge-variance",
    "huge-distance",
    "zero-tag-size",
    "huge-tag-size",
    "400-digits",
]


@pytest.mark.parametrize(("params", "field", "range_text"), BAD_PARAMS, ids=BAD_IDS)
def test_a_rebuild_refuses_a_parameter_out_of_its_range(
    dashboard: Dashboard, params: dict[str, Any], field: str, range_text: str
) -> None:
    client = dashboard.api.client
    map_url = f"/v1/maps/{dashboard.ids['map_id']}"
    jobs_before = client.get(
        "/v1/jobs", params={"map_id": dashboard.ids["map_id"]}, headers=ADMIN
    ).json()
    response = client.post(
        map_url + "/rebuild",
        content=json.dumps({"params": params}, allow_nan=True).encode(),
        headers={**ADMIN, **JSON},
    )
    assert response.status_code == 422, response.text
    error = response.json()
    assert (error["code"], error["field"]) == ("invalid_parameter", field), error
    assert field.removeprefix("params.") in error["detail"]
    assert range_text in error["detail"], error
    assert len(error["detail"]) < 300, error
    assert (
        client.get("/v1/jobs", params={"map_id": dashboard.ids["map_id"]}, headers=ADMIN).json()
        == jobs_before
    )  # none queued


@pytest.mark.parametrize(("params", "field", "range_text"), BAD_PARAMS[:8], ids=BAD_IDS[:8])
def test_the_rebuild_form_refuses_a_parameter_out_of_its_range(
    dashboard: Dashboard, params: dict[str, Any], field: str, range_text: str
) -> None:
    map_id = dashboard.ids["map_id"]
    token = csrf_token(dashboard.api.client, f"/admin/maps/{map_id}")
    form = {name: repr(value) for name, value in params.items()}
    response = dashboard.api.client.post(
        f"/admin/maps/{map_id}/rebuild",
        data={"csrf_token": token, **form},
        follow_redirects=False,
    )
    assert response.status_code == 422, response.text  # the form again, saying why
    assert range_text in response.text
    assert field.removeprefix("params.") in response.text

"""Every text that reaches the database follows one rule (issue 28, finding 1), on SQLite and
PostgreSQL: a NUL or a lone surrogate in a map's display name, a JSON body anywhere (a rebuild's
or a sweep's parameter names, a sweep's ground truth), a dashboard form, is a 422 naming the
field, and nothing is stored. Before, ``PATCH /v1/maps/{id}`` stored a NUL on SQLite (200) and
was a 500 on PostgreSQL, and a lone surrogate in a parameter's name was a 500 on both."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from admin_support import csrf_token, logged_in
from api_support import ADMIN, JSON, ONETAG, Api, running_api
from sqlalchemy import select

from app.storage.orm import ApiKey, Job, MapRow, Sweep

pytestmark = pytest.mark.db

NUL, SURROGATE = "lab \x00 3", "lab \ud800 3"


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    """Map 1, of onetag (unbuilt: nothing here needs a version)."""
    with running_api(database_url) as running:
        running.uploaded(ONETAG)
        yield running


def send(api: Api, method: str, path: str, document: Any) -> Any:
    """``document`` as JSON text, a lone surrogate escaped (``\\ud800``) as a client would."""
    return api.client.request(method, path, content=json.dumps(document), headers={**ADMIN, **JSON})


def display_name(api: Api) -> str | None:
    with api.db.read() as db_session:
        return db_session.scalar(select(MapRow.display_name).where(MapRow.id == 1))


def test_a_display_name_that_is_no_text_is_422_and_not_stored(api: Api) -> None:
    before = display_name(api)
    for bad, words in ((NUL, "NUL"), (SURROGATE, "lone surrogate")):
        answer = send(api, "PATCH", "/v1/maps/1", {"display_name": bad})
        assert answer.status_code == 422, answer.text
        body = answer.json()
        assert (body["code"], body["field"]) == ("validation_error", "display_name")
        assert words in body["detail"]
        assert display_name(api) == before
    assert send(api, "PATCH", "/v1/maps/1", {"display_name": "Lab 3"}).status_code == 200


#: (path, the body with ``bad`` in it, the field named)
JSON_BODIES: list[tuple[str, Callable[[str], Any], str]] = [
    ("/v1/maps/1/rebuild", lambda bad: {"params": {bad: 1}}, "params"),
    (
        "/v1/maps/1/rebuild",
        lambda bad: {"params": {"tag_sizes_m": {"3": 0.15, bad: 0.2}}},
        "params.tag_sizes_m",
    ),
    ("/v1/maps/1/sweeps", lambda bad: {"params": {bad: 1}}, "params"),
    (
        "/v1/maps/1/sweeps",
        lambda bad: {
            "objective": "ground_truth",
            "ground_truth": {"poses": [{"tag_id": 3, "pose": [0, 0, 0, 0, 0, 0, 1]}, bad]},
        },
        "ground_truth.poses[1]",
    ),
]


def test_text_anywhere_in_a_json_body_is_checked_at_the_door(api: Api) -> None:
    for path, document, field in JSON_BODIES:
        for bad in (NUL, SURROGATE):
            answer = send(api, "POST", path, document(bad))
            assert answer.status_code == 422, (path, bad, answer.text)
            assert (answer.json()["code"], answer.json()["field"]) == ("validation_error", field)
    assert (api.count(Job), api.count(Sweep)) == (1, 0)  # only the upload's build


def test_the_dashboards_forms_refuse_a_nul_naming_the_field(api: Api) -> None:
    logged_in(api.client)
    before = display_name(api)
    token = csrf_token(api.client, "/admin/maps/1")
    renamed = api.client.post(
        "/admin/maps/1/rename", data={"csrf_token": token, "display_name": NUL}
    )
    assert renamed.status_code == 422, renamed.text[:300]
    assert "display_name" in renamed.text
    assert "NUL" in renamed.text
    assert display_name(api) == before
    token = csrf_token(api.client, "/admin/keys")
    created = api.client.post(
        "/admin/keys", data={"csrf_token": token, "name": NUL, "role": "device"}
    )
    assert created.status_code == 422, created.text[:300]
    assert api.count(ApiKey) == 0

"""One device cannot hold the workers or the queue for everyone (issue 19, finding 2): uploads
per device key are limited (429 with Retry-After, before the body is read), a device key may ask
for few auto-tuning trials, a rebuild's iteration cap is bounded. On SQLite and PostgreSQL."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import timedelta

import pytest
from api_support import ADMIN, ONETAG, Api, running_api, session_variant
from sqlalchemy import select

from app.storage.orm import SessionRow, utc_now

pytestmark = pytest.mark.db


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url, uploads_per_minute=3, device_max_auto_tune_trials=5) as running:
        yield running


def test_uploads_per_device_key_are_limited(api: Api) -> None:
    phone, other_phone = api.device(), api.device()
    for k in range(3):
        api.uploaded(session_variant(ONETAG, map_id=f"map {k}"), auth=phone)
    refused = api.upload(session_variant(ONETAG, map_id="map 3"), auth=phone)
    assert refused.status_code == 429, refused.text
    assert refused.json()["code"] == "rate_limited"
    assert 1 <= int(refused.headers["retry-after"]) <= 60
    assert api.count(SessionRow) == 3
    # another phone, and an admin, go on uploading
    api.uploaded(session_variant(ONETAG, map_id="other"), auth=other_phone)
    api.uploaded(session_variant(ONETAG, map_id="admin"), auth=ADMIN)


def test_the_upload_limit_holds_across_api_processes(api: Api, database_url: str) -> None:
    # Two apps on one database are two API processes (serve --api-processes 2): the limit is
    # counted from the stored sessions, not per process.
    phone = api.device()
    with running_api(database_url, uploads_per_minute=3) as other_process:
        api.uploaded(session_variant(ONETAG, map_id="a0"), auth=phone)
        other_process.uploaded(session_variant(ONETAG, map_id="b0"), auth=phone)
        api.uploaded(session_variant(ONETAG, map_id="a1"), auth=phone)
        for process in (other_process, api):
            refused = process.upload(session_variant(ONETAG, map_id="late"), auth=phone)
            assert refused.status_code == 429, refused.text
            assert 1 <= int(refused.headers["retry-after"]) <= 60
    assert api.count(SessionRow) == 3


def test_uploads_older_than_a_minute_do_not_count(api: Api) -> None:
    phone = api.device()
    for k in range(3):
        api.uploaded(session_variant(ONETAG, map_id=f"map {k}"), auth=phone)
    assert api.upload(session_variant(ONETAG, map_id="map 3"), auth=phone).status_code == 429
    with api.db.transaction() as db_session:  # the oldest upload is now 61 s old
        oldest = db_session.scalars(select(SessionRow).order_by(SessionRow.id)).first()
        assert oldest is not None
        oldest.created_at = utc_now() - timedelta(seconds=61)
    api.uploaded(session_variant(ONETAG, map_id="map 3"), auth=phone)
    assert api.upload(session_variant(ONETAG, map_id="map 4"), auth=phone).status_code == 429


def test_a_device_key_may_ask_for_few_tuning_trials(api: Api) -> None:
    phone = api.device()
    refused = api.client.post(
        "/v1/sessions?auto_tune_trials=1000",
        content=ONETAG.read_bytes(),
        headers={**phone, "Content-Type": "application/json"},
    )
    assert refused.status_code == 422, refused.text
    assert refused.json()["field"] == "auto_tune_trials"
    assert "at most 5" in refused.json()["detail"]
    allowed = api.client.post(
        "/v1/sessions?auto_tune_trials=5",
        content=ONETAG.read_bytes(),
        headers={**phone, "Content-Type": "application/json"},
    )
    assert allowed.status_code == 202, allowed.text
    as_admin = api.client.post(
        "/v1/sessions?auto_tune_trials=1000",
        content=ONETAG.read_bytes(),
        headers={**ADMIN, "Content-Type": "application/json"},
    )
    assert as_admin.status_code == 202, as_admin.text


@pytest.mark.parametrize("max_iterations", [1e308, 10_001, 2**63])
def test_a_rebuild_may_not_ask_for_endless_iterations(api: Api, max_iterations: float) -> None:
    map_id = api.uploaded(ONETAG)["map_id"]
    response = api.client.post(
        f"/v1/maps/{map_id}/rebuild",
        json={"params": {"max_iterations": max_iterations}},
        headers=ADMIN,
    )
    assert response.status_code == 422, response.text
    assert response.json()["field"] == "params.max_iterations"

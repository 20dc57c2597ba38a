"""What docs/api.md's permissions table says of a device key and what it made
(``tests/doc_facts.py``, ``OWN_ONLY``), by calling each of those operations with the key that made
the thing and with another device key: the other key gets 404 (or an empty list), as if nothing
were there; the maker never 401, 403 or 404. SQLite and PostgreSQL.

The table's other rows (the key each operation needs) are read from the routes' dependencies and
checked in ``tests/unit/test_docs_drift.py``; ``test_api_jobs_keys.py`` calls every operation with
a device key."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from api_support import ONETAG, Api, run_next_job, running_api

from tests.doc_facts import OWN_ONLY

pytestmark = pytest.mark.db


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url) as running:
        yield running


def test_a_device_key_reaches_only_what_it_made_where_the_table_says_so(api: Api) -> None:
    maker, other = api.device(), api.device()
    upload = api.uploaded(ONETAG, headers=maker)
    run_next_job(api.db)
    started = api.client.post(f"/v1/maps/{upload['map_id']}/localizations", headers=maker)
    assert started.status_code == 201, started.text
    ids = {
        "session_id": upload["session_id"],
        "job_id": upload["job_id"],
        "localization_id": started.json()["id"],
    }

    assert len(OWN_ONLY) == 7
    for method, template in OWN_ONLY:
        path = template.format(**ids)
        # a body that passes validation, so that what answers is the ownership
        body = {"poses": [], "tag_data": []} if path.endswith("/updates") else None
        mine = api.client.request(method, path, headers=maker, json=body)
        theirs = api.client.request(method, path, headers=other, json=body)
        assert mine.status_code not in (401, 403, 404), (method, path, mine.text)
        if path == "/v1/sessions":  # a list: the other key's lists nothing
            assert mine.json()["count"] == 1
            assert theirs.status_code == 200
            assert (theirs.json()["count"], theirs.json()["data"]) == (0, [])
        else:
            assert theirs.status_code == 404, (method, path, theirs.text)
            assert theirs.json()["code"] == "not_found"

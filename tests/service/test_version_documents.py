"""Documents derived from a map version (the app-map, the GeoJSON) are made once per API process
and then served from memory: a version never changes. The caches must never serve a stale or a
deleted map: a rebuild is a new version with its own ETag and document, an older version is still
its own, and a deleted map is a 404 (issue 16)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from api_support import ADMIN, OCCAM, Api, run_next_job, running_api

import app.services.maps as map_services


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url) as running:
        yield running


@pytest.fixture
def built(api: Api) -> dict[str, Any]:
    created = api.uploaded(OCCAM)
    assert run_next_job(api.db, path_graph=True) == created["job_id"]
    return created


def _rebuilt(api: Api, created: dict[str, Any]) -> None:
    response = api.client.post(
        created["map_url"] + "/rebuild", json={"params": {"max_iterations": 40}}, headers=ADMIN
    )
    assert response.status_code == 202, response.text
    assert run_next_job(api.db, path_graph=True) is not None


def test_the_app_map_is_made_once_per_version(
    api: Api, built: dict[str, Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    made: list[int] = []
    real = map_services.app_map_content

    def counting(db_session: Any, version: Any) -> bytes:
        made.append(version.number)
        return real(db_session, version)

    monkeypatch.setattr(map_services, "app_map_content", counting)
    url = built["map_url"] + "/app-map"
    plain = api.client.get(url, headers={**ADMIN, "Accept-Encoding": "identity"})
    zipped = api.client.get(url, headers={**ADMIN, "Accept-Encoding": "gzip"})
    assert plain.status_code == zipped.status_code == 200
    assert "content-encoding" not in plain.headers
    assert zipped.headers["content-encoding"] == "gzip"
    assert zipped.json() == plain.json()  # the client undoes the gzip
    assert made == [1]  # the second answer came from memory

    _rebuilt(api, built)
    newer = api.client.get(url, headers=ADMIN)
    assert newer.headers["ETag"] != plain.headers["ETag"]
    assert made == [1, 2]  # a new version: a new document
    first = api.client.get(url + "?version=1", headers=ADMIN)
    assert first.content == plain.content  # the old version is still itself, from memory
    assert made == [1, 2]
    stale = api.client.get(url, headers={**ADMIN, "If-None-Match": plain.headers["ETag"]})
    assert stale.status_code == 200  # the phone holding version 1 gets version 2

    assert api.client.delete(built["map_url"], headers=ADMIN).status_code == 204
    assert api.client.get(url, headers=ADMIN).status_code == 404


def test_geojson_has_an_etag_a_304_and_gzip_and_follows_the_version(
    api: Api, built: dict[str, Any]
) -> None:
    url = built["map_url"] + "/geojson"
    first = api.client.get(url, headers={**ADMIN, "Accept-Encoding": "gzip"})
    assert first.status_code == 200
    assert first.headers["content-type"] == "application/geo+json"
    assert first.headers["content-encoding"] == "gzip"  # occam_room's is larger than 4 kB
    assert first.json()["type"] == "FeatureCollection"
    etag = first.headers["ETag"]
    again = api.client.get(url, headers={**ADMIN, "If-None-Match": etag})
    assert again.status_code == 304
    assert again.content == b""

    _rebuilt(api, built)
    after = api.client.get(url, headers={**ADMIN, "If-None-Match": etag})
    assert after.status_code == 200
    assert after.headers["ETag"] != etag

    assert api.client.delete(built["map_url"], headers=ADMIN).status_code == 204
    assert api.client.get(url, headers=ADMIN).status_code == 404

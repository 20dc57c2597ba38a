"""What the worker derives from a version once (issue 19, finding 3), on SQLite and PostgreSQL:
the app-map and the dashboard's overview stored as blobs with the version and served as stored
(equal to what the API would build), versions without them (stored before, restored, another
export) built as before, the blobs kept by the orphan collector, and a backup round trip."""

from __future__ import annotations

import gzip
import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from admin_support import logged_in
from api_support import ADMIN, OCCAM, Api, run_next_job, running_api

from app.domain.formats.derived_documents import APP_MAP_EXPORT, overview_document
from app.domain.formats.map_io import map_from_json
from app.domain.navigation.path_graph import path_graph_from_json
from app.services import maps as map_services
from app.services.uploads import stored_session
from app.storage import backup, blobs, maps, queue
from app.storage.maps import VersionInfo
from app.storage.navigation import path_graph_document
from app.storage.orm import utc_now
from tests.conftest import fresh_database_url
from tests.service.test_api_multi_session import FLOOR_2, STRAIGHT_209, with_poi
from tests.service.test_version_blobs import LATER
from tests.service.test_worker import settings_for
from workers import pipeline
from workers.main import Worker

pytestmark = pytest.mark.db

_FIGURE = re.compile(r'<script type="application/json" id="map-figure">(.*?)</script>', re.S)


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url) as running:
        yield running


def worker_built(api: Api) -> dict[str, Any]:
    """The real session uploaded and built by a worker (every stage, as served)."""
    created = api.uploaded(OCCAM)
    assert Worker(api.db, settings_for(api.db)).run_once()
    return created


def current_version(api: Api, map_id: int) -> VersionInfo:
    with api.db.read() as tx:
        return maps.get_version(tx, map_id)


def never(*_: object) -> Any:
    raise AssertionError("the whole map document was decoded")


def test_the_worker_stores_the_app_map_and_the_api_serves_it_as_stored(
    api: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    created = worker_built(api)
    version = current_version(api, created["map_id"])
    assert version.app_map_sha256 is not None
    assert version.overview_sha256 is not None
    assert version.app_map_export == APP_MAP_EXPORT
    with api.db.read() as tx:
        stored = maps.derived_bytes(tx, version.app_map_sha256)
        built = map_services.app_map_content(tx, version)
    assert stored is not None
    assert gzip.decompress(stored) == built  # what the API would make, byte for byte

    monkeypatch.setattr(map_services, "app_map_content", never)
    monkeypatch.setattr(maps, "map_document", never)
    url = created["map_url"] + "/app-map"
    plain = api.client.get(url, headers={**ADMIN, "Accept-Encoding": "identity"})
    assert plain.status_code == 200, plain.text
    assert plain.content == built
    with api.client.stream("GET", url, headers={**ADMIN, "Accept-Encoding": "gzip"}) as zipped:
        assert zipped.headers["Content-Encoding"] == "gzip"
        assert gzip.decompress(b"".join(zipped.iter_raw())) == built
    etag = plain.headers["ETag"]
    assert api.client.get(url, headers={**ADMIN, "If-None-Match": etag}).status_code == 304


def test_a_version_without_a_stored_app_map_or_of_another_export_gets_one_built(
    api: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    before = api.uploaded(OCCAM)  # stored as before the derived documents (no worker stage)
    assert run_next_job(api.db, path_graph=True) is not None
    old = current_version(api, before["map_id"])
    assert old.app_map_sha256 is None
    assert old.overview_sha256 is None
    newer = worker_built(api)
    assert newer["map_id"] != before["map_id"]

    made: list[int] = []
    real = map_services.app_map_content

    def counting(db_session: Any, version: VersionInfo) -> bytes:
        made.append(version.map_id)
        return real(db_session, version)

    monkeypatch.setattr(map_services, "app_map_content", counting)
    monkeypatch.setattr(map_services, "APP_MAP_EXPORT", APP_MAP_EXPORT + 1)  # a newer export
    for created in (before, newer):
        answer = api.client.get(created["map_url"] + "/app-map", headers=ADMIN)
        assert answer.status_code == 200, answer.text
        with api.db.read() as tx:
            expected = real(tx, current_version(api, created["map_id"]))
        assert answer.content == expected
    assert made == [before["map_id"], newer["map_id"]]  # both built, the stored one not served


def test_the_map_page_draws_the_stored_overview(api: Api, monkeypatch: pytest.MonkeyPatch) -> None:
    created = worker_built(api)
    version = current_version(api, created["map_id"])
    with api.db.read() as tx:
        graph = path_graph_document(tx, version.id)
        assert graph is not None
        expected = overview_document(
            map_from_json(maps.map_document(tx, created["map_id"])),
            stored_session(tx, created["session_id"]),
            path_graph_from_json(graph),
        )["figure"]

    monkeypatch.setattr(maps, "map_document", never)
    monkeypatch.setattr("app.admin.pages.maps.raw_session", never)
    logged_in(api.client)
    page = api.client.get(f"/admin/maps/{created['map_id']}")
    assert page.status_code == 200, page.text
    match = _FIGURE.search(page.text)
    assert match is not None
    figure = json.loads(match.group(1))
    # what the page built from the whole document before, without reading it
    assert figure == json.loads(json.dumps(expected))
    assert figure["floors"][0]["raw"] is not None  # the raw walk is in it
    tester = api.client.get(f"/admin/maps/{created['map_id']}/route")
    assert tester.status_code == 200, tester.text  # the route tester draws the same figure


def test_the_overview_of_a_map_of_two_sessions_draws_each_session(
    api: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    first = api.uploaded(with_poi(FLOOR_2, "Room 209", 400))
    second = api.uploaded(with_poi(STRAIGHT_209, "Occam lab door", 900))
    worker = Worker(api.db, settings_for(api.db))
    while worker.run_once():
        pass
    merge = api.client.post(
        f"/v1/maps/{first['map_id']}/merge", json={"map_id": second["map_id"]}, headers=ADMIN
    )
    assert merge.status_code == 202, merge.text
    assert worker.run_once()
    version = current_version(api, first["map_id"])
    assert version.session_ids == [first["session_id"], second["session_id"]]
    assert version.overview_sha256 is not None
    with api.db.read() as tx:
        graph = path_graph_document(tx, version.id)
        assert graph is not None
        expected = overview_document(
            map_from_json(maps.map_document(tx, first["map_id"])),
            None,  # each session's raw odometry is in its own frame: none is drawn
            path_graph_from_json(graph),
            sessions=version.statistics["sessions"],
        )["figure"]

    monkeypatch.setattr(maps, "map_document", never)
    logged_in(api.client)
    page = api.client.get(f"/admin/maps/{first['map_id']}")
    assert page.status_code == 200, page.text
    match = _FIGURE.search(page.text)
    assert match is not None
    figure = json.loads(match.group(1))
    assert figure == json.loads(json.dumps(expected))
    assert all(floor["raw"] is None for floor in figure["floors"])
    drawn = {line["name"] for floor in figure["floors"] for line in floor["sessions"]}
    assert drawn == {f"Session {first['session_id']}", f"Session {second['session_id']}"}


def test_a_version_is_stored_without_derived_documents_that_fail(
    api: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    """They are what the API would make anyway: a failure costs the build nothing."""

    def failing(*_: object, **__: object) -> Any:
        raise RuntimeError("no overview")

    monkeypatch.setattr(pipeline.build_map, "packed_documents", failing)
    created = worker_built(api)
    version = current_version(api, created["map_id"])
    assert version.app_map_sha256 is None
    assert version.overview_sha256 is None
    with api.db.read() as tx:
        log_tail = queue.get_job(tx, version.job_id or 0).log_tail
    assert "no app-map or overview stored (RuntimeError)" in log_tail
    answer = api.client.get(created["map_url"] + "/app-map", headers=ADMIN)
    assert answer.status_code == 200, answer.text
    logged_in(api.client)
    assert api.client.get(f"/admin/maps/{created['map_id']}").status_code == 200


def test_the_derived_blobs_are_not_collected_as_orphans(api: Api) -> None:
    created = worker_built(api)
    version = current_version(api, created["map_id"])
    blobs.collect_orphan_blobs(api.db, now=utc_now() + LATER)
    with api.db.read() as tx:
        for sha256 in (version.app_map_sha256, version.overview_sha256):
            assert sha256 is not None
            assert blobs.read_blob(tx, sha256)


def test_an_import_makes_the_derived_documents_again(
    api: Api, request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The archive does not carry them; the import makes them from what it restores, equal to
    what the worker stored, and the restored API serves them without building."""
    created = worker_built(api)
    served = api.client.get(created["map_url"] + "/app-map", headers=ADMIN)
    assert served.status_code == 200
    original = current_version(api, created["map_id"])
    archive = tmp_path / "backup.zip"
    backup.export_archive(api.db, archive)
    (tmp_path / "restored").mkdir()
    for target_url in fresh_database_url("sqlite", request, tmp_path / "restored"):
        with running_api(target_url) as restored:
            backup.import_archive(restored.db, archive)
            version = current_version(restored, created["map_id"])
            assert version.app_map_sha256 == original.app_map_sha256  # the same bytes
            assert version.overview_sha256 == original.overview_sha256
            assert version.app_map_export == APP_MAP_EXPORT
            monkeypatch.setattr(map_services, "app_map_content", never)
            again = restored.client.get(created["map_url"] + "/app-map", headers=ADMIN)
            assert again.status_code == 200, again.text
            assert again.content == served.content
            assert again.headers["ETag"] == served.headers["ETag"]

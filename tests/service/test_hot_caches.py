"""The API's per-process memory of the hot read path (issue 16; docs/api.md, "Caching and
consistency"): what another process changes is seen within the stated bound (a fake clock, no
sleeping), what this process changes at once, an expiry exactly; every cache is bounded.

"Another process" is played by SQL on a second connection: the storage functions would move this
process's change counters (``app.storage.changes``), which is what this process's own changes do.
"""

from __future__ import annotations

import gzip
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from typing import Any

import pytest
from api_support import ADMIN, OCCAM, ONETAG, Api, bearer, run_next_job, running_api
from sqlalchemy import text

from app.services.keys import PrincipalCache
from app.services.maps import MapPages, MapStates
from app.services.version_cache import VersionCache
from app.storage import queue
from app.storage.db import Database
from app.storage.orm import Role
from app.storage.sessions import BUILD_MAP
from app.web.http import ReadyDocument

KEY_BOUND_S = 5.0
MAP_BOUND_S = 2.0


class FakeClock:
    """A monotonic clock that moves only when told."""

    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def api(database_url: str, clock: FakeClock) -> Iterator[Api]:
    with running_api(database_url, key_cache_s=KEY_BOUND_S, map_cache_s=MAP_BOUND_S) as running:
        running.app.state.principals = PrincipalCache(KEY_BOUND_S, clock=clock)
        running.app.state.map_states = MapStates(MAP_BOUND_S, clock=clock)
        running.app.state.map_pages = MapPages(MAP_BOUND_S, clock=clock)
        yield running


@pytest.fixture
def other_process(database_url: str) -> Iterator[Database]:
    """A second connection to the database, as another API process or the CLI has."""
    database = Database(database_url)
    yield database
    database.dispose()


def _sql(database: Database, statement: str, **values: Any) -> None:
    with database.transaction() as db_session:
        db_session.execute(text(statement), values)


# --------------------------------------------------------------------------- keys


def test_a_key_revoked_by_another_process_is_refused_within_the_bound(
    api: Api, clock: FakeClock, other_process: Database
) -> None:
    key_id, secret = api.create_key(Role.DEVICE)
    assert api.client.get("/v1/info", headers=bearer(secret)).status_code == 200  # now kept

    _sql(other_process, "UPDATE api_key SET revoked_at = :now WHERE id = :id",
         now=datetime.now(UTC), id=key_id)  # fmt: skip
    clock.now_s += KEY_BOUND_S - 0.1
    assert api.client.get("/v1/info", headers=bearer(secret)).status_code == 200  # the bound
    clock.now_s += 0.1
    refused = api.client.get("/v1/info", headers=bearer(secret))
    assert refused.status_code == 401
    assert refused.json()["code"] == "unauthorized"


def test_a_key_revoked_in_this_process_is_refused_at_once(api: Api) -> None:
    key_id, secret = api.create_key(Role.DEVICE)
    _other_id, other = api.create_key(Role.DEVICE)
    for key in (secret, other):
        assert api.client.get("/v1/info", headers=bearer(key)).status_code == 200
    assert len(api.app.state.principals) == 2

    assert api.client.delete(f"/v1/keys/{key_id}", headers=ADMIN).status_code == 200
    assert api.client.get("/v1/info", headers=bearer(secret)).status_code == 401
    assert api.client.get("/v1/info", headers=bearer(other)).status_code == 200  # read again


def test_a_kept_key_expires_exactly_at_its_expiry(api: Api) -> None:
    wall = [datetime.now(UTC)]
    api.app.state.principals = PrincipalCache(KEY_BOUND_S, now=lambda: wall[0])
    expires_at = wall[0] + timedelta(hours=1)
    _, secret = api.create_key(Role.DEVICE, expires_at=expires_at)
    assert api.client.get("/v1/info", headers=bearer(secret)).status_code == 200  # now kept

    wall[0] = expires_at - timedelta(microseconds=1)
    assert api.client.get("/v1/info", headers=bearer(secret)).status_code == 200
    wall[0] = expires_at
    assert api.client.get("/v1/info", headers=bearer(secret)).status_code == 401


def test_unknown_keys_are_not_kept_and_known_ones_are_bounded(api: Api) -> None:
    api.app.state.principals = PrincipalCache(KEY_BOUND_S, max_entries=3)
    for k in range(20):
        unknown = f"im_{k:08x}_{'x' * 32}"
        assert api.client.get("/v1/info", headers=bearer(unknown)).status_code == 401
    assert len(api.app.state.principals) == 0
    secrets = [api.create_key(Role.DEVICE)[1] for _ in range(5)]
    for secret in secrets:
        assert api.client.get("/v1/info", headers=bearer(secret)).status_code == 200
    assert len(api.app.state.principals) == 3
    assert all(  # the forgotten ones are read again
        api.client.get("/v1/info", headers=bearer(secret)).status_code == 200 for secret in secrets
    )


def test_no_key_is_kept_with_a_bound_of_zero(api: Api, other_process: Database) -> None:
    api.app.state.principals = PrincipalCache(0.0)
    key_id, secret = api.create_key(Role.DEVICE)
    assert api.client.get("/v1/info", headers=bearer(secret)).status_code == 200
    _sql(other_process, "UPDATE api_key SET revoked_at = :now WHERE id = :id",
         now=datetime.now(UTC), id=key_id)  # fmt: skip
    assert api.client.get("/v1/info", headers=bearer(secret)).status_code == 401
    assert len(api.app.state.principals) == 0


# --------------------------------------------------------------------------- maps


@pytest.fixture
def built(api: Api) -> dict[str, Any]:
    created = api.uploaded(OCCAM)
    assert run_next_job(api.db, path_graph=True) == created["job_id"]
    return created


def test_a_rebuild_in_this_process_is_served_at_once(api: Api, built: dict[str, Any]) -> None:
    url = built["map_url"]
    first = api.client.get(url, headers=ADMIN)
    assert first.json()["current_version"]["number"] == 1
    assert api.client.get(url, headers={**ADMIN, "If-None-Match": first.headers["ETag"]}
                          ).status_code == 304  # fmt: skip

    queued = api.client.post(url + "/rebuild", json={"params": {}}, headers=ADMIN)
    assert queued.status_code == 202
    building = api.client.get(url, headers=ADMIN).json()
    assert building["latest_job"]["state"] == "queued"  # not the kept state
    assert run_next_job(api.db, path_graph=True) is not None  # a worker: another process
    after = api.client.get(url, headers={**ADMIN, "If-None-Match": first.headers["ETag"]})
    assert after.status_code == 200
    assert after.json()["current_version"]["number"] == 2
    assert after.headers["ETag"] != first.headers["ETag"]
    route = api.client.post(url + "/routes", json={"from": {"tag": 0}, "to": {"tag": 2}},
                            headers=ADMIN)  # fmt: skip
    assert route.status_code in {200, 404, 409}, route.text
    if route.status_code == 200:
        assert route.json()["map_version"] == 2


def test_a_version_built_for_another_process_is_served_within_the_bound(
    api: Api, built: dict[str, Any], clock: FakeClock
) -> None:
    url = built["map_url"]
    assert api.client.get(url, headers=ADMIN).json()["current_version"]["number"] == 1
    geojson = api.client.get(url + "/geojson", headers=ADMIN)
    with api.db.transaction() as db_session:  # another API process queues a rebuild…
        queue.enqueue(
            db_session, kind=BUILD_MAP, map_id=built["map_id"], session_id=built["session_id"],
            params={}, max_attempts=1,
        )  # fmt: skip
    assert run_next_job(api.db, path_graph=True) is not None  # …and a worker builds it

    clock.now_s += MAP_BOUND_S - 0.1
    assert api.client.get(url, headers=ADMIN).json()["current_version"]["number"] == 1
    clock.now_s += 0.1
    assert api.client.get(url, headers=ADMIN).json()["current_version"]["number"] == 2
    newer = api.client.get(url + "/geojson", headers=ADMIN)
    assert newer.headers["ETag"] != geojson.headers["ETag"]


def test_a_deleted_map_is_gone(
    api: Api, built: dict[str, Any], clock: FakeClock, other_process: Database
) -> None:
    url = built["map_url"]
    other = api.uploaded(ONETAG)
    assert run_next_job(api.db) == other["job_id"]
    for path in (url, other["map_url"]):
        assert api.client.get(path, headers=ADMIN).status_code == 200  # both kept now
    assert api.client.get(url + "/app-map", headers=ADMIN).status_code == 200

    assert api.client.delete(url, headers=ADMIN).status_code == 204  # in this process
    for path in (url, url + "/app-map", url + "/geojson"):
        assert api.client.get(path, headers=ADMIN).status_code == 404, path

    _sql(other_process, "DELETE FROM map_version WHERE map_id = :id", id=other["map_id"])
    _sql(other_process, "DELETE FROM job WHERE map_id = :id", id=other["map_id"])
    _sql(other_process, "DELETE FROM map_session WHERE map_id = :id", id=other["map_id"])
    _sql(other_process, "DELETE FROM map WHERE id = :id", id=other["map_id"])
    clock.now_s += MAP_BOUND_S
    assert api.client.get(other["map_url"], headers=ADMIN).status_code == 404


def test_a_rename_and_a_new_map_are_seen_at_once(api: Api, built: dict[str, Any]) -> None:
    url = built["map_url"]
    before = api.client.get(url, headers=ADMIN)
    listed = api.client.get("/v1/maps", headers=ADMIN).json()
    assert listed["count"] == 1

    renamed = api.client.patch(url, json={"display_name": "Library"}, headers=ADMIN)
    assert renamed.status_code == 200
    after = api.client.get(url, headers={**ADMIN, "If-None-Match": before.headers["ETag"]})
    assert after.status_code == 200
    assert after.json()["display_name"] == "Library"
    assert api.client.get("/v1/maps", headers=ADMIN).json()["data"][0]["display_name"] == (
        "Library"
    )
    api.uploaded(ONETAG)
    assert api.client.get("/v1/maps", headers=ADMIN).json()["count"] == 2


def test_the_maps_list_follows_another_process_within_the_bound(
    api: Api, built: dict[str, Any], clock: FakeClock, other_process: Database
) -> None:
    assert api.client.get("/v1/maps", headers=ADMIN).json()["data"][0]["display_name"] != "Hall"
    _sql(other_process, "UPDATE map SET display_name = 'Hall' WHERE id = :id",
         id=built["map_id"])  # fmt: skip
    clock.now_s += MAP_BOUND_S - 0.1
    assert api.client.get("/v1/maps", headers=ADMIN).json()["data"][0]["display_name"] != "Hall"
    clock.now_s += 0.1
    assert api.client.get("/v1/maps", headers=ADMIN).json()["data"][0]["display_name"] == "Hall"


def test_the_map_document_is_gzipped_for_clients_that_take_it(
    api: Api, built: dict[str, Any]
) -> None:
    url = built["map_url"]
    plain = api.client.get(url, headers={**ADMIN, "Accept-Encoding": "identity"})
    assert "content-encoding" not in plain.headers
    assert len(plain.content) > 4096  # occam_room's tags
    with api.client.stream("GET", url, headers={**ADMIN, "Accept-Encoding": "gzip"}) as zipped:
        assert zipped.headers["Content-Encoding"] == "gzip"
        assert zipped.headers["ETag"] == plain.headers["ETag"]
        raw = b"".join(zipped.iter_raw())
    assert len(raw) < len(plain.content)


# --------------------------------------------------------------------------- bounds


def test_the_version_cache_is_bounded_by_bytes_and_entries() -> None:
    cache = VersionCache(max_entries=3, max_bytes=100)
    cache.put("a", b"x" * 60)
    cache.put("b", b"y" * 30)
    assert cache.size_bytes == 90
    cache.put("c", b"z" * 30)  # 120 bytes: the least recently used goes
    assert cache.peek("a") is None
    assert cache.size_bytes == 60
    cache.put("huge", b"h" * 101)  # larger than the bound: served, not kept
    assert cache.peek("huge") is None
    assert cache.get("huge", lambda: b"h" * 101) == b"h" * 101
    assert cache.size_bytes == 60
    for k in range(5):
        cache.put(("graph", k), object())  # no bytes: bounded by entries
    assert len(cache) == 3
    assert cache.size_bytes == 0


def test_map_states_keep_only_settled_maps_and_are_bounded(api: Api, built: dict[str, Any]) -> None:
    states = MapStates(MAP_BOUND_S, max_entries=1)
    assert states.load(api.db, built["map_id"]).settled
    assert states.fresh(built["map_id"]) is not None
    unbuilt = api.uploaded(ONETAG)  # its build is queued: read on every request
    assert not states.load(api.db, unbuilt["map_id"]).settled
    assert states.fresh(unbuilt["map_id"]) is None
    assert states.fresh(built["map_id"]) is not None
    assert run_next_job(api.db) == unbuilt["job_id"]
    states.load(api.db, unbuilt["map_id"])
    assert states.fresh(unbuilt["map_id"]) is not None
    assert states.fresh(built["map_id"]) is None  # one entry


def test_a_ready_document_answers_304_and_gzip_only_when_it_pays() -> None:
    small = ReadyDocument.of(b'{"a":1}', media_type="application/json")
    assert small.gzipped is None  # under 4 kB: sent as it is
    assert small.response(None, "gzip").headers.get("Content-Encoding") is None
    large = ReadyDocument.of(b"[" + b"1," * 5000 + b"1]", media_type="application/json")
    assert large.gzipped is not None
    zipped = large.response(None, "br, gzip;q=0.5")
    assert zipped.headers["Content-Encoding"] == "gzip"
    assert gzip.decompress(zipped.body) == large.content
    assert large.response(None, "gzip;q=0").headers.get("Content-Encoding") is None
    for held in (large.etag, f"W/{large.etag}", f'"other", {large.etag}', "*"):
        not_modified = large.response(held, "gzip")
        assert (not_modified.status_code, not_modified.body) == (304, b"")
        assert not_modified.headers["ETag"] == large.etag
    assert large.response('"other"', None).status_code == 200
    named = ReadyDocument.of(b"x", media_type="text/plain", etag='"v2"')
    assert named.etag == '"v2"'


def test_map_states_are_bounded_by_the_bytes_of_their_answers(
    api: Api, built: dict[str, Any]
) -> None:
    other = api.uploaded(ONETAG)
    assert run_next_job(api.db) == other["job_id"]
    states = MapStates(MAP_BOUND_S, max_bytes=1000)
    first = states.load(api.db, built["map_id"])
    second = states.load(api.db, other["map_id"])
    states.attach(first, "map", b"x" * 600)
    assert states.size_bytes == 600
    states.attach(second, "map", b"y" * 600)  # 1200 bytes: the older state goes
    assert states.size_bytes == 600
    assert states.fresh(built["map_id"]) is None
    kept = states.fresh(other["map_id"])
    assert kept is not None
    assert kept.documents["map"] == b"y" * 600
    states.attach(first, "map", b"z" * 10)  # a state no longer kept counts nothing
    assert states.size_bytes == 600
    states.load(api.db, other["map_id"])  # read again: the old state's answer is dropped
    assert (len(states), states.size_bytes) == (1, 0)

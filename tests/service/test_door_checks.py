"""What the API refuses at the door or answers safely (issue 19, findings 6, 7 and 13): text that
cannot be stored, tag ids beyond the database's column, infinite durations, key expiries beyond
the year 9999 are each a 422 naming the field (never a 500 or a build that fails); an upload
whose key is revoked while its body arrives is not stored; the answer carrying a new key's
secret is not cached; every answer has the security headers. On SQLite and PostgreSQL."""

from __future__ import annotations

import json
import os
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from api_support import ADMIN, JSON, ONETAG, Api, onetag, running_api

from app.api import access_log
from app.api.routes import sessions as sessions_route
from app.domain.upload.json_stream import JsonStream
from app.storage import keys
from app.storage.db import Database
from app.storage.orm import MapRow, SessionRow
from app.web.security import API_CSP, COMMON_HEADERS

pytestmark = pytest.mark.db

POIS = ONETAG.parents[1] / "demo" / "floor_2_pois.json"


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url) as running:
        yield running


def with_tag_id(tag_id: int) -> dict[str, Any]:
    document = onetag()
    for frame in document["tag_data"]:
        for detection in frame:
            detection["tag_id"] = tag_id
    return document


def with_timestamps(first: float, last: float) -> dict[str, Any]:
    """Every pose at 0 s but the first and the last (so no step between two overflows)."""
    document = onetag()
    poses = document["pose_data"]
    for pose in poses:
        pose["timestamp"] = 0.0
    poses[0]["timestamp"], poses[-1]["timestamp"] = first, last
    return document


def with_poi(name: str) -> dict[str, Any]:
    """The demo session with points of interest, the first renamed."""
    document: dict[str, Any] = json.loads(POIS.read_bytes())
    document["location_data"][0]["name"] = name
    return document


@pytest.mark.parametrize(
    ("document", "field", "words"),
    [
        (onetag(map_id="lab \ud800 room"), "map_id", "lone surrogate"),
        (onetag(map_id="lab \x00 room"), "map_id", "NUL"),
        (with_poi("exit \udfff"), "location_data[0].name", "lone surrogate"),
        (with_poi("exit \x00"), "location_data[0].name", "NUL"),
        (with_tag_id(2**31), "tag_data", "larger than 2147483647"),
        (with_tag_id(2**53), "tag_data", "larger than 2147483647"),
        (with_timestamps(-1e308, 1e308), "pose_data", "timestamps span"),
    ],
    ids=["surrogate-map-id", "nul-map-id", "surrogate-poi", "nul-poi", "tag-2^31", "tag-2^53",
         "infinite-duration"],
)  # fmt: skip
def test_uploads_that_could_not_be_stored_are_422_naming_the_field(
    api: Api, document: dict[str, Any], field: str, words: str
) -> None:
    # json.dumps escapes a lone surrogate as \ud800 (valid JSON text), as a hostile client would
    response = api.upload(json.dumps(document).encode())
    assert response.status_code == 422, response.text
    body = response.json()
    assert (body["code"], body["field"]) == ("invalid_session", field)
    assert words in body["detail"]
    assert api.count(SessionRow) == 0


def test_the_largest_storable_tag_id_is_accepted(api: Api) -> None:
    accepted = api.upload(json.dumps(with_tag_id(2**31 - 1)).encode())
    assert accepted.status_code == 202, accepted.text


def test_an_upload_whose_key_is_revoked_while_its_body_arrives_is_not_stored(
    api: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    key_id, secret = api.create_key(name="phone")
    real_parse = sessions_route._parse

    def revoke_then_parse(json_bytes: bytes, **kwargs: Any) -> Any:
        with api.db.transaction() as db_session:
            keys.revoke_key(db_session, key_id)
        return real_parse(json_bytes, **kwargs)

    monkeypatch.setattr(sessions_route, "_parse", revoke_then_parse)
    response = api.upload(ONETAG, auth={"Authorization": f"Bearer {secret}"})
    assert response.status_code == 401, response.text
    assert "revoked" in response.json()["detail"]
    assert (api.count(SessionRow), api.count(MapRow)) == (0, 0)


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"name": "x", "role": "device", "expires_at": "9999-12-31T23:59:59-23:59"}, "expires_at"),
        ({"name": "lab \u0000 phone", "role": "device"}, "name"),
    ],
)
def test_keys_that_could_not_be_stored_are_422_naming_the_field(
    api: Api, body: dict[str, Any], field: str
) -> None:
    response = api.client.post("/v1/keys", json=body, headers=ADMIN)
    assert response.status_code == 422, response.text
    assert response.json()["field"] == field


def test_the_answer_with_a_new_keys_secret_is_not_cached(api: Api) -> None:
    response = api.client.post("/v1/keys", json={"name": "x", "role": "device"}, headers=ADMIN)
    assert response.status_code == 201
    assert response.headers["cache-control"] == "no-store"


def test_every_answer_has_the_security_headers(api: Api) -> None:
    answers = {
        path: api.client.get(path, headers=ADMIN)
        for path in ("/healthz", "/v1/info", "/v1/maps/999", "/openapi.json", "/docs", "/redoc")
    }
    answers["upload refused"] = api.client.post("/v1/sessions", content=b"{", headers=JSON)
    for what, answer in answers.items():
        for name, value in COMMON_HEADERS.items():
            assert answer.headers.get(name) == value, what
        policy = answer.headers["content-security-policy"]
        assert "http" not in policy, what  # no other origin
        assert "frame-ancestors 'none'" in policy, what
    assert answers["/v1/info"].headers["content-security-policy"] == API_CSP
    assert "script-src 'self' 'sha256-" in answers["/docs"].headers["content-security-policy"]


def test_sqlite_files_are_readable_by_their_owner_only(tmp_path: Path) -> None:
    new = tmp_path / "new" / "db.sqlite3"
    Database(f"sqlite:///{new}").dispose()
    assert stat.S_IMODE(new.stat().st_mode) == 0o600
    old = tmp_path / "old.sqlite3"
    old.touch()
    os.chmod(old, 0o644)
    database = Database(f"sqlite:///{old}")
    with database.transaction() as db_session:
        db_session.connection().exec_driver_sql("CREATE TABLE t (x)")
    database.dispose()
    assert stat.S_IMODE(old.stat().st_mode) == 0o600
    for suffix in ("-wal", "-shm"):
        side = old.with_name(old.name + suffix)
        if side.exists():
            assert stat.S_IMODE(side.stat().st_mode) == 0o600


@pytest.mark.parametrize(
    ("target", "redacted"),
    [
        ("/v1/info?api_key=im_0a1b2c3d_s3cret-XYZ", "/v1/info?api_key=***"),
        ("/v1/maps?limit=5&token=abc&x=1", "/v1/maps?limit=5&token=***&x=1"),
        ("/v1/maps/im_0a1b2c3d_s3cret", "/v1/maps/im_***"),
        ("/v1/maps?limit=5", "/v1/maps?limit=5"),
    ],
)
def test_keys_in_a_request_target_are_redacted_in_the_access_log(
    target: str, redacted: str
) -> None:
    assert access_log.redact(target) == redacted


def test_a_session_with_more_poses_than_allowed_is_refused_while_parsing(
    database_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    items_decoded: list[object] = []
    real_array_items = JsonStream.array_items

    def counted_array_items(stream: JsonStream) -> Iterator[Any]:
        for item in real_array_items(stream):
            items_decoded.append(item)
            yield item

    monkeypatch.setattr(JsonStream, "array_items", counted_array_items)
    with running_api(database_url, max_poses=10) as api:
        response = api.upload(ONETAG)
        assert response.status_code == 422, response.text
        assert response.json()["field"] == "pose_data"
        assert "at most 10 (INVISIBLE_MAP_MAX_POSES)" in response.json()["detail"]
        # refused at pose 11 (pose_data comes first in the app's upload), the rest never decoded
        assert len(items_decoded) == 11
        assert len(json.loads(ONETAG.read_bytes())["pose_data"]) == 25
        assert api.count(SessionRow) == 0

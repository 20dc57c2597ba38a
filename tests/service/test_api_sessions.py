"""POST/GET /v1/sessions: uploads (plain, gzip, idempotent), every way an upload is refused with
nothing stored, listing, reading, and the raw download byte for byte. SQLite and PostgreSQL."""

from __future__ import annotations

import gzip
import hashlib
import json
import threading
from collections.abc import Iterator

import pytest
from api_support import ADMIN, JSON, OCCAM, ONETAG, Api, bearer, running_api, session_variant
from sqlalchemy.orm import Session

from app.api.routes.sessions import UPLOAD_EXAMPLE
from app.domain.upload.session import load_session
from app.storage import sessions
from app.storage.orm import Job, MapRow, SessionRow, SessionUpload

pytestmark = pytest.mark.db


@pytest.fixture
def api(database_url: str) -> Iterator[Api]:
    with running_api(database_url) as running:
        yield running


def nothing_stored(api: Api) -> bool:
    return all(api.count(table) == 0 for table in (SessionRow, SessionUpload, MapRow, Job))


# --------------------------------------------------------------------------- happy paths


def test_upload_answers_202_with_ids_location_and_statistics(api: Api) -> None:
    response = api.upload(OCCAM)

    assert response.status_code == 202, response.text
    body = response.json()
    assert response.headers["Location"] == f"/v1/jobs/{body['job_id']}"
    assert body["job_url"] == f"/v1/jobs/{body['job_id']}"
    assert body["map_url"] == f"/v1/maps/{body['map_id']}"
    assert "Idempotent-Replayed" not in response.headers
    expected = load_session(OCCAM)
    stats = body["statistics"]
    assert stats["pose_count"] == expected.num_poses == 621
    assert stats["detection_count"] == len(expected.detections)
    assert stats["tag_ids"] == expected.tag_ids
    assert stats["tag_count"] == len(expected.tag_ids)
    assert stats["poi_count"] == len(expected.pois)
    assert stats["path_length_m"] == pytest.approx(expected.path_length_m())
    assert stats["duration_s"] == pytest.approx(expected.timestamp_s[-1] - expected.timestamp_s[0])
    assert body["map_name"] == expected.map_id
    assert [api.count(t) for t in (SessionRow, SessionUpload, MapRow, Job)] == [1, 1, 1, 1]

    job = api.client.get(body["job_url"], headers=ADMIN).json()
    assert job["state"] == "queued"
    assert job["progress"] == 0
    assert job["kind"] == "build_map"
    assert job["session_id"] == body["session_id"]
    assert job["map_id"] == body["map_id"]
    assert job["max_attempts"] == api.settings.max_attempts


def test_get_session_has_metadata_statistics_map_and_jobs(api: Api) -> None:
    created = api.uploaded(ONETAG, idempotency_key="walk-1")

    response = api.client.get(f"/v1/sessions/{created['session_id']}", headers=ADMIN)

    assert response.status_code == 200
    session = response.json()
    raw = ONETAG.read_bytes()
    assert session["id"] == created["session_id"]
    assert session["map_id"] == created["map_id"]
    assert session["job_ids"] == [created["job_id"]]
    assert session["uploaded_by"] == "env-admin"
    assert session["idempotency_key"] == "walk-1"
    assert session["raw_size_bytes"] == len(raw)
    assert 0 < session["stored_size_bytes"] < len(raw)
    assert session["statistics"] == created["statistics"]
    assert session["raw_sha256"] == hashlib.sha256(raw).hexdigest()


def test_documented_example_upload_is_accepted(api: Api) -> None:
    response = api.upload(json.dumps(UPLOAD_EXAMPLE).encode())

    assert response.status_code == 202, response.text
    assert response.json()["statistics"]["tag_ids"] == [3]


@pytest.mark.parametrize(
    "content_type", ["application/json; charset=utf-8", "Application/JSON", "application/json;"]
)
def test_json_media_type_with_utf8_charset_is_accepted(api: Api, content_type: str) -> None:
    response = api.upload(ONETAG, headers={"Content-Type": content_type})

    assert response.status_code == 202, response.text


def test_raw_download_is_byte_identical_plain_and_gzip(api: Api) -> None:
    # Unusual but valid JSON formatting must survive as sent: whitespace, key order, unknown keys.
    original = b'  {"zzz_unknown": [1, 2.50, "\\u00e9"],\n' + ONETAG.read_bytes().lstrip()[1:]
    plain = api.uploaded(original)
    gzipped = api.uploaded(OCCAM, compress=True)

    for created, expected in ((plain, original), (gzipped, OCCAM.read_bytes())):
        url = f"/v1/sessions/{created['session_id']}/raw"
        as_gzip = api.client.get(url, headers={**ADMIN, "Accept-Encoding": "gzip"})
        identity = api.client.get(url, headers={**ADMIN, "Accept-Encoding": "identity"})
        assert as_gzip.status_code == identity.status_code == 200
        assert as_gzip.headers["Content-Encoding"] == "gzip"
        assert "Content-Encoding" not in identity.headers
        assert as_gzip.headers["Content-Type"] == identity.headers["Content-Type"]
        assert identity.headers["Content-Type"].startswith("application/json")
        assert as_gzip.content == identity.content == expected


def test_gzip_body_without_content_encoding_is_inflated(api: Api) -> None:
    response = api.upload(gzip.compress(ONETAG.read_bytes()))

    assert response.status_code == 202, response.text
    raw = api.client.get(
        f"/v1/sessions/{response.json()['session_id']}/raw",
        headers={**ADMIN, "Accept-Encoding": "identity"},
    )
    assert raw.content == ONETAG.read_bytes()


def test_multi_member_gzip_upload_is_stored_whole(api: Api) -> None:
    raw = ONETAG.read_bytes()
    body = gzip.compress(raw[:5000]) + gzip.compress(raw[5000:])

    response = api.upload(body, headers={"Content-Encoding": "gzip"})

    assert response.status_code == 202, response.text
    url = f"/v1/sessions/{response.json()['session_id']}/raw"
    assert api.client.get(url, headers={**ADMIN, "Accept-Encoding": "gzip"}).content == raw


# --------------------------------------------------------------------------- refused uploads


VALID_POSE = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]


def document(**changes: object) -> bytes:
    base: dict[str, object] = {
        "map_id": "m",
        "pose_data": [{"id": 0, "timestamp": 0.0, "pose": VALID_POSE}],
        "tag_data": [],
    }
    base.update(changes)
    return json.dumps(base, allow_nan=True).encode()


INVALID_SESSIONS = [
    pytest.param(b'{"map_id": "m", "pose_data": [', None, "not valid JSON", id="malformed-json"),
    pytest.param(b"", None, "not valid JSON", id="empty-body"),
    pytest.param(b"[1, 2, 3]", None, "expected a JSON object, got a list", id="not-an-object"),
    pytest.param(b'"text"', None, "expected a JSON object, got a string", id="a-string"),
    pytest.param(b'{"map_id": "\xff\xfe"}', None, "not UTF-8", id="not-utf8"),
    pytest.param(document(pose_data=None), "pose_data", "missing", id="missing-pose-data"),
    pytest.param(document(map_id=None), "map_id", "missing", id="missing-map-id"),
    pytest.param(document(map_id="x" * 201), "map_id", "longer than 200", id="map-id-too-long"),
    pytest.param(document(pose_data=[]), "pose_data", "empty session", id="empty-session"),
    pytest.param(
        document(pose_data=[{"id": 0, "timestamp": 0.0}]),
        "pose_data[0].pose",
        "missing",
        id="missing-pose",
    ),
    pytest.param(
        document(pose_data=[{"id": 0, "timestamp": 0.0, "pose": [float("nan"), *VALID_POSE[1:]]}]),
        "pose_data[0].pose[0]",
        "non-finite number nan",
        id="nan",
    ),
    pytest.param(
        document(pose_data=[{"id": 0, "timestamp": float("inf"), "pose": VALID_POSE}]),
        "pose_data[0].timestamp",
        "non-finite number inf",
        id="infinity",
    ),
    pytest.param(
        document(pose_data=[{"id": 0, "timestamp": 0.0, "pose": VALID_POSE[:15]}]),
        "pose_data[0].pose",
        "expected 16 numbers, got 15",
        id="matrix-not-16",
    ),
    pytest.param(
        document(pose_data=[{"id": 0, "timestamp": 0.0, "pose": [2, *VALID_POSE[1:]]}]),
        "pose_data[0].pose",
        "orthonormal",
        id="rotation-not-orthonormal",
    ),
    pytest.param(
        document(
            tag_data=[[{"tag_id": 1, "pose_id": 7, "tag_pose": VALID_POSE}]],
        ),
        "tag_data[0][0].pose_id",
        "no pose with id 7",
        id="pose-id-without-pose",
    ),
]


@pytest.mark.parametrize(("body", "field", "reason"), INVALID_SESSIONS)
def test_invalid_session_is_422_naming_field_and_nothing_is_stored(
    api: Api, body: bytes, field: str | None, reason: str
) -> None:
    response = api.upload(body)

    assert response.status_code == 422, response.text
    error = response.json()
    assert error["code"] == "invalid_session"
    assert error["field"] == field
    assert reason in error["detail"]
    assert field is None or error["detail"].startswith(field)
    assert nothing_stored(api)


@pytest.mark.parametrize(
    ("headers", "field"),
    [
        ({"Content-Type": "text/plain"}, "Content-Type"),
        ({"Content-Type": "application/x-www-form-urlencoded"}, "Content-Type"),
        ({"Content-Type": "application/json; charset=latin-1"}, "Content-Type"),
        ({"Content-Type": ""}, "Content-Type"),
        ({"Content-Encoding": "br"}, "Content-Encoding"),
        ({"Content-Encoding": "gzip, gzip"}, "Content-Encoding"),
    ],
)
def test_wrong_media_type_or_encoding_is_415(api: Api, headers: dict[str, str], field: str) -> None:
    response = api.upload(ONETAG, headers=headers)

    assert response.status_code == 415, response.text
    assert response.json()["code"] == "unsupported_media_type"
    assert response.json()["field"] == field
    assert nothing_stored(api)


def test_missing_content_type_is_415(api: Api) -> None:
    response = api.client.post("/v1/sessions", content=ONETAG.read_bytes(), headers=ADMIN)

    assert response.status_code == 415
    assert "Content-Type is missing" in response.json()["detail"]
    assert nothing_stored(api)


@pytest.mark.parametrize(
    ("body", "reason"),
    [
        (b"this is not gzip at all", "not valid gzip"),
        (gzip.compress(ONETAG.read_bytes())[:-100], "ends too soon"),
        (gzip.compress(ONETAG.read_bytes()) + b"trailing garbage", "not valid gzip"),
        (b"", "ends too soon"),
        (gzip.compress(gzip.compress(ONETAG.read_bytes())), "compressed twice"),
    ],
    ids=["garbage", "truncated", "trailing-garbage", "empty", "double-gzip"],
)
def test_invalid_gzip_is_400(api: Api, body: bytes, reason: str) -> None:
    response = api.upload(body, headers={"Content-Encoding": "gzip"})

    assert response.status_code == 400, response.text
    assert response.json()["code"] == "invalid_gzip"
    assert reason in response.json()["detail"]
    assert nothing_stored(api)


def test_gzip_bomb_is_413(database_url: str) -> None:
    """Over HTTP; that inflation stops at the limit is shown in test_upload_chunks.py."""
    bomb = gzip.compress(bytes(50 * 2**20), compresslevel=9)  # 50 MiB of zeros in ~50 KiB
    assert len(bomb) < 100_000
    with running_api(database_url, max_session_bytes=2**20) as api:
        response = api.upload(bomb, headers={"Content-Encoding": "gzip"})

        assert response.status_code == 413, response.text
        assert response.json()["code"] == "payload_too_large"
        assert "after gunzip" in response.json()["detail"]
        assert nothing_stored(api)


def test_plain_body_over_the_session_limit_is_413(database_url: str) -> None:
    with running_api(database_url, max_session_bytes=10_000) as api:
        response = api.upload(ONETAG)  # 15.5 kB

        assert response.status_code == 413
        assert nothing_stored(api)


def test_body_over_the_raw_limit_is_413_by_length_and_by_stream(database_url: str) -> None:
    with running_api(database_url, max_upload_bytes=10_000) as api:
        by_length = api.upload(ONETAG)

        def chunks() -> Iterator[bytes]:  # no Content-Length: chunked transfer
            data = ONETAG.read_bytes()
            for start in range(0, len(data), 4096):
                yield data[start : start + 4096]

        by_stream = api.client.post("/v1/sessions", content=chunks(), headers={**ADMIN, **JSON})

        for response in (by_length, by_stream):
            assert response.status_code == 413, response.text
            assert response.json()["code"] == "payload_too_large"
            assert "10000 bytes" in response.json()["detail"]
        assert nothing_stored(api)
        # Under the raw limit once compressed: accepted.
        assert api.upload(ONETAG, compress=True).status_code == 202


def test_upload_needs_a_valid_key_before_anything_else(api: Api) -> None:
    no_key = api.client.post(
        "/v1/sessions", content=b"not json", headers={"Content-Type": "text/plain"}
    )
    wrong_key = api.upload(ONETAG, auth=bearer("im_deadbeef_nope"))

    for response in (no_key, wrong_key):
        assert response.status_code == 401
        assert response.headers["WWW-Authenticate"].startswith("Bearer")
    assert nothing_stored(api)


@pytest.mark.parametrize("key", ["x" * 201, "has space", "tab\there"])
def test_invalid_idempotency_key_is_422(api: Api, key: str) -> None:
    response = api.upload(ONETAG, idempotency_key=key)

    assert response.status_code == 422
    assert response.json()["field"] == "Idempotency-Key"
    assert nothing_stored(api)


# --------------------------------------------------------------------------- idempotency


def test_idempotent_retry_returns_the_first_result_and_stores_nothing(api: Api) -> None:
    first = api.upload(OCCAM, idempotency_key="occam-1")
    again = api.upload(OCCAM, idempotency_key="occam-1")
    again_gzip = api.upload(OCCAM, idempotency_key="occam-1", compress=True)

    assert first.status_code == again.status_code == again_gzip.status_code == 202
    assert again.json() == again_gzip.json() == first.json()
    assert again.headers["Idempotent-Replayed"] == "true"
    assert again.headers["Location"] == first.headers["Location"]
    assert [api.count(t) for t in (SessionRow, SessionUpload, MapRow, Job)] == [1, 1, 1, 1]


def test_same_key_with_another_body_is_409(api: Api) -> None:
    first = api.uploaded(ONETAG, idempotency_key="walk")

    response = api.upload(session_variant(ONETAG, map_id="other"), idempotency_key="walk")

    assert response.status_code == 409
    assert response.json()["code"] == "idempotency_conflict"
    assert "body differs" in response.json()["detail"]
    assert str(first["session_id"]) in response.json()["detail"]
    assert api.count(SessionRow) == 1


def test_keys_are_per_key_holder_and_uploads_without_a_key_are_distinct(api: Api) -> None:
    device = api.device()
    mine = api.uploaded(ONETAG, idempotency_key="same")
    theirs = api.uploaded(ONETAG, idempotency_key="same", auth=device)
    no_key_1 = api.uploaded(ONETAG)
    no_key_2 = api.uploaded(ONETAG)

    ids = {r["session_id"] for r in (mine, theirs, no_key_1, no_key_2)}
    assert len(ids) == 4
    assert api.count(SessionRow) == 4


def test_replay_after_the_map_was_deleted_is_409(api: Api) -> None:
    first = api.uploaded(ONETAG, idempotency_key="gone")
    assert api.client.delete(first["map_url"], headers=ADMIN).status_code == 204

    response = api.upload(ONETAG, idempotency_key="gone")

    assert response.status_code == 409
    assert "map has been deleted" in response.json()["detail"]
    assert api.count(SessionRow) == 1


def test_concurrent_duplicate_uploads_make_one_session(api: Api) -> None:
    barrier = threading.Barrier(4)
    results: list[tuple[int, dict[str, object]]] = []

    def upload() -> None:
        barrier.wait()
        response = api.upload(OCCAM, idempotency_key="race")
        results.append((response.status_code, response.json()))

    threads = [threading.Thread(target=upload) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()

    assert [status for status, _ in results] == [202] * 4
    assert len({json.dumps(body, sort_keys=True) for _, body in results}) == 1
    assert [api.count(t) for t in (SessionRow, SessionUpload, MapRow, Job)] == [1, 1, 1, 1]


# --------------------------------------------------------------------------- reading


def test_list_sessions_is_paginated_newest_first(api: Api) -> None:
    created = [api.uploaded(session_variant(ONETAG, map_id=f"map-{i}")) for i in range(3)]
    newest_first = [c["session_id"] for c in reversed(created)]

    page_1 = api.client.get("/v1/sessions?limit=2", headers=ADMIN).json()
    page_2 = api.client.get("/v1/sessions?limit=2&offset=2", headers=ADMIN).json()
    beyond = api.client.get("/v1/sessions?offset=10", headers=ADMIN).json()

    assert [s["id"] for s in page_1["data"]] == newest_first[:2]
    assert [s["id"] for s in page_2["data"]] == newest_first[2:]
    assert page_1["count"] == page_2["count"] == beyond["count"] == 3
    assert (page_1["limit"], page_1["offset"], page_2["offset"]) == (2, 0, 2)
    assert beyond["data"] == []
    assert page_1["data"][0]["map_name"] == "map-2"


@pytest.mark.parametrize(
    ("query", "field"), [("limit=0", "limit"), ("limit=201", "limit"), ("offset=-1", "offset")]
)
def test_list_sessions_bounds(api: Api, query: str, field: str) -> None:
    response = api.client.get(f"/v1/sessions?{query}", headers=ADMIN)

    assert response.status_code == 422
    assert response.json()["code"] == "validation_error"
    assert response.json()["field"] == field


def test_a_device_sees_only_its_own_sessions(api: Api) -> None:
    alice, bob = api.device(), api.device()
    hers = api.uploaded(ONETAG, auth=alice)
    api.uploaded(session_variant(ONETAG, map_id="bob"), auth=bob)

    listed = api.client.get("/v1/sessions", headers=alice).json()
    assert [s["id"] for s in listed["data"]] == [hers["session_id"]]
    assert listed["count"] == 1
    assert api.client.get("/v1/sessions", headers=ADMIN).json()["count"] == 2
    url = f"/v1/sessions/{hers['session_id']}"
    assert api.client.get(url, headers=alice).status_code == 200
    assert api.client.get(url + "/raw", headers=alice).status_code == 200
    assert api.client.get(url, headers=bob).status_code == 404
    assert api.client.get(url + "/raw", headers=bob).status_code == 404
    assert api.client.get(url, headers=ADMIN).status_code == 200


@pytest.mark.parametrize("session_id", ["999", "0", "-1", str(2**70)])
def test_unknown_session_is_404(api: Api, session_id: str) -> None:
    for path in (f"/v1/sessions/{session_id}", f"/v1/sessions/{session_id}/raw"):
        response = api.client.get(path, headers=ADMIN)
        assert response.status_code == 404, path
        assert response.json() == {
            "detail": f"session {session_id} not found",
            "code": "not_found",
            "field": None,
        }


def test_non_integer_session_id_is_422(api: Api) -> None:
    response = api.client.get("/v1/sessions/abc", headers=ADMIN)

    assert response.status_code == 422
    assert response.json()["field"] == "session_id"


def test_a_race_lost_at_the_unique_constraint_replays_the_winner(
    api: Api, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The duplicate is not visible to the check before the insert (it committed in between):
    the insert hits the unique constraint, and the winner's result comes back."""
    first = api.uploaded(ONETAG, idempotency_key="late")
    real_lookup = sessions.find_by_idempotency_key
    calls: list[str] = []

    def not_yet_visible(db_session: Session, uploaded_by: str, key: str) -> int | None:
        calls.append(key)
        return None if len(calls) <= 2 else real_lookup(db_session, uploaded_by, key)

    monkeypatch.setattr(sessions, "find_by_idempotency_key", not_yet_visible)

    response = api.upload(ONETAG, idempotency_key="late")

    assert response.status_code == 202, response.text
    assert response.json() == first
    assert len(calls) == 3  # the API's check, create_session's check, the lookup after the error
    assert [api.count(t) for t in (SessionRow, SessionUpload, MapRow, Job)] == [1, 1, 1, 1]

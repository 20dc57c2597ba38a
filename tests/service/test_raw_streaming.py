"""The raw download (``GET /v1/sessions/{id}/raw`` and the dashboard's) streamed from the
database a bounded piece at a time, never read whole: byte for byte the upload, gzip or
inflated, on SQLite and PostgreSQL."""

from __future__ import annotations

import gzip
from collections.abc import Iterator

import pytest
from admin_support import logged_in
from api_support import ADMIN, OCCAM, ONETAG, Api, running_api

from app.storage import sessions
from app.web import http

pytestmark = pytest.mark.db


@pytest.fixture
def api(database_url: str, monkeypatch: pytest.MonkeyPatch) -> Iterator[Api]:
    monkeypatch.setattr(http, "RAW_CHUNK_BYTES", 1000)  # many pieces for a small upload

    def whole_file(*_: object) -> bytes:
        raise AssertionError("the whole stored upload was read")

    monkeypatch.setattr(sessions, "raw_upload_gzip", whole_file)
    with running_api(database_url) as running:
        yield running


@pytest.mark.parametrize("compress", [True, False], ids=["sent gzip", "sent plain"])
def test_the_download_is_streamed_in_pieces_byte_for_byte(api: Api, compress: bool) -> None:
    raw = OCCAM.read_bytes()
    session_id = api.uploaded(raw, compress=compress)["session_id"]
    url = f"/v1/sessions/{session_id}/raw"
    with api.db.read() as db_session:
        stored_size = sessions.raw_upload_gzip_size(db_session, session_id)
    assert stored_size > 5 * 1000

    with api.client.stream("GET", url, headers={**ADMIN, "Accept-Encoding": "gzip"}) as answer:
        assert answer.headers["Content-Encoding"] == "gzip"
        assert int(answer.headers["Content-Length"]) == stored_size
        packed = b"".join(answer.iter_raw())
    assert gzip.decompress(packed) == raw

    with api.client.stream("GET", url, headers={**ADMIN, "Accept-Encoding": "identity"}) as answer:
        assert "Content-Encoding" not in answer.headers
        pieces = list(answer.iter_raw())
    assert b"".join(pieces) == raw
    assert len(pieces) > 1


def test_a_stored_upload_of_several_members_is_inflated_whole(api: Api) -> None:
    raw = ONETAG.read_bytes()
    body = gzip.compress(raw[:5000]) + gzip.compress(raw[5000:])
    session_id = api.uploaded(body, headers={"Content-Encoding": "gzip"})["session_id"]
    identity = api.client.get(
        f"/v1/sessions/{session_id}/raw", headers={**ADMIN, "Accept-Encoding": "identity"}
    )
    assert identity.content == raw


def test_slices_read_only_what_is_asked_and_a_missing_session_is_not_found(api: Api) -> None:
    session_id = api.uploaded(ONETAG, compress=True)["session_id"]
    with api.db.read() as db_session:
        size = sessions.raw_upload_gzip_size(db_session, session_id)
        whole = b"".join(
            sessions.raw_upload_gzip_slice(db_session, session_id, offset, 777)
            for offset in range(0, size, 777)
        )
        assert sessions.raw_upload_gzip_slice(db_session, session_id, size, 10) == b""
        for missing in (
            lambda: sessions.raw_upload_gzip_size(db_session, 999),
            lambda: sessions.raw_upload_gzip_slice(db_session, 999, 0, 10),
        ):
            with pytest.raises(sessions.SessionNotFound):
                missing()
    assert gzip.decompress(whole) == ONETAG.read_bytes()
    assert api.client.get("/v1/sessions/999/raw", headers=ADMIN).status_code == 404


def test_the_dashboards_download_is_streamed_too(api: Api) -> None:
    session_id = api.uploaded(OCCAM, compress=True)["session_id"]
    logged_in(api.client)
    answer = api.client.get(
        f"/admin/sessions/{session_id}/raw", headers={"Accept-Encoding": "identity"}
    )
    assert answer.status_code == 200
    assert answer.content == OCCAM.read_bytes()

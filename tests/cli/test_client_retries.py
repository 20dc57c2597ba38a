"""``Client.upload_session(retries=N)`` against a fake server (``httpx.MockTransport``): what is
retried (no answer, a 503), what is not (any other error), and that every try carries the same
Idempotency-Key. The same against a real server killed mid-upload is in tests/e2e/test_faults.py.
"""

from __future__ import annotations

import json
from collections.abc import Callable

import httpx
import pytest

from app.client import ApiError, Client

ACCEPTED = {"session_id": 1, "map_id": 1, "job_id": 1}


def fake_server(
    answers: list[Callable[[httpx.Request], httpx.Response]],
) -> tuple[httpx.MockTransport, list[httpx.Request]]:
    """A transport answering the n-th request with ``answers[n]`` (which may raise)."""
    seen: list[httpx.Request] = []

    def handle(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return answers[len(seen) - 1](request)

    return httpx.MockTransport(handle), seen


def dropped(request: httpx.Request) -> httpx.Response:
    raise httpx.RemoteProtocolError(
        "Server disconnected without sending a response.", request=request
    )


def refused(request: httpx.Request) -> httpx.Response:
    raise httpx.ConnectError("[Errno 111] Connection refused", request=request)


def status(code: int, body: dict[str, object]) -> Callable[[httpx.Request], httpx.Response]:
    return lambda _request: httpx.Response(code, json=body)


UNAVAILABLE = status(503, {"detail": "busy", "code": "database_unavailable", "field": None})


def upload(transport: httpx.MockTransport, **options: object) -> dict[str, object]:
    with Client("http://server", api_key="k", transport=transport) as client:
        return client.upload_session(b'{"map_id": "x"}', retry_wait_s=0, **options)  # type: ignore[arg-type]


def test_no_answer_and_503s_are_retried_with_one_idempotency_key() -> None:
    transport, seen = fake_server([dropped, refused, UNAVAILABLE, status(202, ACCEPTED)])

    assert upload(transport, retries=3) == ACCEPTED

    keys = {request.headers["Idempotency-Key"] for request in seen}
    assert len(seen) == 4
    assert len(keys) == 1
    assert keys.pop().startswith("upload-")


def test_a_given_idempotency_key_is_kept() -> None:
    transport, seen = fake_server([dropped, status(202, ACCEPTED)])

    upload(transport, retries=1, idempotency_key="walk-7")

    assert [r.headers["Idempotency-Key"] for r in seen] == ["walk-7", "walk-7"]


def test_the_last_failure_is_raised_when_retries_run_out() -> None:
    transport, seen = fake_server([dropped, dropped, dropped])

    with pytest.raises(httpx.RemoteProtocolError):
        upload(transport, retries=2)
    assert len(seen) == 3


def test_a_client_error_is_not_retried() -> None:
    invalid = status(422, {"detail": "pose_data: missing", "code": "invalid_session",
                           "field": "pose_data"})  # fmt: skip
    transport, seen = fake_server([invalid, status(202, ACCEPTED)])

    with pytest.raises(ApiError) as raised:
        upload(transport, retries=3)
    assert (raised.value.status_code, raised.value.field) == (422, "pose_data")
    assert len(seen) == 1


def test_without_retries_no_key_is_made_up_and_nothing_is_retried() -> None:
    transport, seen = fake_server([UNAVAILABLE])

    with pytest.raises(ApiError) as raised:
        upload(transport)
    assert raised.value.code == "database_unavailable"
    assert "Idempotency-Key" not in seen[0].headers


def test_the_picture_and_name_requests_are_what_the_server_expects() -> None:
    seen: list[httpx.Request] = []

    def handle(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        if request.url.path.endswith("/image") and request.method == "GET":
            return httpx.Response(404, json={"detail": "no picture", "code": "no_image"})
        return httpx.Response(200, json={"ok": True})

    with Client("http://server", api_key="k", transport=httpx.MockTransport(handle)) as client:
        assert client.put_session_image(7, b"\xff\xd8\xff\xd9") == {"ok": True}
        assert client.rename_map(3, "Lobby") == {"ok": True}
        with pytest.raises(ApiError) as info:
            client.map_image(3)
    assert info.value.status_code == 404
    assert info.value.code == "no_image"
    put, patch, get = seen
    assert (put.method, put.url.path, put.headers["Content-Type"]) == (
        "PUT",
        "/v1/sessions/7/image",
        "image/jpeg",
    )
    assert put.content == b"\xff\xd8\xff\xd9"
    assert (patch.method, patch.url.path) == ("PATCH", "/v1/maps/3")
    assert json.loads(patch.content) == {"display_name": "Lobby"}
    assert (get.method, get.url.path) == ("GET", "/v1/maps/3/image")

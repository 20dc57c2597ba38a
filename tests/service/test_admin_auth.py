"""The admin dashboard's login, its cookie, CSRF, the login throttle and the security headers.
SQLite only: none of it depends on the database beyond reading keys (the pages' tests run on
both)."""

from __future__ import annotations

import asyncio
import logging
import re
import shutil
import stat
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from admin_support import csrf_token, log_in, logged_in
from api_support import ADMIN, ADMIN_KEY, Api, bearer, running_api
from fastapi.routing import APIRoute
from fastapi.testclient import TestClient
from sqlalchemy import update

from app.admin import auth
from app.admin.auth import (
    LOGIN_COOKIE,
    LOGIN_FREE_FAILURES_PER_SOURCE,
    LOGIN_MAX_HOLD_S,
    LOGIN_WINDOW_S,
    LoginThrottle,
)
from app.admin.router import router as admin_router
from app.admin.signing import SECRET_FILE_NAME, Signer
from app.admin.templating import SECURITY_HEADERS
from app.main import create_app
from app.storage.orm import ApiKey, Role

pytestmark = pytest.mark.db


@pytest.fixture
def database_url(sqlite_template: Path, tmp_path: Path) -> str:
    """A fresh migrated SQLite database (this module's tests run on SQLite alone)."""
    path = tmp_path / "test.sqlite3"
    shutil.copyfile(sqlite_template, path)
    return f"sqlite:///{path}"


@pytest.fixture
def api(database_url: str, tmp_path: Path) -> Iterator[Api]:
    with running_api(database_url, data_dir=tmp_path) as running:
        yield running


# --------------------------------------------------------------------------- without a login


@pytest.mark.parametrize(
    ("path", "login_url"),
    [
        ("/admin", "/admin/login?next=/admin"),
        ("/admin/maps?page=2", "/admin/login?next=/admin/maps%3Fpage%3D2"),
        ("/admin/jobs/1", "/admin/login?next=/admin/jobs/1"),
        ("/admin/live/overview", "/admin/login?next=/admin/live/overview"),
        ("/admin/no/such/page", "/admin/login?next=/admin/no/such/page"),
    ],
)
def test_a_page_without_a_login_redirects_to_the_login(api: Api, path: str, login_url: str) -> None:
    response = api.client.get(path, follow_redirects=False)
    assert response.status_code == 303
    assert response.headers["location"] == login_url


def test_a_form_without_a_login_redirects_and_changes_nothing(api: Api) -> None:
    response = api.client.post("/admin/keys", data={"name": "x", "role": "admin"})
    assert response.status_code == 200  # followed to the login page
    assert "Log in" in response.text
    assert api.client.get("/v1/keys", headers=ADMIN).json()["count"] == 0


def test_a_forged_or_foreign_cookie_is_no_login(api: Api) -> None:
    forged = Signer(b"another secret, not the server's" * 2).sign(
        "login", {"sub": "env-admin", "kid": None, "nonce": "n"}, ttl_s=3600
    )
    for value in (forged, "garbage", forged.replace(".", "")):
        api.client.cookies.set(LOGIN_COOKIE, value, path="/admin")
        assert api.client.get("/admin", follow_redirects=False).status_code == 303


def test_the_login_page_is_public_and_says_what_key_it_wants(api: Api) -> None:
    page = api.client.get("/admin/login")
    assert page.status_code == 200
    assert 'for="key"' in page.text
    assert "Device keys cannot log in" in page.text


# --------------------------------------------------------------------------- logging in


def test_the_admin_key_logs_in_with_a_strict_http_only_cookie(api: Api) -> None:
    response = log_in(api.client, next_url="/admin/maps")
    assert response.status_code == 303
    assert response.headers["location"] == "/admin/maps"
    cookie = next(
        header
        for header in response.headers.get_list("set-cookie")
        if header.startswith(LOGIN_COOKIE + "=")
    )
    assert "HttpOnly" in cookie
    assert "SameSite=strict" in cookie
    assert "Path=/admin" in cookie
    assert "Secure" not in cookie  # plain http here; https sets Secure
    assert api.client.get("/admin").status_code == 200


def test_over_https_the_cookie_is_secure(database_url: str, tmp_path: Path) -> None:
    with running_api(database_url, data_dir=tmp_path) as api:
        client = TestClient(api.app, base_url="https://testserver")
        response = log_in(client)
        assert response.status_code == 303
        assert all("Secure" in h for h in response.headers.get_list("set-cookie"))


def test_an_admin_key_from_the_database_logs_in(api: Api) -> None:
    _, secret = api.create_key(Role.ADMIN, name="ops")
    assert log_in(api.client, secret).status_code == 303
    assert "Logged in with API key key:" in api.client.get("/admin").text


@pytest.mark.parametrize(
    ("key", "status", "message"),
    [
        ("im_nope_nope", 401, "unknown, revoked or expired"),
        ("not a key at all", 401, "unknown, revoked or expired"),
        ("", 422, "Enter an admin API key"),
    ],
)
def test_a_bad_key_is_refused_with_a_reason(api: Api, key: str, status: int, message: str) -> None:
    response = log_in(api.client, key)
    assert response.status_code == status
    assert message in response.text
    assert api.client.get("/admin", follow_redirects=False).status_code == 303


def test_a_device_key_cannot_log_in(api: Api) -> None:
    _, secret = api.create_key(Role.DEVICE)
    response = log_in(api.client, secret)
    assert response.status_code == 403
    assert "a device key cannot log in" in response.text
    assert LOGIN_COOKIE not in response.cookies


def dashboard_routes() -> list[tuple[str, str]]:
    """Every (method, path) of the dashboard but its static files, login and logout, with path
    parameters filled in with 1."""
    found: list[tuple[str, str]] = []

    def walk(router: Any, prefix: str) -> None:
        for route in router.routes:
            if hasattr(route, "original_router"):  # an included router (FastAPI ≥ 0.16x)
                walk(route.original_router, prefix + (route.include_context.prefix or ""))
            elif isinstance(route, APIRoute):
                for method in route.methods:
                    found.append((method, prefix + route.path))

    walk(admin_router, "")
    paths = [
        (method, re.sub(r"\{[a-z_]+(:path)?\}", "1", path))
        for method, path in found
        if not path.startswith(("/admin/static", "/admin/login", "/admin/logout"))
    ]
    assert len(paths) >= 30
    return sorted(paths)


def test_a_device_key_reaches_no_dashboard_page_or_form(api: Api) -> None:
    """Whichever way a device key is offered — as a bearer token, or as the login cookie — every
    page and form of the dashboard answers with the way to the login page, and nothing changes."""
    _, device = api.create_key(Role.DEVICE)
    before = api.client.get("/v1/keys", headers=ADMIN).json()

    as_bearer = TestClient(api.app, headers=bearer(device))
    as_cookie = TestClient(api.app, cookies={LOGIN_COOKIE: device})
    for method, path in dashboard_routes():
        for client in (as_bearer, as_cookie):
            response = client.request(method, path, follow_redirects=False)
            assert response.status_code == 303, (method, path)
            assert response.headers["location"].startswith("/admin/login"), (method, path)
    assert api.client.get("/v1/keys", headers=ADMIN).json() == before


def test_an_expired_key_cannot_log_in(api: Api) -> None:
    _, secret = api.create_key(Role.ADMIN, expires_at=datetime.now(UTC) + timedelta(seconds=1))
    with api.db.transaction() as db_session:
        db_session.execute(
            update(ApiKey).values(expires_at=datetime.now(UTC) - timedelta(seconds=1))
        )
    assert log_in(api.client, secret).status_code == 401


def test_next_may_only_lead_into_the_dashboard(api: Api) -> None:
    for evil in ("https://evil.example/", "//evil.example/admin", "/v1/keys", "/admin\\@evil"):
        response = log_in(api.client, next_url=evil)
        assert response.headers["location"] == "/admin", evil


def test_the_login_form_without_its_token_is_refused(api: Api) -> None:
    response = api.client.post("/admin/login", data={"key": ADMIN_KEY, "next": "/admin"})
    assert response.status_code == 403
    assert "security token" in response.text


@pytest.fixture
def holds(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """The holds the login throttle asks for (recorded, not slept: no test waits for them)."""
    asked: list[float] = []

    async def recorded_sleep(seconds: float) -> None:
        asked.append(seconds)

    monkeypatch.setattr(auth.asyncio, "sleep", recorded_sleep)
    return asked


def test_wrong_keys_from_anyone_never_lock_the_right_key_out(api: Api, holds: list[float]) -> None:
    """Issue 28, finding 2: ten wrong keys from anyone locked the right admin key out for a
    minute (429). Now guessing is slowed (each attempt held before its key is checked) and the
    right key logs in all the same: the server's admin key and a stored one."""
    for k in range(3 * LOGIN_FREE_FAILURES_PER_SOURCE):
        assert log_in(api.client, f"wrong-key-{k}").status_code == 401
        assert log_in(api.client, f"im_0badc0de_guess{k}").status_code == 401
    assert holds  # the guesses were slowed …
    assert max(holds) == LOGIN_MAX_HOLD_S  # … up to the longest hold
    holds.clear()
    assert log_in(api.client).status_code == 303  # INVISIBLE_MAP_ADMIN_KEY
    assert holds == [LOGIN_MAX_HOLD_S]  # held like any attempt from that source, not refused
    _, secret = api.create_key(Role.ADMIN, name="ops")
    assert log_in(api.client, secret).status_code == 303
    assert log_in(api.client, "x").status_code == 401  # a wrong key is still only wrong


def test_guessing_is_slowed_per_source_and_in_all() -> None:
    clock = [0.0]
    throttle = LoginThrottle(
        free_per_source=3, free_overall=8, first_hold_s=0.5, max_hold_s=4.0, clock=lambda: clock[0]
    )
    for _ in range(3):
        assert throttle.hold_s("203.0.113.7") == 0.0
        throttle.failed("203.0.113.7")
    steps = []
    for _ in range(5):
        steps.append(throttle.hold_s("203.0.113.7"))
        throttle.failed("203.0.113.7")
    assert steps == [0.5, 1.0, 2.0, 4.0, 4.0]  # doubling from the first hold, up to the longest
    assert throttle.hold_s("198.51.100.1") == 0.5  # another source: only the overall count, 8
    for k in range(20):
        throttle.failed(f"198.51.100.{k}")  # one failure each from many sources
    assert throttle.hold_s("192.0.2.1") == 2.0  # 28 in all: 20 beyond the free 8, 2 doublings
    clock[0] += LOGIN_WINDOW_S + 0.1  # a minute later, all is forgotten
    assert throttle.hold_s("203.0.113.7") == 0.0
    assert throttle.hold_s("192.0.2.1") == 0.0


def test_the_throttle_remembers_a_bounded_number_of_sources() -> None:
    throttle = LoginThrottle(max_sources=100, max_failures=50, free_per_source=1)
    for k in range(10_000):
        throttle.failed(f"2001:db8::{k:x}")
    assert len(throttle._by_source) == 100
    assert len(throttle._all) == 50
    assert throttle.hold_s("2001:db8::270f") > 0  # the most recent is remembered


def test_forwarded_headers_from_an_untrusted_peer_do_not_change_the_source(
    api: Api, holds: list[float]
) -> None:
    """Without INVISIBLE_MAP_TRUSTED_PROXIES, X-Forwarded-For is not believed: a guesser
    cannot spread its attempts over made-up addresses."""
    for k in range(LOGIN_FREE_FAILURES_PER_SOURCE + 5):
        form = api.client.get("/admin/login")
        token = re.search(r'name="form_token" value="([^"]+)"', form.text)
        assert token is not None
        answer = api.client.post(
            "/admin/login",
            data={"form_token": token.group(1), "key": "im_0badc0de_wrong", "next": "/admin"},
            headers={"X-Forwarded-For": f"203.0.113.{k}"},
        )
        assert answer.status_code == 401
    assert len(holds) == 5  # the 11th to the 15th attempt were held: one source


def test_a_client_that_disconnects_while_posting_the_login_is_one_quiet_line(
    api: Api, caplog: pytest.LogCaptureFixture
) -> None:
    """Issue 28, finding 5: it was logged as an unhandled error with a traceback."""
    assert api.client.get("/admin/login").status_code == 200
    messages: list[dict[str, Any]] = [
        {"type": "http.request", "body": b"form_token=abc&key=im_", "more_body": True},
        {"type": "http.disconnect"},
    ]
    sent: list[dict[str, Any]] = []

    async def receive() -> dict[str, Any]:
        return messages.pop(0) if messages else {"type": "http.disconnect"}

    async def send(message: dict[str, Any]) -> None:
        sent.append(message)

    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "POST",
        "scheme": "http",
        "path": "/admin/login",
        "raw_path": b"/admin/login",
        "query_string": b"",
        "root_path": "",
        "headers": [
            (b"host", b"testserver"),
            (b"content-type", b"application/x-www-form-urlencoded"),
            (b"content-length", b"100"),
        ],
        "client": ("203.0.113.9", 50000),
        "server": ("testserver", 80),
        "state": {},
    }
    with caplog.at_level(logging.INFO):
        asyncio.run(api.app(scope, receive, send))
    assert not [record for record in caplog.records if record.exc_info]
    problems = [record for record in caplog.records if record.levelno >= logging.WARNING]
    assert problems == []
    said = [
        record.getMessage() for record in caplog.records if "disconnected" in record.getMessage()
    ]
    assert said == ["client disconnected while sending POST /admin/login"]


# --------------------------------------------------------------------------- while logged in


def test_revoking_the_key_ends_its_dashboard_login(api: Api) -> None:
    key_id, secret = api.create_key(Role.ADMIN, name="ops")
    logged_in(api.client, secret)
    token = csrf_token(api.client, "/admin/keys")
    response = api.client.post(
        f"/admin/keys/{key_id}/revoke", data={"csrf_token": token}, follow_redirects=False
    )
    assert response.status_code == 303
    assert api.client.get("/admin/keys", follow_redirects=False).status_code == 303


def test_a_changed_environment_admin_key_ends_its_logins(database_url: str, tmp_path: Path) -> None:
    with running_api(database_url, data_dir=tmp_path) as api:
        logged_in(api.client)
        cookie = api.client.cookies.get(LOGIN_COOKIE)
    changed = api.settings.model_copy(update={"admin_key": "another-admin-key-0123456789"})
    with TestClient(create_app(changed)) as client:
        client.cookies.set(LOGIN_COOKIE, cookie or "", path="/admin")
        assert client.get("/admin", follow_redirects=False).status_code == 303


def test_logout_ends_the_login(api: Api) -> None:
    logged_in(api.client)
    token = csrf_token(api.client)
    response = api.client.post("/admin/logout", data={"csrf_token": token})
    assert response.status_code == 200
    assert "You are logged out." in response.text
    assert api.client.get("/admin", follow_redirects=False).status_code == 303


@pytest.mark.parametrize("token", [None, "", "wrong-token"])
@pytest.mark.parametrize(
    "action",
    ["/admin/keys", "/admin/logout", "/admin/jobs/1/cancel", "/admin/maps/1/rebuild"],
)
def test_a_form_without_the_right_csrf_token_is_refused(
    api: Api, action: str, token: str | None
) -> None:
    logged_in(api.client)
    data = {"name": "forged", "role": "admin"}
    if token is not None:
        data["csrf_token"] = token
    response = api.client.post(action, data=data, follow_redirects=False)
    assert response.status_code == 403
    assert "security token is missing or wrong" in response.text
    assert api.client.get("/admin", follow_redirects=False).status_code == 200  # still logged in


def test_the_csrf_token_of_another_login_is_refused(api: Api) -> None:
    logged_in(api.client)
    token = csrf_token(api.client)
    other = TestClient(api.app)
    logged_in(other)
    response = other.post("/admin/keys", data={"csrf_token": token, "name": "x", "role": "admin"})
    assert response.status_code == 403


# --------------------------------------------------------------------------- headers, secret


def test_every_dashboard_answer_has_the_security_headers(api: Api) -> None:
    answers = [api.client.get("/admin/login"), api.client.get("/admin", follow_redirects=False)]
    logged_in(api.client)
    answers += [api.client.get("/admin"), api.client.get("/admin/maps/12345")]
    answers.append(api.client.get("/admin/static/admin.css"))
    for answer in answers:
        for name, value in SECURITY_HEADERS.items():
            assert answer.headers[name] == value
        policy = answer.headers["content-security-policy"]
        assert "http" not in policy  # no other origin
        assert "frame-ancestors 'none'" in policy


def test_the_signing_secret_is_kept_in_the_data_dir_for_every_process(
    database_url: str, tmp_path: Path
) -> None:
    with running_api(database_url, data_dir=tmp_path) as first:
        logged_in(first.client)
        cookie = first.client.cookies.get(LOGIN_COOKIE)
    secret_file = tmp_path / SECRET_FILE_NAME
    assert stat.S_IMODE(secret_file.stat().st_mode) == 0o600
    with running_api(database_url, data_dir=tmp_path) as second:  # another API process
        second.client.cookies.set(LOGIN_COOKIE, cookie or "", path="/admin")
        assert second.client.get("/admin", follow_redirects=False).status_code == 200


def test_a_configured_session_secret_is_used_instead_of_the_file(
    database_url: str, tmp_path: Path
) -> None:
    with running_api(database_url, data_dir=tmp_path, session_secret="s" * 40) as api:
        logged_in(api.client)
    assert not (tmp_path / SECRET_FILE_NAME).exists()


def test_the_dashboard_is_not_in_the_openapi_document(api: Api) -> None:
    paths = api.client.get("/openapi.json").json()["paths"]
    assert not [path for path in paths if path.startswith("/admin")]

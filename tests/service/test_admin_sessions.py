"""Dashboard logins kept on the server (``admin_login``): a cookie captured before logout, with
its CSRF token, opens nothing after it; revoking the key that opened a login ends it; "end all
dashboard sessions" ends every one; a changed ``INVISIBLE_MAP_ADMIN_KEY`` ends its logins. On
SQLite and PostgreSQL."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from admin_support import csrf_token, logged_in
from api_support import Api, running_api
from fastapi.testclient import TestClient

from app.admin.auth import LOGIN_COOKIE
from app.main import create_app
from app.storage.orm import AdminLogin, ApiKey, Role

pytestmark = pytest.mark.db


@pytest.fixture
def api(database_url: str, tmp_path: Path) -> Iterator[Api]:
    with running_api(database_url, data_dir=tmp_path) as running:
        yield running


def copy_of(api: Api, client: TestClient) -> TestClient:
    """Another browser with the same login cookie (a captured cookie)."""
    other = TestClient(api.app)
    other.cookies.set(LOGIN_COOKIE, client.cookies.get(LOGIN_COOKIE) or "", path="/admin")
    return other


def test_a_cookie_captured_before_logout_opens_nothing_after_it(api: Api) -> None:
    logged_in(api.client)
    token = csrf_token(api.client, "/admin/keys")
    thief = copy_of(api, api.client)
    assert thief.get("/admin", follow_redirects=False).status_code == 200  # the same login
    assert api.count(AdminLogin) == 1

    response = api.client.post("/admin/logout", data={"csrf_token": token})
    assert "You are logged out." in response.text
    assert api.count(AdminLogin) == 0

    assert thief.get("/admin", follow_redirects=False).status_code == 303
    keys_before = api.count(ApiKey)
    forged = thief.post(
        "/admin/keys",
        data={"csrf_token": token, "name": "after logout", "role": "admin"},
        follow_redirects=False,
    )
    assert forged.status_code == 303  # to the login page
    assert api.count(ApiKey) == keys_before


def test_revoking_a_key_ends_the_logins_it_opened_and_only_those(api: Api) -> None:
    key_id, secret = api.create_key(Role.ADMIN, name="ops")
    ops = TestClient(api.app)
    logged_in(ops, secret)
    logged_in(api.client)  # the environment's admin key
    assert api.count(AdminLogin) == 2

    token = csrf_token(api.client, "/admin/keys")
    revoked = api.client.post(
        f"/admin/keys/{key_id}/revoke", data={"csrf_token": token}, follow_redirects=False
    )
    assert revoked.status_code == 303
    assert api.count(AdminLogin) == 1
    assert ops.get("/admin", follow_redirects=False).status_code == 303
    assert api.client.get("/admin", follow_redirects=False).status_code == 200


def test_end_all_dashboard_sessions(api: Api) -> None:
    _, secret = api.create_key(Role.ADMIN, name="ops")
    ops = TestClient(api.app)
    logged_in(ops, secret)
    logged_in(api.client)
    page = api.client.get("/admin/keys")
    assert "2 dashboard sessions open" in page.text
    assert "End all dashboard sessions" in page.text

    token = csrf_token(api.client, "/admin/keys")
    ended = api.client.post("/admin/logins/end-all", data={"csrf_token": token})
    assert "Every dashboard session is ended (2)" in ended.text
    assert api.count(AdminLogin) == 0
    for client in (ops, api.client):
        assert client.get("/admin", follow_redirects=False).status_code == 303
    logged_in(api.client)  # and one can log in again
    assert api.client.get("/admin").status_code == 200


def test_end_all_needs_the_csrf_token(api: Api) -> None:
    logged_in(api.client)
    refused = api.client.post("/admin/logins/end-all", data={"csrf_token": "wrong"})
    assert refused.status_code == 403
    assert api.count(AdminLogin) == 1


def test_a_changed_environment_admin_key_ends_its_logins(api: Api) -> None:
    logged_in(api.client)
    changed = api.settings.model_copy(update={"admin_key": "another-admin-key-0123456789"})
    with TestClient(create_app(changed)) as client:
        client.cookies.set(LOGIN_COOKIE, api.client.cookies.get(LOGIN_COOKIE) or "", path="/admin")
        assert client.get("/admin", follow_redirects=False).status_code == 303

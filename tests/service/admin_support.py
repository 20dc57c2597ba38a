"""Helpers of the admin dashboard's service tests: logging in through the login form, and the
CSRF token of a page, with the API's TestClient."""

from __future__ import annotations

import re

import httpx2
from api_support import ADMIN_KEY
from fastapi.testclient import TestClient

_FORM_TOKEN = re.compile(r'name="form_token" value="([^"]+)"')
_CSRF_TOKEN = re.compile(r'name="csrf_token" value="([^"]+)"')


def log_in(
    client: TestClient, key: str = ADMIN_KEY, *, next_url: str = "/admin"
) -> httpx2.Response:
    """Post the login form (with its token) as a browser would; the answer, not followed."""
    form = client.get("/admin/login")
    assert form.status_code == 200, form.text
    match = _FORM_TOKEN.search(form.text)
    assert match is not None
    return client.post(
        "/admin/login",
        data={"form_token": match.group(1), "key": key, "next": next_url},
        follow_redirects=False,
    )


def logged_in(client: TestClient, key: str = ADMIN_KEY) -> None:
    response = log_in(client, key)
    assert response.status_code == 303, response.text


def csrf_token(client: TestClient, path: str = "/admin") -> str:
    """The CSRF token the forms of ``path`` carry."""
    page = client.get(path)
    assert page.status_code == 200, page.text
    match = _CSRF_TOKEN.search(page.text)
    assert match is not None
    return match.group(1)


def assert_error_pages(client: TestClient, cases: list[tuple[str, int, str]]) -> None:
    """Each (path, status, message): a GET answers that status with an HTML page saying it."""
    for path, status, message in cases:
        response = client.get(path)
        assert response.status_code == status, path
        assert response.headers["content-type"].startswith("text/html"), path
        assert message in response.text, path

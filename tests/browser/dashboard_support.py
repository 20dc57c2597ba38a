"""Helpers of the browser tests (a module of its own: test modules cannot import a conftest)."""

from __future__ import annotations

from app.cli.server_process import ServerProcess

#: How long a browser test waits for something to appear, ms.
TIMEOUT_MS = 30_000


def log_in(page, server: ServerProcess) -> None:  # type: ignore[no-untyped-def]
    """Log ``page`` in to the dashboard with the server's admin key, through the login form."""
    page.goto("/admin/login")
    page.get_by_label("Admin API key").fill(server.admin_key)
    page.get_by_role("button", name="Log in").click()
    page.wait_for_url(server.url + "/admin")

"""``/docs`` and ``/redoc`` in a real browser: every script, style and icon comes from the server
itself (no CDN), and the documentation renders (the API's title and its endpoints)."""

from __future__ import annotations

import pytest
from dashboard_support import TIMEOUT_MS


@pytest.fixture
def fresh_page(browser, server):  # type: ignore[no-untyped-def]
    """A page with no login, recording every request it makes."""
    context = browser.new_context(base_url=server.url)
    context.set_default_timeout(TIMEOUT_MS)
    tab = context.new_page()
    tab.requested = []
    tab.on("request", lambda request: tab.requested.append(request.url))
    yield tab
    context.close()


def _elsewhere(urls: list[str], origin: str) -> list[str]:
    return [u for u in urls if not u.startswith((origin, "data:", "blob:"))]


def test_swagger_ui_loads_its_scripts_from_the_server_and_shows_the_endpoints(fresh_page, server):
    fresh_page.goto("/docs")
    fresh_page.locator(".swagger-ui .info .title").wait_for()
    assert "Invisible Map" in fresh_page.locator(".swagger-ui .info .title").inner_text()
    fresh_page.get_by_text("/v1/sessions", exact=True).first.wait_for()
    scripts = [u for u in fresh_page.requested if u.endswith(".js")]
    assert any(u.endswith("/docs-assets/swagger-ui-bundle.js") for u in scripts)
    assert _elsewhere(fresh_page.requested, server.url) == []


def test_redoc_loads_its_script_from_the_server_and_shows_the_api(fresh_page, server):
    fresh_page.goto("/redoc")
    heading = fresh_page.locator("h1").first
    heading.wait_for()
    assert "Invisible Map" in heading.inner_text()
    assert any(u.endswith("/docs-assets/redoc.standalone.js") for u in fresh_page.requested)
    assert _elsewhere(fresh_page.requested, server.url) == []

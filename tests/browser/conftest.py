"""Fixtures of the browser tests: one server (``invisible-map serve`` on SQLite), one worker that
tests switch on and off, one headless Chromium logged in to the dashboard — each per module.

Chromium is Debian's (``/usr/bin/chromium``, installed by ``.ci/run``), driven by Playwright;
``playwright install`` is never run. Where it is missing the tests are skipped with the reason,
unless ``INVISIBLE_MAP_REQUIRE_BROWSER=1`` (CI sets it), which makes that an error.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from dashboard_support import TIMEOUT_MS, log_in

from app.cli.server_process import ServerProcess, WorkerProcess
from app.client import Client
from tests.skip_report import CHROMIUM, browser_unavailable_reason

REQUIRE_BROWSER = os.environ.get("INVISIBLE_MAP_REQUIRE_BROWSER") == "1"


@pytest.fixture(scope="module")
def browser():  # type: ignore[no-untyped-def]
    reason = browser_unavailable_reason()
    if reason is not None:
        if REQUIRE_BROWSER:
            pytest.fail(f"INVISIBLE_MAP_REQUIRE_BROWSER=1 but {reason}")
        pytest.skip(f"browser tests skipped: {reason}")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=str(CHROMIUM))
        yield chromium
        chromium.close()


@pytest.fixture(scope="module")
def data_path(tmp_path_factory: pytest.TempPathFactory, sqlite_template: Path) -> Path:
    """A data directory with a fresh migrated SQLite database."""
    path = tmp_path_factory.mktemp("dashboard")
    shutil.copyfile(sqlite_template, path / "test.sqlite3")
    return path


@pytest.fixture(scope="module")
def server(data_path: Path) -> Iterator[ServerProcess]:
    """The API and dashboard, with no worker of its own (see :func:`worker`)."""
    with ServerProcess(
        f"sqlite:///{data_path / 'test.sqlite3'}",
        workers=0,
        env={"INVISIBLE_MAP_DATA_DIR": str(data_path)},
        log_path=data_path / "server.log",
    ) as process:
        yield process


class WorkerSwitch:
    """One worker process that a test can turn on (to see jobs run) or off (to see them wait)."""

    def __init__(self, database_url: str, data_path: Path) -> None:
        self.database_url = database_url
        self.data_path = data_path
        self.process: WorkerProcess | None = None

    def on(self) -> None:
        if self.process is None:
            self.process = WorkerProcess(
                self.database_url,
                env={"INVISIBLE_MAP_DATA_DIR": str(self.data_path)},
                log_path=self.data_path / "worker.log",
            )
            self.process.start()

    def off(self) -> None:
        if self.process is not None:
            self.process.stop()
            self.process = None


@pytest.fixture(scope="module")
def worker(data_path: Path, server: ServerProcess) -> Iterator[WorkerSwitch]:  # noqa: ARG001
    switch = WorkerSwitch(f"sqlite:///{data_path / 'test.sqlite3'}", data_path)
    yield switch
    switch.off()


@pytest.fixture(scope="module")
def api(server: ServerProcess) -> Iterator[Client]:
    """The REST API with the server's admin key."""
    with Client(server.url, api_key=server.admin_key) as client:
        yield client


@pytest.fixture(scope="module")
def page(browser, server: ServerProcess):  # type: ignore[no-untyped-def]
    """A page logged in to the dashboard."""
    context = browser.new_context(base_url=server.url, viewport={"width": 1280, "height": 900})
    context.set_default_timeout(TIMEOUT_MS)
    tab = context.new_page()
    log_in(tab, server)
    yield tab
    context.close()

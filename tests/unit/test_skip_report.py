"""What the suite says up front it will skip (``tests/skip_report.py``, printed by scripts/test
before pytest starts): each missing part named, with how to install it."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests import skip_report


def test_a_missing_chromium_is_said_with_how_to_install_it(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(skip_report, "CHROMIUM", tmp_path / "chromium")
    monkeypatch.setattr(skip_report, "postgres_unavailable_reason", lambda: None)
    lines = skip_report.report()
    assert lines[0] == "will be skipped on this machine (see the end of the run for each test):"
    assert f"  - browser tests: {tmp_path / 'chromium'} is missing (apt-get install chromium)" in (
        lines
    )


def test_an_unreachable_postgresql_is_said_with_how_to_start_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:9/postgres")
    monkeypatch.setattr(
        "tests.conftest.POSTGRES_ADMIN_URL", "postgresql+psycopg://postgres@127.0.0.1:9/postgres"
    )
    (line,) = [line for line in skip_report.report() if "PostgreSQL half" in line]
    assert "unreachable" in line
    assert "apt-get install postgresql" in line


def test_nothing_missing_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in (
        "postgres_unavailable_reason",
        "browser_unavailable_reason",
        "jemalloc_unavailable_reason",
        "fault_tests_unavailable_reason",
    ):
        monkeypatch.setattr(skip_report, name, lambda: None)
    assert skip_report.report() == [
        "nothing will be skipped: PostgreSQL, Chromium, jemalloc and pg_ctl found"
    ]

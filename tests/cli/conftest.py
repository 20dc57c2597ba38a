"""Fixtures of the command-line tests."""

from __future__ import annotations

import os
from pathlib import Path

import pytest


@pytest.fixture
def env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> pytest.MonkeyPatch:
    """No Invisible Map setting from the outer environment; a private data directory."""
    for name in list(os.environ):
        if name == "DATABASE_URL" or name.startswith("INVISIBLE_MAP_"):
            monkeypatch.delenv(name)
    monkeypatch.setenv("INVISIBLE_MAP_DATA_DIR", str(tmp_path / "var"))
    return monkeypatch

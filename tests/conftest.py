"""Shared test helpers: where the repository and its shipped data are."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA_DIR = REPO_ROOT / "data"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The project root (where ``pyproject.toml`` and ``data/`` are)."""
    return REPO_ROOT


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """``data/``: the real sessions and ground truth shipped with the project."""
    return DATA_DIR

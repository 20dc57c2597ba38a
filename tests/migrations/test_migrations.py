"""The migrations in ``migrations/``: up, down, up again, and in step with the ORM models."""

from __future__ import annotations

import pytest
from alembic import command
from alembic.util.exc import CommandError
from sqlalchemy import inspect

from app.storage.db import Database
from app.storage.migrate import alembic_config, current_revision, head_revision, is_current
from app.storage.orm import Base

pytestmark = pytest.mark.db


@pytest.fixture
def empty_db(request, tmp_path):
    """An empty database (no migrations applied) on each backend."""
    backend = request.param
    if backend == "sqlite":
        url = f"sqlite:///{tmp_path / 'empty.sqlite3'}"
        database = Database(url)
        yield database
        database.dispose()
        return
    url = request.getfixturevalue("database_url_for_postgres_empty")
    database = Database(url)
    yield database
    database.dispose()


@pytest.fixture
def database_url_for_postgres_empty(postgres_url):
    """A PostgreSQL database emptied of the template's migration."""
    database = Database(postgres_url)
    command.downgrade(alembic_config(postgres_url), "base")
    database.dispose()
    return postgres_url


BACKENDS = pytest.mark.parametrize("empty_db", ["sqlite", "postgresql"], indirect=True)


@BACKENDS
def test_upgrade_downgrade_upgrade_and_check(empty_db):
    url = empty_db.url.render_as_string(hide_password=False)
    config = alembic_config(url)
    assert current_revision(empty_db) is None
    assert not is_current(empty_db)

    command.upgrade(config, "head")
    assert current_revision(empty_db) == head_revision()
    tables = set(inspect(empty_db.engine).get_table_names())
    assert set(Base.metadata.tables) <= tables

    command.downgrade(config, "base")
    assert set(inspect(empty_db.engine).get_table_names()) <= {"alembic_version"}

    command.upgrade(config, "head")
    assert is_current(empty_db)
    command.check(config)  # raises if the models and the migrations disagree


@BACKENDS
def test_check_fails_when_the_schema_lags_the_models(empty_db):
    config = alembic_config(empty_db.url.render_as_string(hide_password=False))
    with pytest.raises(CommandError, match="Target database is not up to date"):
        command.check(config)

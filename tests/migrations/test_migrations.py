"""The migrations in ``migrations/``: up, down, up again, and in step with the ORM models."""

from __future__ import annotations

import pytest
from alembic import command
from alembic.util.exc import CommandError
from sqlalchemy import inspect, text

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


FIRST_REVISION = "255ed7c85f58"


@BACKENDS
def test_rows_survive_the_upgrade_and_ids_are_never_reused(empty_db):
    url = empty_db.url.render_as_string(hide_password=False)
    config = alembic_config(url)
    command.upgrade(config, FIRST_REVISION)
    now = "2026-11-22 00:00:00"
    with empty_db.engine.begin() as connection:
        session_id = connection.execute(
            text(
                "INSERT INTO session (map_name, created_at, uploaded_by, raw_sha256,"
                " raw_size_bytes, stored_size_bytes, pose_count, detection_count, tag_count,"
                " poi_count, duration_s, path_length_m, tag_ids, warnings)"
                f" VALUES ('m', '{now}', 'env-admin', 'x', 1, 1, 1, 0, 0, 0, 0, 0, '[]', '[]')"
                " RETURNING id"
            )
        ).scalar_one()
        map_ids = [
            connection.execute(
                text(
                    "INSERT INTO map (name, session_id, created_at)"
                    f" VALUES ('m', {session_id}, '{now}') RETURNING id"
                )
            ).scalar_one()
            for _ in range(2)
        ]
        connection.execute(
            text(
                "INSERT INTO job (kind, state, map_id, session_id, params, priority, attempts,"
                " max_attempts, run_after, lease_token, cancel_requested, progress, log_tail,"
                f" created_at, updated_at) VALUES ('build_map', 'queued', {map_ids[0]},"
                f" {session_id}, '{{}}', 0, 0, 3, '{now}', 0, false, 0, '', '{now}', '{now}')"
            )
        )

    command.upgrade(config, "head")

    with empty_db.engine.begin() as connection:
        assert connection.execute(text("SELECT count(*) FROM map")).scalar_one() == 2
        assert connection.execute(text("SELECT count(*) FROM job")).scalar_one() == 1
        connection.execute(text(f"DELETE FROM map WHERE id = {map_ids[1]}"))
        new_id = connection.execute(
            text(
                "INSERT INTO map (name, session_id, created_at)"
                f" VALUES ('again', {session_id}, '{now}') RETURNING id"
            )
        ).scalar_one()
    assert new_id > map_ids[1], "a deleted map's id was given to a new map"

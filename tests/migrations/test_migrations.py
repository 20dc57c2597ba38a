"""The migrations in ``migrations/``: up, down, up again, and in step with the ORM models."""

from __future__ import annotations

import gzip
import json

import pytest
from alembic import command
from alembic.util.exc import CommandError
from sqlalchemy import inspect, text

from app.storage import blobs, maps
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


BEFORE_BLOBS = "a1bdea7a7cb1"


@BACKENDS
def test_versions_stored_before_the_blobs_keep_working_and_blobs_go_back_on_downgrade(empty_db):
    """Upgrading past the blob table leaves earlier versions' bytes in their rows (read as
    before); a downgrade copies the blobs of later versions back into their rows."""
    url = empty_db.url.render_as_string(hide_password=False)
    config = alembic_config(url)
    command.upgrade(config, BEFORE_BLOBS)
    now = "2026-11-25 00:00:00"
    document = {"tags": [], "rejections": [], "format": "old"}
    packed = gzip.compress(json.dumps(document).encode())
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
        map_id = connection.execute(
            text(
                f"INSERT INTO map (name, session_id, created_at) VALUES ('m', {session_id},"
                f" '{now}') RETURNING id"
            )
        ).scalar_one()
        connection.execute(
            text(
                "INSERT INTO map_version (map_id, number, created_at, params, statistics, metrics,"
                " tag_count, detections_used, detections_rejected, rejections, warnings,"
                " map_json_gzip, plot_png, content_sha256) VALUES (:map_id, 1, :now, '{}', '{}',"
                " '{}', 0, 0, 0, '[]', '[]', :packed, :png, 'c')"
            ),
            {"map_id": map_id, "now": now, "packed": packed, "png": b"old plot"},
        )

    command.upgrade(config, "head")
    with empty_db.transaction() as tx:
        assert maps.map_document(tx, map_id, 1) == document
        assert maps.plot_png(tx, map_id, 1) == b"old plot"
        new_document = {"tags": [], "rejections": [], "format": "new"}
        tx.execute(
            text(
                "INSERT INTO map_version (map_id, number, created_at, params, statistics, metrics,"
                " tag_count, detections_used, detections_rejected, rejections, warnings,"
                " content_sha256, map_json_sha256, plot_png_sha256) VALUES (:map_id, 2, :now,"
                " '{}', '{}', '{}', 0, 0, 0, '[]', '[]', 'c', :doc, :png)"
            ),
            {
                "map_id": map_id,
                "now": now,
                "doc": blobs.put_blob_in(tx, gzip.compress(json.dumps(new_document).encode())),
                "png": blobs.put_blob_in(tx, b"new plot"),
            },
        )
    with empty_db.read() as tx:
        assert maps.map_document(tx, map_id, 2) == new_document
        assert maps.plot_png(tx, map_id, 2) == b"new plot"

    command.downgrade(config, BEFORE_BLOBS)
    with empty_db.engine.begin() as connection:
        rows = connection.execute(
            text("SELECT number, map_json_gzip, plot_png FROM map_version ORDER BY number")
        ).all()
    assert [(n, json.loads(gzip.decompress(d))["format"], bytes(p)) for n, d, p in rows] == [
        (1, "old", b"old plot"),
        (2, "new", b"new plot"),
    ]


def _state_storage(database: Database) -> str:
    """PostgreSQL's storage mode of ``localization.state`` (``x`` extended, ``e`` external)."""
    with database.engine.connect() as connection:
        return str(
            connection.execute(
                text(
                    "SELECT attstorage FROM pg_attribute "
                    "WHERE attrelid = 'localization'::regclass AND attname = 'state'"
                )
            ).scalar_one()
        )


@pytest.mark.parametrize("empty_db", ["postgresql"], indirect=True)
def test_the_localization_state_is_stored_uncompressed_on_postgresql(empty_db):
    # Each update rewrites ~19 KB of state: compressing it cost ~40% of PostgreSQL's CPU.
    config = alembic_config(empty_db.url.render_as_string(hide_password=False))
    command.upgrade(config, "head")
    assert _state_storage(empty_db) == "e"
    command.downgrade(config, "3c7e5a1f2b90")  # the revision before
    assert _state_storage(empty_db) == "x"
    command.upgrade(config, "head")
    assert _state_storage(empty_db) == "e"


@BACKENDS
def test_the_isam_state_tables_go_with_their_revision(empty_db):
    # issue 38: derivable state, so the downgrade drops it (a batch build writes it again)
    config = alembic_config(empty_db.url.render_as_string(hide_password=False))
    command.upgrade(config, "head")
    state_tables = {"isam_state", "isam_walk_state"}
    assert state_tables <= set(inspect(empty_db.engine).get_table_names())
    command.downgrade(config, "3c9e51b7a2d8")  # the revision before
    assert not state_tables & set(inspect(empty_db.engine).get_table_names())
    command.upgrade(config, "head")
    assert state_tables <= set(inspect(empty_db.engine).get_table_names())
    command.check(config)

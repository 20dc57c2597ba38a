"""Run and inspect the Alembic migrations in ``migrations/`` from code."""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory

from app.storage.db import Database

MIGRATIONS_DIR = Path(__file__).resolve().parents[2] / "migrations"


def alembic_config(url: str) -> Config:
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    config.set_main_option("file_template", "%%(year)d-%%(month).2d-%%(day).2d_%%(slug)s")
    config.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    return config


def upgrade_to_head(database: Database) -> None:
    """Bring the schema to the newest revision (a no-op when it is there already).

    Migrations run on a plain connection of their own, not the application's: on SQLite that
    connection has foreign keys off, as SQLite's table rebuilds need (with them on, dropping the
    old copy of a table would cascade-delete the rows that refer to it).
    """
    command.upgrade(alembic_config(database.url.render_as_string(hide_password=False)), "head")


def head_revision() -> str | None:
    return ScriptDirectory.from_config(alembic_config("sqlite://")).get_current_head()


def current_revision(database: Database) -> str | None:
    with database.read_engine.connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()


def is_current(database: Database) -> bool:
    """True when the database's schema is at the newest revision."""
    return current_revision(database) == head_revision()

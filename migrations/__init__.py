"""Alembic migrations: ``app/storage/migrate.py`` runs them; ``alembic.ini`` is for the CLI."""

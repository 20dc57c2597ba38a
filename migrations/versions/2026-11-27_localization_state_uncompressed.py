"""A navigation session's state is stored uncompressed on PostgreSQL (issue 16).

Every localization update rewrites the session's ``state`` (~19 KB of JSON, mostly base64 of
float64 arrays). PostgreSQL compressed each new value before storing it out of line (TOAST,
``STORAGE EXTENDED``): ~40% of the database server's CPU per update, for ~25% less space on data
base64 already packs. ``STORAGE EXTERNAL`` stores it out of line as it is: 0.53 → 0.31 ms of the
server's CPU per update (``bench/http.py``'s update row, one API process). Values written before
stay compressed until their next update. SQLite: nothing to do (it never compresses).

Revision ID: 8a41c2d7e5b3
Revises: 3c7e5a1f2b90
Create Date: 2026-11-27 16:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

from alembic import op

revision: str = "8a41c2d7e5b3"
down_revision: str | None = "3c7e5a1f2b90"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    if op.get_bind().dialect.name == "postgresql":
        op.execute("ALTER TABLE localization ALTER COLUMN state SET STORAGE EXTERNAL")


def downgrade() -> None:
    if op.get_bind().dialect.name == "postgresql":
        op.execute("ALTER TABLE localization ALTER COLUMN state SET STORAGE EXTENDED")

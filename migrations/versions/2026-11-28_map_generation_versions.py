"""A map's generation, the generation each build job builds and each version was built for
(issue 25).

Every change of what a map's next version is built from (its sessions, a rebuild's parameters)
bumps ``map.generation``; a build job carries the generation it was queued for
(``job.map_generation``), and its version is stored only while that is still the map's
(otherwise the build was overtaken and is dropped). Existing maps start at 0, as do the build
jobs already queued (null, read as 0); existing versions have none (null).

Revision ID: 5d2b8e7f1c04
Revises: 8a41c2d7e5b3
Create Date: 2026-11-28 10:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "5d2b8e7f1c04"
down_revision: str | None = "8a41c2d7e5b3"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # a plain ADD COLUMN (SQLite takes a NOT NULL one with a constant default): a batch would
    # copy the table, and SQLite's copy would lose AUTOINCREMENT (ids never reused)
    op.add_column(
        "map", sa.Column("generation", sa.Integer(), server_default=sa.text("0"), nullable=False)
    )
    op.add_column("map_version", sa.Column("generation", sa.Integer(), nullable=True))
    op.add_column("job", sa.Column("map_generation", sa.Integer(), nullable=True))


def downgrade() -> None:
    for table, column in (
        ("job", "map_generation"),
        ("map_version", "generation"),
        ("map", "generation"),
    ):
        with op.batch_alter_table(
            table, schema=None, table_kwargs={"sqlite_autoincrement": True}
        ) as batch_op:
            batch_op.drop_column(column)

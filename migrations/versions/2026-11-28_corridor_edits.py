"""Corridor edits (issue 27): an operator's corrections of a map's corridor graph, per map, and
the map's edit revision (what the API's caches of edited graphs are keyed by).

Revision ID: e27c0a11d5f3
Revises: 5d2b8e7f1c04
Create Date: 2026-11-28 10:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "e27c0a11d5f3"
down_revision: str | None = "5d2b8e7f1c04"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

JSON_VALUE = sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")


def upgrade() -> None:
    # ADD COLUMN in place: a batch copy of the table would lose SQLite's AUTOINCREMENT
    op.add_column(
        "map",
        sa.Column(
            "corridor_edits_revision", sa.Integer(), server_default=sa.text("0"), nullable=False
        ),
    )
    op.create_table(
        "corridor_edit",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("map_id", sa.Integer(), nullable=False),
        sa.Column("edit", JSON_VALUE, nullable=False),
        sa.Column("created_by", sa.String(length=64), nullable=False),
        sa.Column("created_by_name", sa.String(length=100), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["map_id"], ["map.id"], name=op.f("fk_corridor_edit_map_id_map"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_corridor_edit")),
        sqlite_autoincrement=True,
    )
    with op.batch_alter_table("corridor_edit", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_corridor_edit_map_id"), ["map_id"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("corridor_edit", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_corridor_edit_map_id"))
    op.drop_table("corridor_edit")
    with op.batch_alter_table(
        "map", schema=None, table_kwargs={"sqlite_autoincrement": True}
    ) as batch_op:
        batch_op.drop_column("corridor_edits_revision")

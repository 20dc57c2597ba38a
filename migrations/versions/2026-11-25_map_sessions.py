"""Maps of several sessions: the sessions each map is made of; which ones a version used.

Every existing map gets its one session as its first ``map_session`` row; existing versions keep
``session_ids`` null (made from their map's ``session_id`` alone).

Revision ID: 8d2e6b41c7f3
Revises: 5c1f3a9e7b20
Create Date: 2026-11-25 16:00:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "8d2e6b41c7f3"
down_revision: str | None = "5c1f3a9e7b20"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

JSON_VALUE = sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")


def upgrade() -> None:
    op.create_table(
        "map_session",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("map_id", sa.Integer(), nullable=False),
        sa.Column("session_id", sa.Integer(), nullable=False),
        sa.Column("added_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["map_id"], ["map.id"], name=op.f("fk_map_session_map_id_map"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["session_id"],
            ["session.id"],
            name=op.f("fk_map_session_session_id_session"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_map_session")),
        sa.UniqueConstraint("map_id", "session_id", name=op.f("uq_map_session_map_id_session_id")),
    )
    with op.batch_alter_table("map_session", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_map_session_map_id"), ["map_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_map_session_session_id"), ["session_id"], unique=False)
    op.execute(
        "INSERT INTO map_session (map_id, session_id, added_at) "
        "SELECT id, session_id, created_at FROM map ORDER BY id"
    )
    with op.batch_alter_table("map_version", schema=None) as batch_op:
        batch_op.add_column(sa.Column("session_ids", JSON_VALUE, nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("map_version", schema=None) as batch_op:
        batch_op.drop_column("session_ids")
    with op.batch_alter_table("map_session", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_map_session_session_id"))
        batch_op.drop_index(batch_op.f("ix_map_session_map_id"))
    op.drop_table("map_session")

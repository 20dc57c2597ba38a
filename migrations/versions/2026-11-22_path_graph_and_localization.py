"""Path graphs on map versions; live localization sessions.

Revision ID: 445dc56590f9
Revises: 255ed7c85f58
Create Date: 2026-11-22 04:53:29.649396
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "445dc56590f9"
down_revision: str | None = "255ed7c85f58"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

JSON_VALUE = sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")


#: Tables whose ids must never be reused (SQLite: AUTOINCREMENT; a no-op on PostgreSQL).
NEVER_REUSE_ID_TABLES = ("api_key", "session", "map", "job", "map_version")


def upgrade() -> None:
    if op.get_bind().dialect.name == "sqlite":
        for table in NEVER_REUSE_ID_TABLES:
            with op.batch_alter_table(
                table, recreate="always", table_kwargs={"sqlite_autoincrement": True}
            ):
                pass
    op.create_table(
        "localization",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("map_id", sa.Integer(), nullable=False),
        sa.Column("map_version_id", sa.Integer(), nullable=False),
        sa.Column("created_by", sa.String(length=64), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("revision", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(length=32), nullable=False),
        sa.Column("update_count", sa.Integer(), nullable=False),
        sa.Column("state", JSON_VALUE, nullable=False),
        sa.ForeignKeyConstraint(
            ["map_id"], ["map.id"], name=op.f("fk_localization_map_id_map"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["map_version_id"],
            ["map_version.id"],
            name=op.f("fk_localization_map_version_id_map_version"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_localization")),
        sqlite_autoincrement=True,
    )
    with op.batch_alter_table("localization", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_localization_map_id"), ["map_id"], unique=False)

    with op.batch_alter_table("map_version", schema=None) as batch_op:
        batch_op.add_column(sa.Column("path_graph_gzip", sa.LargeBinary(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("map_version", schema=None) as batch_op:
        batch_op.drop_column("path_graph_gzip")

    with op.batch_alter_table("localization", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_localization_map_id"))

    op.drop_table("localization")
    if op.get_bind().dialect.name == "sqlite":
        for table in NEVER_REUSE_ID_TABLES:
            with op.batch_alter_table(
                table, recreate="always", table_kwargs={"sqlite_autoincrement": False}
            ):
                pass

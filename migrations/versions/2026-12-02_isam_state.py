"""The incremental state of building maps (issue 38): ``isam_state``, one row per map version
that has one (what makes the version's ISAM2 tree again: its tags, walks in order, parameters,
next free pose key), and ``isam_walk_state``, one row per walk of it. Derivable: a batch build
writes it again, so the downgrade drops it and backups skip it.

Revision ID: 8b41d6c2f0a9
Revises: 3c9e51b7a2d8
Create Date: 2026-12-02 07:10:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "8b41d6c2f0a9"
down_revision: str | None = "3c9e51b7a2d8"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

JSON_VALUE = sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")


def upgrade() -> None:
    op.create_table(
        "isam_state",
        sa.Column("map_version_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("map_id", sa.Integer(), nullable=False),
        sa.Column("format", sa.String(length=32), nullable=False),
        sa.Column("fingerprint", sa.String(length=64), nullable=False),
        sa.Column("params", JSON_VALUE, nullable=False),
        sa.Column("walk_ids", JSON_VALUE, nullable=False),
        sa.Column("walk_fingerprints", JSON_VALUE, nullable=False),
        sa.Column("next_key", sa.Integer(), nullable=False),
        sa.Column("arrays", sa.LargeBinary(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["map_id"], ["map.id"], name=op.f("fk_isam_state_map_id_map"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["map_version_id"],
            ["map_version.id"],
            name=op.f("fk_isam_state_map_version_id_map_version"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("map_version_id", name=op.f("pk_isam_state")),
    )
    with op.batch_alter_table("isam_state", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_isam_state_map_id"), ["map_id"], unique=False)
    op.create_table(
        "isam_walk_state",
        sa.Column("map_version_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("position", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("walk_id", sa.String(length=100), nullable=False),
        sa.Column("fingerprint", sa.String(length=64), nullable=False),
        sa.Column("depth_scale", sa.Float(), nullable=False),
        sa.Column("cost_alone", sa.Float(), nullable=False),
        sa.Column("key_offset", sa.Integer(), nullable=False),
        sa.Column("arrays", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(
            ["map_version_id"],
            ["isam_state.map_version_id"],
            name=op.f("fk_isam_walk_state_map_version_id_isam_state"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("map_version_id", "position", name=op.f("pk_isam_walk_state")),
    )


def downgrade() -> None:
    op.drop_table("isam_walk_state")
    with op.batch_alter_table("isam_state", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_isam_state_map_id"))
    op.drop_table("isam_state")

"""Dashboard logins kept on the server (logout, key revocation and "end all" end them).

Revision ID: a1bdea7a7cb1
Revises: 3a7c90d15e42
Create Date: 2026-11-25 15:40:59.811418
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "a1bdea7a7cb1"
down_revision: str | None = "3a7c90d15e42"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "admin_login",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("token_sha256", sa.String(length=64), nullable=False),
        sa.Column("key_id", sa.Integer(), nullable=True),
        sa.Column("subject", sa.String(length=64), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("expires_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["key_id"],
            ["api_key.id"],
            name=op.f("fk_admin_login_key_id_api_key"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_admin_login")),
        sa.UniqueConstraint("token_sha256", name=op.f("uq_admin_login_token_sha256")),
    )
    with op.batch_alter_table("admin_login", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_admin_login_key_id"), ["key_id"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("admin_login", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_admin_login_key_id"))
    op.drop_table("admin_login")

"""An index of each key's sessions by time: the upload rate limit counts them from the table.

Revision ID: 5d2e8b41c7f3
Revises: 6f2b8c3d9e14
Create Date: 2026-11-25 18:15:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

from alembic import op

revision: str = "5d2e8b41c7f3"
down_revision: str | None = "6f2b8c3d9e14"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("session", schema=None) as batch_op:
        batch_op.create_index(
            "ix_session_uploaded_by_created_at", ["uploaded_by", "created_at"], unique=False
        )


def downgrade() -> None:
    with op.batch_alter_table("session", schema=None) as batch_op:
        batch_op.drop_index("ix_session_uploaded_by_created_at")

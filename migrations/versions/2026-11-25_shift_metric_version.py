"""Which definition of the shift metric a sweep's trials were scored with.

Sweeps stored before this revision used the origin-dependent form (version 1); new ones the
origin-invariant form of docs/architecture.md §4 (version 2, ``SHIFT_METRIC_VERSION``).

Revision ID: 5c1f3a9e7b20
Revises: 7c3e9a41d2b6
Create Date: 2026-11-25 15:40:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "5c1f3a9e7b20"
down_revision: str | None = "7c3e9a41d2b6"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("sweep", schema=None) as batch_op:
        batch_op.add_column(
            sa.Column(
                "shift_metric_version", sa.Integer(), server_default=sa.text("1"), nullable=False
            )
        )


def downgrade() -> None:
    with op.batch_alter_table("sweep", schema=None) as batch_op:
        batch_op.drop_column("shift_metric_version")

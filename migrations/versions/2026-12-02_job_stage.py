"""How long each stage of a job took (issue 40): the ``job_stage`` table, one row per stage of an
attempt that ran to its end, which ``/metrics`` counts from (docs/operations.md, "Metrics").
Jobs finished before it have none.

Revision ID: 3c9e51b7a2d8
Revises: e27c0a11d5f3
Create Date: 2026-12-02 02:30:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "3c9e51b7a2d8"
down_revision: str | None = "e27c0a11d5f3"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "job_stage",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("job_id", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(length=32), nullable=False),
        sa.Column("stage", sa.String(length=32), nullable=False),
        sa.Column("attempt", sa.Integer(), nullable=False),
        sa.Column("duration_s", sa.Float(), nullable=False),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["job_id"], ["job.id"], name=op.f("fk_job_stage_job_id_job"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_job_stage")),
    )
    with op.batch_alter_table("job_stage", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_job_stage_job_id"), ["job_id"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("job_stage", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_job_stage_job_id"))
    op.drop_table("job_stage")

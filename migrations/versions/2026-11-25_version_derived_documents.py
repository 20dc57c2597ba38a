"""What the worker derives from a map version once (issue 19, finding 3): ``map_version``'s
references to the blobs of its app-map (with the export that made it) and of the dashboard's
overview. Versions stored before have none (the API builds both then). A downgrade drops the
references; the blobs are then orphans, collected as any.

Revision ID: 3c7e5a1f2b90
Revises: 5d2e8b41c7f3
Create Date: 2026-11-25 19:10:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "3c7e5a1f2b90"
down_revision: str | None = "5d2e8b41c7f3"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

#: map_version's references to the blobs of its derived documents
REFERENCES = ("app_map_sha256", "overview_sha256")


def upgrade() -> None:
    with op.batch_alter_table("map_version", schema=None) as batch_op:
        for column in REFERENCES:
            batch_op.add_column(sa.Column(column, sa.String(length=64), nullable=True))
            batch_op.create_index(batch_op.f(f"ix_map_version_{column}"), [column], unique=False)
            batch_op.create_foreign_key(
                batch_op.f(f"fk_map_version_{column}_blob"), "blob", [column], ["sha256"]
            )
        batch_op.add_column(sa.Column("app_map_export", sa.Integer(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("map_version", schema=None) as batch_op:
        batch_op.drop_column("app_map_export")
        for column in REFERENCES:
            batch_op.drop_constraint(
                batch_op.f(f"fk_map_version_{column}_blob"), type_="foreignkey"
            )
            batch_op.drop_index(batch_op.f(f"ix_map_version_{column}"))
            batch_op.drop_column(column)

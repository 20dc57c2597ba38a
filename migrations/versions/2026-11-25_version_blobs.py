"""A version's bulk data as content-addressed blobs, written outside the transaction that stores
the version (issue 19, finding 4): ``blob`` and ``blob_chunk``, and ``map_version``'s references
to them. Versions stored before keep their bytes in their own row (``map_json_gzip`` becomes
nullable); a downgrade copies every blob a version refers to back into its row.

Revision ID: 6f2b8c3d9e14
Revises: a1bdea7a7cb1
Create Date: 2026-11-25 18:20:00.000000
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "6f2b8c3d9e14"
down_revision: str | None = "a1bdea7a7cb1"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

#: map_version's blob reference → the column that holds the same bytes in the row
REFERENCES = {
    "map_json_sha256": "map_json_gzip",
    "plot_png_sha256": "plot_png",
    "path_graph_sha256": "path_graph_gzip",
}


def upgrade() -> None:
    op.create_table(
        "blob",
        sa.Column("sha256", sa.String(length=64), nullable=False),
        sa.Column("size_bytes", sa.Integer(), nullable=False),
        sa.Column("chunk_count", sa.Integer(), nullable=False),
        sa.Column("complete", sa.Boolean(), nullable=False),
        sa.Column("touched_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("sha256", name=op.f("pk_blob")),
    )
    with op.batch_alter_table("blob", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_blob_touched_at"), ["touched_at"], unique=False)
    op.create_table(
        "blob_chunk",
        sa.Column("sha256", sa.String(length=64), nullable=False),
        sa.Column("number", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(
            ["sha256"], ["blob.sha256"], name=op.f("fk_blob_chunk_sha256_blob"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("sha256", "number", name=op.f("pk_blob_chunk")),
    )
    with op.batch_alter_table("map_version", schema=None) as batch_op:
        batch_op.alter_column("map_json_gzip", existing_type=sa.LargeBinary(), nullable=True)
        for column in REFERENCES:
            batch_op.add_column(sa.Column(column, sa.String(length=64), nullable=True))
            batch_op.create_index(batch_op.f(f"ix_map_version_{column}"), [column], unique=False)
            batch_op.create_foreign_key(
                batch_op.f(f"fk_map_version_{column}_blob"), "blob", [column], ["sha256"]
            )


def downgrade() -> None:
    connection = op.get_bind()
    for reference, inline in REFERENCES.items():
        rows = connection.execute(
            sa.text(f"SELECT id, {reference} FROM map_version WHERE {reference} IS NOT NULL")
        ).all()
        for version_id, sha256 in rows:
            chunks = connection.execute(
                sa.text("SELECT data FROM blob_chunk WHERE sha256 = :sha ORDER BY number"),
                {"sha": sha256},
            ).scalars()
            connection.execute(
                sa.text(f"UPDATE map_version SET {inline} = :data WHERE id = :id"),
                {"data": b"".join(bytes(chunk) for chunk in chunks), "id": version_id},
            )
    with op.batch_alter_table("map_version", schema=None) as batch_op:
        for column in REFERENCES:
            batch_op.drop_constraint(
                batch_op.f(f"fk_map_version_{column}_blob"), type_="foreignkey"
            )
            batch_op.drop_index(batch_op.f(f"ix_map_version_{column}"))
            batch_op.drop_column(column)
        batch_op.alter_column("map_json_gzip", existing_type=sa.LargeBinary(), nullable=False)
    op.drop_table("blob_chunk")
    with op.batch_alter_table("blob", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_blob_touched_at"))
    op.drop_table("blob")

"""Initial schema: keys, sessions and their raw uploads, maps, versions, tags, jobs, workers.

Revision ID: 255ed7c85f58
Revises:
Create Date: 2026-11-22 04:15:07.121500
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "255ed7c85f58"
down_revision: str | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# JSON everywhere, JSONB on PostgreSQL (queryable, indexable).
JSON_VALUE = sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")


def upgrade() -> None:
    op.create_table(
        "api_key",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=100), nullable=False),
        sa.Column("role", sa.String(length=16), nullable=False),
        sa.Column("prefix", sa.String(length=16), nullable=False),
        sa.Column("secret_sha256", sa.String(length=64), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("expires_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("revoked_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("last_used_at", sa.DateTime(timezone=True), nullable=True),
        sa.CheckConstraint("role IN ('device', 'admin')", name=op.f("ck_api_key_role")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_api_key")),
        sa.UniqueConstraint("prefix", name=op.f("uq_api_key_prefix")),
    )
    op.create_table(
        "session",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("map_name", sa.String(length=200), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("uploaded_by", sa.String(length=64), nullable=False),
        sa.Column("idempotency_key", sa.String(length=200), nullable=True),
        sa.Column("raw_sha256", sa.String(length=64), nullable=False),
        sa.Column("raw_size_bytes", sa.Integer(), nullable=False),
        sa.Column("stored_size_bytes", sa.Integer(), nullable=False),
        sa.Column("pose_count", sa.Integer(), nullable=False),
        sa.Column("detection_count", sa.Integer(), nullable=False),
        sa.Column("tag_count", sa.Integer(), nullable=False),
        sa.Column("poi_count", sa.Integer(), nullable=False),
        sa.Column("duration_s", sa.Float(), nullable=False),
        sa.Column("path_length_m", sa.Float(), nullable=False),
        sa.Column("tag_ids", JSON_VALUE, nullable=False),
        sa.Column("warnings", JSON_VALUE, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_session")),
        sa.UniqueConstraint(
            "uploaded_by", "idempotency_key", name=op.f("uq_session_uploaded_by_idempotency_key")
        ),
    )
    op.create_table(
        "worker",
        sa.Column("id", sa.String(length=100), nullable=False),
        sa.Column("hostname", sa.String(length=255), nullable=False),
        sa.Column("pid", sa.Integer(), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("heartbeat_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("current_job_id", sa.Integer(), nullable=True),
        sa.Column("jobs_done", sa.Integer(), nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_worker")),
    )
    op.create_table(
        "map",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("session_id", sa.Integer(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["session_id"],
            ["session.id"],
            name=op.f("fk_map_session_id_session"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_map")),
    )
    with op.batch_alter_table("map", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_map_session_id"), ["session_id"], unique=False)

    op.create_table(
        "session_upload",
        sa.Column("session_id", sa.Integer(), nullable=False),
        sa.Column("raw_gzip", sa.LargeBinary(), nullable=False),
        sa.ForeignKeyConstraint(
            ["session_id"],
            ["session.id"],
            name=op.f("fk_session_upload_session_id_session"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("session_id", name=op.f("pk_session_upload")),
    )
    op.create_table(
        "job",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("kind", sa.String(length=32), nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("map_id", sa.Integer(), nullable=True),
        sa.Column("session_id", sa.Integer(), nullable=True),
        sa.Column("params", JSON_VALUE, nullable=False),
        sa.Column("priority", sa.Integer(), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("max_attempts", sa.Integer(), nullable=False),
        sa.Column("run_after", sa.DateTime(timezone=True), nullable=False),
        sa.Column("lease_owner", sa.String(length=100), nullable=True),
        sa.Column("lease_token", sa.Integer(), nullable=False),
        sa.Column("lease_expires_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("cancel_requested", sa.Boolean(), nullable=False),
        sa.Column("progress", sa.Float(), nullable=False),
        sa.Column("stage", sa.String(length=32), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("log_tail", sa.Text(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint(
            "state IN ('queued', 'running', 'succeeded', 'failed', 'canceled')",
            name=op.f("ck_job_state"),
        ),
        sa.CheckConstraint("progress >= 0 AND progress <= 1", name=op.f("ck_job_progress")),
        sa.ForeignKeyConstraint(
            ["map_id"], ["map.id"], name=op.f("fk_job_map_id_map"), ondelete="CASCADE"
        ),
        sa.ForeignKeyConstraint(
            ["session_id"],
            ["session.id"],
            name=op.f("fk_job_session_id_session"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_job")),
    )
    with op.batch_alter_table("job", schema=None) as batch_op:
        batch_op.create_index("ix_job_claim", ["state", "run_after", "priority"], unique=False)
        batch_op.create_index(batch_op.f("ix_job_map_id"), ["map_id"], unique=False)
        batch_op.create_index(batch_op.f("ix_job_session_id"), ["session_id"], unique=False)

    op.create_table(
        "map_version",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("map_id", sa.Integer(), nullable=False),
        sa.Column("number", sa.Integer(), nullable=False),
        sa.Column("job_id", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("params", JSON_VALUE, nullable=False),
        sa.Column("statistics", JSON_VALUE, nullable=False),
        sa.Column("metrics", JSON_VALUE, nullable=False),
        sa.Column("shift_metric", sa.Float(), nullable=True),
        sa.Column("tag_count", sa.Integer(), nullable=False),
        sa.Column("detections_used", sa.Integer(), nullable=False),
        sa.Column("detections_rejected", sa.Integer(), nullable=False),
        sa.Column("rejections", JSON_VALUE, nullable=False),
        sa.Column("warnings", JSON_VALUE, nullable=False),
        sa.Column("map_json_gzip", sa.LargeBinary(), nullable=False),
        sa.Column("plot_png", sa.LargeBinary(), nullable=True),
        sa.Column("content_sha256", sa.String(length=64), nullable=False),
        sa.ForeignKeyConstraint(
            ["job_id"], ["job.id"], name=op.f("fk_map_version_job_id_job"), ondelete="SET NULL"
        ),
        sa.ForeignKeyConstraint(
            ["map_id"], ["map.id"], name=op.f("fk_map_version_map_id_map"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_map_version")),
        sa.UniqueConstraint("job_id", name=op.f("uq_map_version_job_id")),
        sa.UniqueConstraint("map_id", "number", name=op.f("uq_map_version_map_id_number")),
    )
    with op.batch_alter_table("map_version", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_map_version_map_id"), ["map_id"], unique=False)

    op.create_table(
        "map_tag",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("map_version_id", sa.Integer(), nullable=False),
        sa.Column("tag_id", sa.Integer(), nullable=False),
        sa.Column("x_m", sa.Float(), nullable=False),
        sa.Column("y_m", sa.Float(), nullable=False),
        sa.Column("z_m", sa.Float(), nullable=False),
        sa.Column("qx", sa.Float(), nullable=False),
        sa.Column("qy", sa.Float(), nullable=False),
        sa.Column("qz", sa.Float(), nullable=False),
        sa.Column("qw", sa.Float(), nullable=False),
        sa.Column("detection_count", sa.Integer(), nullable=False),
        sa.Column("covariance", JSON_VALUE, nullable=True),
        sa.ForeignKeyConstraint(
            ["map_version_id"],
            ["map_version.id"],
            name=op.f("fk_map_tag_map_version_id_map_version"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_map_tag")),
        sa.UniqueConstraint(
            "map_version_id", "tag_id", name=op.f("uq_map_tag_map_version_id_tag_id")
        ),
    )
    with op.batch_alter_table("map_tag", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_map_tag_tag_id"), ["tag_id"], unique=False)


def downgrade() -> None:
    with op.batch_alter_table("map_tag", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_map_tag_tag_id"))

    op.drop_table("map_tag")
    with op.batch_alter_table("map_version", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_map_version_map_id"))

    op.drop_table("map_version")
    with op.batch_alter_table("job", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_job_session_id"))
        batch_op.drop_index(batch_op.f("ix_job_map_id"))
        batch_op.drop_index("ix_job_claim")

    op.drop_table("job")
    op.drop_table("session_upload")
    with op.batch_alter_table("map", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_map_session_id"))

    op.drop_table("map")
    op.drop_table("worker")
    op.drop_table("session")
    op.drop_table("api_key")

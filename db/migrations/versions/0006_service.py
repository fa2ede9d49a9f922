"""The service's records (`docs/service.md`): API keys (hashed, with scopes), model imports and
sequence uploads as the HTTP API tracks them, the job's current stage, and per unit the Celery
task id of its last delivery and the time it last started running (for the sweeper).

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-25 20:10:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None


def _ts(name: str, nullable: bool = False) -> sa.Column:
    return sa.Column(
        name,
        sa.DateTime(timezone=True),
        nullable=nullable,
        server_default=None if nullable else sa.text("now()"),
    )


def upgrade() -> None:
    op.create_table(
        "api_key",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("name", sa.Text(), nullable=False),
        sa.Column("prefix", sa.Text(), nullable=False),
        sa.Column("key_hash", sa.Text(), nullable=False, unique=True),
        sa.Column("scopes", postgresql.ARRAY(sa.Text()), nullable=False),
        _ts("created_at"),
        _ts("revoked_at", nullable=True),
        sa.CheckConstraint("scopes <@ ARRAY['read', 'submit', 'admin']::text[]", name="ck_api_key_scopes"),
    )
    op.create_table(
        "model_import",
        sa.Column("id", sa.BigInteger(), primary_key=True),
        sa.Column("name", sa.Text(), nullable=False),
        sa.Column("status", sa.Text(), nullable=False),
        sa.Column("message", sa.Text(), nullable=True),
        sa.Column("upload_path", sa.Text(), nullable=True),
        sa.Column(
            "city_model_id", sa.Integer(), sa.ForeignKey("city_model.id", ondelete="SET NULL"), nullable=True
        ),
        sa.Column("bytes", sa.BigInteger(), nullable=False, server_default="0"),
        sa.Column("progress", sa.Double(), nullable=False, server_default="0"),
        _ts("created_at"),
        _ts("updated_at"),
        sa.CheckConstraint("status IN ('importing', 'ready', 'failed')", name="ck_model_import_status"),
    )
    op.create_index(
        "uq_model_import_name_active",
        "model_import",
        ["name"],
        unique=True,
        postgresql_where=sa.text("status <> 'failed'"),
    )
    op.create_table(
        "sequence_upload",
        sa.Column("id", sa.Uuid(), primary_key=True),
        sa.Column("status", sa.Text(), nullable=False),
        sa.Column("parts", postgresql.JSONB(), nullable=False, server_default=sa.text("'{}'::jsonb")),
        sa.Column("bytes", sa.BigInteger(), nullable=False, server_default="0"),
        sa.Column("message", sa.Text(), nullable=True),
        sa.Column(
            "sequence_id", sa.Integer(), sa.ForeignKey("sequence.id", ondelete="SET NULL"), nullable=True
        ),
        _ts("created_at"),
        _ts("updated_at"),
        sa.CheckConstraint("status IN ('open', 'committed', 'failed')", name="ck_sequence_upload_status"),
    )
    op.add_column("job", sa.Column("stage", sa.Text(), nullable=False, server_default="accepted"))
    op.add_column("job_unit", sa.Column("task_id", sa.Text(), nullable=True))
    op.add_column("job_unit", sa.Column("heartbeat_at", sa.DateTime(timezone=True), nullable=True))
    op.create_index("ix_job_unit_job_status", "job_unit", ["job_id", "status"])


def downgrade() -> None:
    op.drop_index("ix_job_unit_job_status", table_name="job_unit")
    op.drop_column("job_unit", "heartbeat_at")
    op.drop_column("job_unit", "task_id")
    op.drop_column("job", "stage")
    op.drop_table("sequence_upload")
    op.drop_index("uq_model_import_name_active", table_name="model_import")
    op.drop_table("model_import")
    op.drop_table("api_key")

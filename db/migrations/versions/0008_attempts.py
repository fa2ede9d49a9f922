"""Deliveries counted for the tasks that are not building units: `job.attempts` (prepare and
finish deliveries of a job) and `model_import.attempts`, so that a task whose worker dies every
time (out of memory, past its hard time limit) fails its job or import after a bounded number of
deliveries instead of being delivered again for ever.

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-25 21:35:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("job", sa.Column("attempts", sa.Integer(), nullable=False, server_default="0"))
    op.add_column("model_import", sa.Column("attempts", sa.Integer(), nullable=False, server_default="0"))


def downgrade() -> None:
    op.drop_column("model_import", "attempts")
    op.drop_column("job", "attempts")

"""Bulk loading: drop the redundant foreign key surface.city_model_id -> city_model (the surface's
building already belongs to the model; the column stays, indexed, for filtering and deletes).
Checking it cost as much as the rest of a surface row's COPY.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-21 06:10:00
"""

from __future__ import annotations

from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.drop_constraint("surface_city_model_id_fkey", "surface", type_="foreignkey")


def downgrade() -> None:
    op.create_foreign_key(
        "surface_city_model_id_fkey", "surface", "city_model", ["city_model_id"], ["id"], ondelete="CASCADE"
    )

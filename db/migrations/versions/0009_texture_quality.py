"""Texture quality per surface (issue 15): the texels per metre of the surface's grid (coarser
than the job's where the frames see it only coarsely), the best local resolution among its
observations, the mean number of observations a fused texel rests on, and why a surface the
frames see got no texel.

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-25 23:45:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None

COLUMNS = (
    ("resolution_px_per_m", sa.Double()),
    ("best_resolution_m", sa.Double()),
    ("mean_observations", sa.Double()),
    ("reason", sa.Text()),
)


def upgrade() -> None:
    for name, type_ in COLUMNS:
        op.add_column("surface_thermal", sa.Column(name, type_, nullable=True))


def downgrade() -> None:
    for name, _ in reversed(COLUMNS):
        op.drop_column("surface_thermal", name)

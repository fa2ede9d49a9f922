"""Facade feature texts (issue 17, bench): each `surface_thermal` row keeps its GeoJSON Feature in
CRS84 as the OGC API - Features service writes it (`feature`) and the fingerprint of the
definition that wrote it (`feature_spec`), so that a page of `facades` is an index scan over
stored text (`db.facade_features`, `docs/features.md`). The rows already there get theirs here,
with the properties of the schema as it is (the service uses a text only when its fingerprint
is the one of its own definition, and writes the others itself).

Revision ID: 0012
Revises: 0011
Create Date: 2026-11-26 10:40:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from db.facade_features import write_feature_texts

revision = "0012"
down_revision = "0011"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("surface_thermal", sa.Column("feature", sa.Text(), nullable=True))
    op.add_column("surface_thermal", sa.Column("feature_spec", sa.Integer(), nullable=True))
    write_feature_texts(op.get_bind(), "TRUE", all_columns=False)


def downgrade() -> None:
    op.drop_column("surface_thermal", "feature_spec")
    op.drop_column("surface_thermal", "feature")

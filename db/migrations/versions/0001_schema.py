"""Schema: city models, buildings, surfaces, sequences, frames, jobs, poses, appearances (CityGML
appearance model: appearance -> surface_data -> texture_param / tex_image), thermal statistics.

Revision ID: 0001
Revises:
Create Date: 2026-11-21 05:52:39.392301
"""

from __future__ import annotations

import geoalchemy2
import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.execute("CREATE EXTENSION IF NOT EXISTS postgis")
    op.create_table(
        "city_model",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.Text(), nullable=False),
        sa.Column("srs_name", sa.Text(), nullable=True),
        sa.Column("srid", sa.Integer(), nullable=False),
        sa.Column("vertical_epsg", sa.Integer(), nullable=True),
        sa.Column("citygml_version", sa.Text(), nullable=True),
        sa.Column("gml_name", sa.Text(), nullable=True),
        sa.Column("source_file", sa.Text(), nullable=True),
        sa.Column("imported_at", sa.DateTime(timezone=True), server_default=sa.text("now()"), nullable=False),
        sa.Column("building_count", sa.Integer(), nullable=False),
        sa.Column("part_count", sa.Integer(), nullable=False),
        sa.Column("surface_count", sa.BigInteger(), nullable=False),
        sa.Column("state", sa.Text(), nullable=False),
        sa.Column(
            "envelope",
            geoalchemy2.types.Geometry(
                geometry_type="POLYGONZ",
                srid=0,
                dimension=3,
                spatial_index=False,
                from_text="ST_GeomFromEWKT",
                name="geometry",
            ),
            nullable=True,
        ),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("name"),
    )
    op.create_table(
        "sequence",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.Text(), nullable=False),
        sa.Column("manifest", postgresql.JSONB(astext_type=sa.Text()), nullable=False),
        sa.Column("storage_location", sa.Text(), nullable=False),
        sa.Column("frame_count", sa.Integer(), nullable=False),
        sa.Column("srs_name", sa.Text(), nullable=True),
        sa.Column("srid", sa.Integer(), nullable=False),
        sa.Column(
            "trajectory",
            geoalchemy2.types.Geometry(
                geometry_type="LINESTRINGZ",
                srid=0,
                dimension=3,
                spatial_index=False,
                from_text="ST_GeomFromEWKT",
                name="geometry",
            ),
            nullable=True,
        ),
        sa.Column("created_at", sa.DateTime(timezone=True), server_default=sa.text("now()"), nullable=False),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("name"),
    )
    op.create_index(
        "ix_sequence_trajectory", "sequence", ["trajectory"], unique=False, postgresql_using="gist"
    )
    op.create_table(
        "building",
        sa.Column("id", sa.BigInteger(), nullable=False),
        sa.Column("city_model_id", sa.Integer(), nullable=False),
        sa.Column("gml_id", sa.Text(), nullable=False),
        sa.Column("parent_id", sa.BigInteger(), nullable=True),
        sa.Column("root_id", sa.BigInteger(), nullable=True),
        sa.Column("is_part", sa.Boolean(), nullable=False),
        sa.Column("ordinal", sa.Integer(), nullable=False),
        sa.Column("name", sa.Text(), nullable=True),
        sa.Column("srs_name", sa.Text(), nullable=True),
        sa.Column("generated_id", sa.Boolean(), nullable=False),
        sa.Column("attributes", postgresql.JSONB(astext_type=sa.Text()), nullable=False),
        sa.Column(
            "footprint",
            geoalchemy2.types.Geometry(
                geometry_type="MULTIPOLYGON",
                srid=0,
                dimension=2,
                spatial_index=False,
                from_text="ST_GeomFromEWKT",
                name="geometry",
            ),
            nullable=True,
        ),
        sa.Column(
            "envelope",
            geoalchemy2.types.Geometry(
                geometry_type="POLYGONZ",
                srid=0,
                dimension=3,
                spatial_index=False,
                from_text="ST_GeomFromEWKT",
                name="geometry",
            ),
            nullable=True,
        ),
        sa.ForeignKeyConstraint(["city_model_id"], ["city_model.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["parent_id"], ["building.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["root_id"], ["building.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("city_model_id", "gml_id", name="uq_building_model_gml_id"),
    )
    op.create_index("ix_building_envelope", "building", ["envelope"], unique=False, postgresql_using="gist")
    op.create_index("ix_building_footprint", "building", ["footprint"], unique=False, postgresql_using="gist")
    op.create_index("ix_building_model_ordinal", "building", ["city_model_id", "ordinal"], unique=False)
    op.create_index("ix_building_parent", "building", ["parent_id"], unique=False)
    op.create_index("ix_building_root", "building", ["root_id"], unique=False)
    op.create_table(
        "frame",
        sa.Column("id", sa.BigInteger(), nullable=False),
        sa.Column("sequence_id", sa.Integer(), nullable=False),
        sa.Column("index", sa.Integer(), nullable=False),
        sa.Column("file", sa.Text(), nullable=False),
        sa.Column("time_s", sa.Double(), nullable=True),
        sa.Column(
            "prior_center",
            geoalchemy2.types.Geometry(
                geometry_type="POINTZ",
                srid=0,
                dimension=3,
                spatial_index=False,
                from_text="ST_GeomFromEWKT",
                name="geometry",
            ),
            nullable=True,
        ),
        sa.Column("prior_rotation", postgresql.ARRAY(sa.Double()), nullable=True),
        sa.Column("record", postgresql.JSONB(astext_type=sa.Text()), nullable=True),
        sa.ForeignKeyConstraint(["sequence_id"], ["sequence.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("sequence_id", "index", name="uq_frame_sequence_index"),
    )
    op.create_table(
        "job",
        sa.Column("id", sa.Uuid(), nullable=False),
        sa.Column("city_model_id", sa.Integer(), nullable=False),
        sa.Column("sequence_id", sa.Integer(), nullable=True),
        sa.Column("theme", sa.Text(), nullable=False),
        sa.Column("status", sa.Text(), nullable=False),
        sa.Column("progress", sa.Double(), nullable=False),
        sa.Column("message", sa.Text(), nullable=True),
        sa.Column("options", postgresql.JSONB(astext_type=sa.Text()), nullable=False),
        sa.Column("mounting", postgresql.JSONB(astext_type=sa.Text()), nullable=True),
        sa.Column("timings_s", postgresql.JSONB(astext_type=sa.Text()), nullable=False),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("results_location", sa.Text(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), server_default=sa.text("now()"), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("updated_at", sa.DateTime(timezone=True), server_default=sa.text("now()"), nullable=False),
        sa.CheckConstraint(
            "status IN ('accepted', 'running', 'successful', 'failed', 'dismissed')", name="ck_job_status"
        ),
        sa.ForeignKeyConstraint(["city_model_id"], ["city_model.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["sequence_id"], ["sequence.id"], ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index("ix_job_city_model", "job", ["city_model_id"], unique=False)
    op.create_index("ix_job_status", "job", ["status"], unique=False)
    op.create_table(
        "appearance",
        sa.Column("id", sa.BigInteger(), nullable=False),
        sa.Column("city_model_id", sa.Integer(), nullable=False),
        sa.Column("building_id", sa.BigInteger(), nullable=True),
        sa.Column("job_id", sa.Uuid(), nullable=True),
        sa.Column("theme", sa.Text(), nullable=False),
        sa.Column("gml_id", sa.Text(), nullable=True),
        sa.Column("ordinal", sa.Integer(), nullable=False),
        sa.Column("radiometry", postgresql.JSONB(astext_type=sa.Text()), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), server_default=sa.text("now()"), nullable=False),
        sa.ForeignKeyConstraint(["building_id"], ["building.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["city_model_id"], ["city_model.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["job_id"], ["job.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index("ix_appearance_building_theme", "appearance", ["building_id", "theme"], unique=False)
    op.create_index(
        "uq_appearance_job_building",
        "appearance",
        ["job_id", "building_id"],
        unique=True,
        postgresql_where=sa.text("job_id IS NOT NULL"),
    )
    op.create_index("ix_appearance_model_theme", "appearance", ["city_model_id", "theme"], unique=False)
    op.create_table(
        "frame_pose",
        sa.Column("id", sa.BigInteger(), nullable=False),
        sa.Column("job_id", sa.Uuid(), nullable=False),
        sa.Column("building_id", sa.BigInteger(), nullable=False),
        sa.Column("frame_index", sa.Integer(), nullable=False),
        sa.Column("frame_id", sa.BigInteger(), nullable=True),
        sa.Column("status", sa.Text(), nullable=False),
        sa.Column("prior_center", postgresql.ARRAY(sa.Double()), nullable=True),
        sa.Column("prior_rotation", postgresql.ARRAY(sa.Double()), nullable=True),
        sa.Column("refined_center", postgresql.ARRAY(sa.Double()), nullable=False),
        sa.Column("refined_rotation", postgresql.ARRAY(sa.Double()), nullable=False),
        sa.Column(
            "center",
            geoalchemy2.types.Geometry(
                geometry_type="POINTZ",
                srid=0,
                dimension=3,
                spatial_index=False,
                from_text="ST_GeomFromEWKT",
                name="geometry",
            ),
            nullable=True,
        ),
        sa.Column("rms_px", sa.Double(), nullable=True),
        sa.Column("matches", sa.Integer(), nullable=False),
        sa.ForeignKeyConstraint(["building_id"], ["building.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["frame_id"], ["frame.id"], ondelete="SET NULL"),
        sa.ForeignKeyConstraint(["job_id"], ["job.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("job_id", "building_id", "frame_index", name="uq_frame_pose"),
    )
    op.create_index("ix_frame_pose_building", "frame_pose", ["building_id"], unique=False)
    op.create_index("ix_frame_pose_center", "frame_pose", ["center"], unique=False, postgresql_using="gist")
    op.create_index("ix_frame_pose_frame", "frame_pose", ["frame_id"], unique=False)
    op.create_table(
        "job_unit",
        sa.Column("id", sa.BigInteger(), nullable=False),
        sa.Column("job_id", sa.Uuid(), nullable=False),
        sa.Column("building_id", sa.BigInteger(), nullable=False),
        sa.Column("status", sa.Text(), nullable=False),
        sa.Column("progress", sa.Double(), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("timings_s", postgresql.JSONB(astext_type=sa.Text()), nullable=False),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.CheckConstraint(
            "status IN ('accepted', 'running', 'successful', 'failed', 'dismissed')",
            name="ck_job_unit_status",
        ),
        sa.ForeignKeyConstraint(["building_id"], ["building.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["job_id"], ["job.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("job_id", "building_id", name="uq_job_unit_job_building"),
    )
    op.create_index("ix_job_unit_building", "job_unit", ["building_id"], unique=False)
    op.create_table(
        "surface",
        sa.Column("id", sa.BigInteger(), nullable=False),
        sa.Column("city_model_id", sa.Integer(), nullable=False),
        sa.Column("building_id", sa.BigInteger(), nullable=False),
        sa.Column("ordinal", sa.Integer(), nullable=False),
        sa.Column("gml_id", sa.Text(), nullable=False),
        sa.Column("generated_id", sa.Boolean(), nullable=False),
        sa.Column("ring_ids", postgresql.ARRAY(sa.Text()), nullable=False),
        sa.Column("ring_generated", postgresql.ARRAY(sa.Boolean()), nullable=False),
        sa.Column("ring_closed", postgresql.ARRAY(sa.Boolean()), nullable=False),
        sa.Column("surface_class", sa.Text(), nullable=False),
        sa.Column("surface_gml_id", sa.Text(), nullable=True),
        sa.Column("lod", sa.SmallInteger(), nullable=False),
        sa.Column("in_solid", sa.Boolean(), nullable=False),
        sa.Column("collection_id", sa.Text(), nullable=True),
        sa.Column(
            "geometry",
            geoalchemy2.types.Geometry(
                geometry_type="POLYGONZ",
                srid=0,
                dimension=3,
                spatial_index=False,
                from_text="ST_GeomFromEWKT",
                name="geometry",
            ),
            nullable=True,
        ),
        sa.Column("raw_rings", postgresql.JSONB(astext_type=sa.Text()), nullable=True),
        sa.Column("plane_normal", postgresql.ARRAY(sa.Double()), nullable=True),
        sa.Column("plane_offset", sa.Double(), nullable=True),
        sa.Column("area_m2", sa.Double(), nullable=True),
        sa.Column("checks", postgresql.JSONB(astext_type=sa.Text()), nullable=True),
        sa.ForeignKeyConstraint(["building_id"], ["building.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["city_model_id"], ["city_model.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index("ix_surface_building", "surface", ["building_id", "ordinal"], unique=False)
    op.create_index("ix_surface_geometry", "surface", ["geometry"], unique=False, postgresql_using="gist")
    op.create_index("ix_surface_model_gml_id", "surface", ["city_model_id", "gml_id"], unique=False)
    op.create_table(
        "surface_thermal",
        sa.Column("id", sa.BigInteger(), nullable=False),
        sa.Column("appearance_id", sa.BigInteger(), nullable=False),
        sa.Column("surface_id", sa.BigInteger(), nullable=False),
        sa.Column("texels_total", sa.Integer(), nullable=False),
        sa.Column("texels_observed", sa.Integer(), nullable=False),
        sa.Column("observed_share", sa.Double(), nullable=False),
        sa.Column("frames_used", postgresql.ARRAY(sa.Integer()), nullable=False),
        sa.Column("resolution_m", sa.Double(), nullable=True),
        sa.Column("view_angle_deg", sa.Double(), nullable=True),
        sa.Column("mean_k", sa.Double(), nullable=True),
        sa.Column("median_k", sa.Double(), nullable=True),
        sa.Column("std_k", sa.Double(), nullable=True),
        sa.Column("min_k", sa.Double(), nullable=True),
        sa.Column("max_k", sa.Double(), nullable=True),
        sa.Column("p05_k", sa.Double(), nullable=True),
        sa.Column("p25_k", sa.Double(), nullable=True),
        sa.Column("p75_k", sa.Double(), nullable=True),
        sa.Column("p95_k", sa.Double(), nullable=True),
        sa.Column("temperature", postgresql.JSONB(astext_type=sa.Text()), nullable=False),
        sa.Column("unit", sa.Text(), nullable=True),
        sa.ForeignKeyConstraint(["appearance_id"], ["appearance.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["surface_id"], ["surface.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("appearance_id", "surface_id", name="uq_surface_thermal"),
    )
    op.create_index("ix_surface_thermal_surface", "surface_thermal", ["surface_id"], unique=False)
    op.create_table(
        "tex_image",
        sa.Column("id", sa.BigInteger(), nullable=False),
        sa.Column("appearance_id", sa.BigInteger(), nullable=False),
        sa.Column("uri", sa.Text(), nullable=False),
        sa.Column("mime_type", sa.Text(), nullable=False),
        sa.Column("image", sa.LargeBinary(), nullable=False),
        sa.Column("width", sa.Integer(), nullable=False),
        sa.Column("height", sa.Integer(), nullable=False),
        sa.Column("bit_depth", sa.SmallInteger(), nullable=False),
        sa.Column("radiometry_scale", sa.Double(), nullable=True),
        sa.Column("radiometry_offset", sa.Double(), nullable=True),
        sa.Column("radiometry_unit", sa.Text(), nullable=True),
        sa.Column("sha256", sa.Text(), nullable=False),
        sa.ForeignKeyConstraint(["appearance_id"], ["appearance.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
        sa.UniqueConstraint("appearance_id", "uri", name="uq_tex_image_appearance_uri"),
    )
    op.create_index("ix_tex_image_sha256", "tex_image", ["sha256"], unique=False)
    op.create_table(
        "thermal_anomaly",
        sa.Column("id", sa.BigInteger(), nullable=False),
        sa.Column("job_id", sa.Uuid(), nullable=False),
        sa.Column("appearance_id", sa.BigInteger(), nullable=True),
        sa.Column("building_id", sa.BigInteger(), nullable=False),
        sa.Column("surface_id", sa.BigInteger(), nullable=True),
        sa.Column("kind", sa.Text(), nullable=False),
        sa.Column(
            "outline",
            geoalchemy2.types.Geometry(
                geometry_type="POLYGONZ",
                srid=0,
                dimension=3,
                spatial_index=False,
                from_text="ST_GeomFromEWKT",
                name="geometry",
            ),
            nullable=True,
        ),
        sa.Column("centre", postgresql.ARRAY(sa.Double()), nullable=False),
        sa.Column("area_m2", sa.Double(), nullable=False),
        sa.Column("peak_delta_k", sa.Double(), nullable=False),
        sa.Column("mean_delta_k", sa.Double(), nullable=False),
        sa.ForeignKeyConstraint(["appearance_id"], ["appearance.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["building_id"], ["building.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["job_id"], ["job.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["surface_id"], ["surface.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index("ix_thermal_anomaly_appearance", "thermal_anomaly", ["appearance_id"], unique=False)
    op.create_index("ix_thermal_anomaly_building", "thermal_anomaly", ["building_id"], unique=False)
    op.create_index(
        "ix_thermal_anomaly_job_building", "thermal_anomaly", ["job_id", "building_id"], unique=False
    )
    op.create_index(
        "ix_thermal_anomaly_outline", "thermal_anomaly", ["outline"], unique=False, postgresql_using="gist"
    )
    op.create_index("ix_thermal_anomaly_surface", "thermal_anomaly", ["surface_id"], unique=False)
    op.create_table(
        "surface_data",
        sa.Column("id", sa.BigInteger(), nullable=False),
        sa.Column("appearance_id", sa.BigInteger(), nullable=False),
        sa.Column("ordinal", sa.Integer(), nullable=False),
        sa.Column("kind", sa.Text(), nullable=False),
        sa.Column("gml_id", sa.Text(), nullable=True),
        sa.Column("is_front", sa.Boolean(), nullable=False),
        sa.Column("image_uri", sa.Text(), nullable=True),
        sa.Column("tex_image_id", sa.BigInteger(), nullable=True),
        sa.Column("mime_type", sa.Text(), nullable=True),
        sa.Column("texture_type", sa.Text(), nullable=True),
        sa.Column("wrap_mode", sa.Text(), nullable=True),
        sa.Column("border_color", sa.Text(), nullable=True),
        sa.Column("diffuse_color", postgresql.ARRAY(sa.Double()), nullable=True),
        sa.Column("specular_color", postgresql.ARRAY(sa.Double()), nullable=True),
        sa.Column("emissive_color", postgresql.ARRAY(sa.Double()), nullable=True),
        sa.Column("ambient_intensity", sa.Double(), nullable=True),
        sa.Column("shininess", sa.Double(), nullable=True),
        sa.Column("transparency", sa.Double(), nullable=True),
        sa.Column("is_smooth", sa.Boolean(), nullable=True),
        sa.Column("reference_point", postgresql.ARRAY(sa.Double()), nullable=True),
        sa.Column("orientation", postgresql.ARRAY(sa.Double()), nullable=True),
        sa.Column("prefer_world_file", sa.Boolean(), nullable=True),
        sa.CheckConstraint(
            "kind IN ('ParameterizedTexture', 'X3DMaterial', 'GeoreferencedTexture')",
            name="ck_surface_data_kind",
        ),
        sa.ForeignKeyConstraint(["appearance_id"], ["appearance.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["tex_image_id"], ["tex_image.id"], ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index("ix_surface_data_appearance", "surface_data", ["appearance_id", "ordinal"], unique=False)
    op.create_index("ix_surface_data_tex_image", "surface_data", ["tex_image_id"], unique=False)
    op.create_table(
        "texture_param",
        sa.Column("id", sa.BigInteger(), nullable=False),
        sa.Column("surface_data_id", sa.BigInteger(), nullable=False),
        sa.Column("ordinal", sa.Integer(), nullable=False),
        sa.Column("target_gml_id", sa.Text(), nullable=False),
        sa.Column("surface_id", sa.BigInteger(), nullable=True),
        sa.Column("ring_ids", postgresql.ARRAY(sa.Text()), nullable=True),
        sa.Column("tex_coords", postgresql.JSONB(astext_type=sa.Text()), nullable=True),
        sa.ForeignKeyConstraint(["surface_data_id"], ["surface_data.id"], ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["surface_id"], ["surface.id"], ondelete="CASCADE"),
        sa.PrimaryKeyConstraint("id"),
    )
    op.create_index("ix_texture_param_surface", "texture_param", ["surface_id"], unique=False)
    op.create_index(
        "ix_texture_param_surface_data", "texture_param", ["surface_data_id", "ordinal"], unique=False
    )


def downgrade() -> None:
    op.drop_index("ix_texture_param_surface_data", table_name="texture_param")
    op.drop_index("ix_texture_param_surface", table_name="texture_param")
    op.drop_table("texture_param")
    op.drop_index("ix_surface_data_tex_image", table_name="surface_data")
    op.drop_index("ix_surface_data_appearance", table_name="surface_data")
    op.drop_table("surface_data")
    op.drop_index("ix_thermal_anomaly_surface", table_name="thermal_anomaly")
    op.drop_index("ix_thermal_anomaly_outline", table_name="thermal_anomaly", postgresql_using="gist")
    op.drop_index("ix_thermal_anomaly_job_building", table_name="thermal_anomaly")
    op.drop_index("ix_thermal_anomaly_building", table_name="thermal_anomaly")
    op.drop_index("ix_thermal_anomaly_appearance", table_name="thermal_anomaly")
    op.drop_table("thermal_anomaly")
    op.drop_index("ix_tex_image_sha256", table_name="tex_image")
    op.drop_table("tex_image")
    op.drop_index("ix_surface_thermal_surface", table_name="surface_thermal")
    op.drop_table("surface_thermal")
    op.drop_index("ix_surface_model_gml_id", table_name="surface")
    op.drop_index("ix_surface_geometry", table_name="surface", postgresql_using="gist")
    op.drop_index("ix_surface_building", table_name="surface")
    op.drop_table("surface")
    op.drop_index("ix_job_unit_building", table_name="job_unit")
    op.drop_table("job_unit")
    op.drop_index("ix_frame_pose_frame", table_name="frame_pose")
    op.drop_index("ix_frame_pose_center", table_name="frame_pose", postgresql_using="gist")
    op.drop_index("ix_frame_pose_building", table_name="frame_pose")
    op.drop_table("frame_pose")
    op.drop_index("ix_appearance_model_theme", table_name="appearance")
    op.drop_index("uq_appearance_job_building", table_name="appearance")
    op.drop_index("ix_appearance_building_theme", table_name="appearance")
    op.drop_table("appearance")
    op.drop_index("ix_job_status", table_name="job")
    op.drop_index("ix_job_city_model", table_name="job")
    op.drop_table("job")
    op.drop_table("frame")
    op.drop_index("ix_building_root", table_name="building")
    op.drop_index("ix_building_parent", table_name="building")
    op.drop_index("ix_building_model_ordinal", table_name="building")
    op.drop_index("ix_building_footprint", table_name="building", postgresql_using="gist")
    op.drop_index("ix_building_envelope", table_name="building", postgresql_using="gist")
    op.drop_table("building")
    op.drop_index("ix_sequence_trajectory", table_name="sequence", postgresql_using="gist")
    op.drop_table("sequence")
    op.drop_table("city_model")

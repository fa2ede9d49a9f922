"""The city model database schema (SQLAlchemy 2 typed declarative + GeoAlchemy2).

In: nothing (declarations). Out: ORM classes mirroring the tables the Alembic migrations in
`db/migrations/` create (the migrations are the only way the schema is created or changed; a
test checks that these classes and the migrated database agree).

The appearance part follows CityGML's appearance model as 3DCityDB stores it:
`appearance` (theme; of a building, of the city model, or of a job) → `surface_data`
(`ParameterizedTexture`, `X3DMaterial`, `GeoreferencedTexture`) → `texture_param` (one row per
target polygon: texture coordinates per ring) and `tex_image` (the PNG bytes). A query for one
theme reaches textures only through `appearance.theme`, so it cannot pick another theme's texture.
Per-surface thermal statistics (`surface_thermal`) hang off the appearance as well.

Geometries carry the SRID of their city model (the EPSG code of the model's horizontal CRS, 0
when it has none); columns are typed (`POLYGON Z`, `MULTIPOLYGON`, ...) but not pinned to one SRID
so that models in different CRSs share the tables. Coordinates are stored exactly as read
(float64), in the model CRS, metres.
"""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Any

from geoalchemy2 import Geometry
from sqlalchemy import (
    BigInteger,
    Boolean,
    CheckConstraint,
    DateTime,
    Double,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    SmallInteger,
    Text,
    UniqueConstraint,
    Uuid,
    func,
    text,
)
from sqlalchemy.dialects.postgresql import ARRAY, JSONB
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

#: Job and job unit states (OGC API Processes).
JOB_STATUSES: tuple[str, ...] = ("accepted", "running", "successful", "failed", "dismissed")
#: `surface_data.kind` values (CityGML `_SurfaceData` subtypes).
SURFACE_DATA_KINDS: tuple[str, ...] = ("ParameterizedTexture", "X3DMaterial", "GeoreferencedTexture")


def _geom(geometry_type: str) -> Geometry:
    """A PostGIS geometry column type of `geometry_type` accepting any SRID (typmod SRID 0);
    spatial indexes are declared explicitly in `__table_args__` (and in the migration)."""
    return Geometry(geometry_type=geometry_type, srid=0, spatial_index=False)


class Base(DeclarativeBase):
    """Declarative base of all citytherm tables."""

    type_annotation_map = {  # noqa: RUF012
        dict[str, Any]: JSONB,
        list[Any]: JSONB,
    }


class CityModel(Base):
    """One imported CityGML file."""

    __tablename__ = "city_model"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(Text, unique=True)
    srs_name: Mapped[str | None] = mapped_column(Text)
    srid: Mapped[int] = mapped_column(Integer, default=0)
    vertical_epsg: Mapped[int | None] = mapped_column(Integer)
    citygml_version: Mapped[str | None] = mapped_column(Text)
    gml_name: Mapped[str | None] = mapped_column(Text)
    source_file: Mapped[str | None] = mapped_column(Text)
    imported_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())
    building_count: Mapped[int] = mapped_column(Integer, default=0)
    part_count: Mapped[int] = mapped_column(Integer, default=0)
    surface_count: Mapped[int] = mapped_column(BigInteger, default=0)
    #: "complete" once imported. The importer writes a model in one transaction, so other sessions
    #: see only complete models; "importing" is left only by an import of an older version that
    #: died (the GIS views hide such models; `citytherm db repair` or the next import removes them).
    state: Mapped[str] = mapped_column(Text, default="importing")
    envelope: Mapped[Any | None] = mapped_column(_geom("POLYGONZ"))


class Building(Base):
    """A `bldg:Building` or `bldg:BuildingPart` (parts point to their parent and to their root)."""

    __tablename__ = "building"
    __table_args__ = (
        UniqueConstraint("city_model_id", "gml_id", name="uq_building_model_gml_id"),
        Index("ix_building_parent", "parent_id"),
        Index("ix_building_root", "root_id"),
        Index("ix_building_model_ordinal", "city_model_id", "ordinal"),
        Index("ix_building_footprint", "footprint", postgresql_using="gist"),
        Index("ix_building_envelope", "envelope", postgresql_using="gist"),
    )

    id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    city_model_id: Mapped[int] = mapped_column(ForeignKey("city_model.id", ondelete="CASCADE"))
    gml_id: Mapped[str] = mapped_column(Text)
    parent_id: Mapped[int | None] = mapped_column(ForeignKey("building.id", ondelete="CASCADE"))
    #: the top-level building (itself for a top-level building).
    root_id: Mapped[int | None] = mapped_column(ForeignKey("building.id", ondelete="CASCADE"))
    is_part: Mapped[bool] = mapped_column(Boolean, default=False)
    #: order in the file (top-level buildings and parts share one counter per model).
    ordinal: Mapped[int] = mapped_column(Integer)
    name: Mapped[str | None] = mapped_column(Text)
    srs_name: Mapped[str | None] = mapped_column(Text)
    generated_id: Mapped[bool] = mapped_column(Boolean, default=False)
    attributes: Mapped[dict[str, Any]] = mapped_column(JSONB, default=dict)
    #: 2D footprint (union of ground surfaces, or of downward-facing polygons), parts included.
    footprint: Mapped[Any | None] = mapped_column(_geom("MULTIPOLYGON"))
    #: 3D envelope as 3DCityDB stores it: a POLYGON Z through the box corners (min, max).
    envelope: Mapped[Any | None] = mapped_column(_geom("POLYGONZ"))


class Surface(Base):
    """One surface polygon of a building (rings exterior first), with its plane and checks."""

    __tablename__ = "surface"
    __table_args__ = (
        Index("ix_surface_building", "building_id", "ordinal"),
        Index("ix_surface_model_gml_id", "city_model_id", "gml_id"),
        Index("ix_surface_geometry", "geometry", postgresql_using="gist"),
    )

    id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    #: the model of the owning building (no foreign key: implied by `building_id`, and checking it
    #: doubled the cost of bulk loads; migration 0003).
    city_model_id: Mapped[int] = mapped_column(Integer)
    building_id: Mapped[int] = mapped_column(ForeignKey("building.id", ondelete="CASCADE"))
    ordinal: Mapped[int] = mapped_column(Integer)
    gml_id: Mapped[str] = mapped_column(Text)
    generated_id: Mapped[bool] = mapped_column(Boolean, default=False)
    #: ring gml ids, exterior first; `ring_generated[i]` true when ring i's id was generated.
    ring_ids: Mapped[list[str]] = mapped_column(ARRAY(Text))
    ring_generated: Mapped[list[bool]] = mapped_column(ARRAY(Boolean))
    #: false where the input ring was not closed (the geometry closes it; export drops it again).
    ring_closed: Mapped[list[bool]] = mapped_column(ARRAY(Boolean))
    surface_class: Mapped[str] = mapped_column(Text)
    #: gml id of the thematic surface (e.g. `bldg:WallSurface`) holding the polygon.
    surface_gml_id: Mapped[str | None] = mapped_column(Text)
    lod: Mapped[int] = mapped_column(SmallInteger)
    in_solid: Mapped[bool] = mapped_column(Boolean, default=False)
    #: gml id of the `gml:MultiSurface` / `CompositeSurface` / `Shell` holding the polygon, if any.
    collection_id: Mapped[str | None] = mapped_column(Text)
    #: NULL when PostGIS cannot hold the rings (fewer than 3 distinct vertices): see `raw_rings`.
    geometry: Mapped[Any | None] = mapped_column(_geom("POLYGONZ"))
    #: the rings as `[[[x, y, z], ...], ...]` only when `geometry` is NULL.
    raw_rings: Mapped[list[Any] | None] = mapped_column(JSONB)
    #: plane `normal · x = offset` (unit normal by the right-hand rule of the exterior ring).
    plane_normal: Mapped[list[float] | None] = mapped_column(ARRAY(Double))
    plane_offset: Mapped[float | None] = mapped_column(Double)
    area_m2: Mapped[float | None] = mapped_column(Double)
    #: results of the reader's per-polygon geometry checks.
    checks: Mapped[dict[str, Any] | None] = mapped_column(JSONB)


class Sequence(Base):
    """A TIR image sequence package (`docs/sequence-format.md`)."""

    __tablename__ = "sequence"
    __table_args__ = (Index("ix_sequence_trajectory", "trajectory", postgresql_using="gist"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(Text, unique=True)
    manifest: Mapped[dict[str, Any]] = mapped_column(JSONB)
    storage_location: Mapped[str] = mapped_column(Text)
    frame_count: Mapped[int] = mapped_column(Integer, default=0)
    srs_name: Mapped[str | None] = mapped_column(Text)
    srid: Mapped[int] = mapped_column(Integer, default=0)
    trajectory: Mapped[Any | None] = mapped_column(_geom("LINESTRINGZ"))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())


class Frame(Base):
    """One frame of a sequence with its GNSS/INS prior."""

    __tablename__ = "frame"
    __table_args__ = (UniqueConstraint("sequence_id", "index", name="uq_frame_sequence_index"),)

    id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    sequence_id: Mapped[int] = mapped_column(ForeignKey("sequence.id", ondelete="CASCADE"))
    index: Mapped[int] = mapped_column(Integer)
    file: Mapped[str] = mapped_column(Text)
    time_s: Mapped[float | None] = mapped_column(Double)
    #: prior projection centre (model CRS) and `R_world_from_cam` rows.
    prior_center: Mapped[Any | None] = mapped_column(_geom("POINTZ"))
    prior_rotation: Mapped[list[float] | None] = mapped_column(ARRAY(Double))
    record: Mapped[dict[str, Any] | None] = mapped_column(JSONB)


class Job(Base):
    """A texturing job (OGC API Processes job)."""

    __tablename__ = "job"
    __table_args__ = (
        CheckConstraint(f"status IN {JOB_STATUSES!r}", name="ck_job_status"),
        Index("ix_job_status", "status"),
        Index("ix_job_city_model", "city_model_id"),
    )

    id: Mapped[uuid.UUID] = mapped_column(Uuid, primary_key=True, default=uuid.uuid4)
    city_model_id: Mapped[int] = mapped_column(ForeignKey("city_model.id", ondelete="CASCADE"))
    sequence_id: Mapped[int | None] = mapped_column(ForeignKey("sequence.id", ondelete="SET NULL"))
    theme: Mapped[str] = mapped_column(Text, default="thermal-ir")
    status: Mapped[str] = mapped_column(Text, default="accepted")
    progress: Mapped[float] = mapped_column(Double, default=0.0)
    message: Mapped[str | None] = mapped_column(Text)
    options: Mapped[dict[str, Any]] = mapped_column(JSONB, default=dict)
    mounting: Mapped[dict[str, Any] | None] = mapped_column(JSONB)
    timings_s: Mapped[dict[str, Any]] = mapped_column(JSONB, default=dict)
    error: Mapped[str | None] = mapped_column(Text)
    results_location: Mapped[str | None] = mapped_column(Text)
    #: the stage the job is in: accepted, ingest, calibrate, orient, plan, units, finish.
    stage: Mapped[str] = mapped_column(Text, server_default="accepted")
    #: deliveries of its prepare and finish tasks (bounded: a task whose worker dies every time).
    attempts: Mapped[int] = mapped_column(Integer, server_default="0")
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())
    started_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    updated_at: Mapped[datetime] = mapped_column(
        DateTime(timezone=True), server_default=func.now(), onupdate=func.now()
    )


class JobUnit(Base):
    """One building unit of a job."""

    __tablename__ = "job_unit"
    __table_args__ = (
        UniqueConstraint("job_id", "building_id", name="uq_job_unit_job_building"),
        Index("ix_job_unit_building", "building_id"),
        Index("ix_job_unit_job_status", "job_id", "status"),
        CheckConstraint(f"status IN {JOB_STATUSES!r}", name="ck_job_unit_status"),
    )

    id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    job_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("job.id", ondelete="CASCADE"))
    building_id: Mapped[int] = mapped_column(ForeignKey("building.id", ondelete="CASCADE"))
    status: Mapped[str] = mapped_column(Text, default="accepted")
    progress: Mapped[float] = mapped_column(Double, default=0.0)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    timings_s: Mapped[dict[str, Any]] = mapped_column(JSONB, default=dict)
    error: Mapped[str | None] = mapped_column(Text)
    started_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))
    #: Celery task id of the unit's last delivery (a dismissal revokes it).
    task_id: Mapped[str | None] = mapped_column(Text)
    #: when the unit last started running (the sweeper re-queues units running too long).
    heartbeat_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True))


class FramePose(Base):
    """Orientation of one frame against one top-level building in a job: prior and refined."""

    __tablename__ = "frame_pose"
    __table_args__ = (
        UniqueConstraint("job_id", "building_id", "frame_index", name="uq_frame_pose"),
        Index("ix_frame_pose_center", "center", postgresql_using="gist"),
        Index("ix_frame_pose_building", "building_id"),
        Index("ix_frame_pose_frame", "frame_id"),
    )

    id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    job_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("job.id", ondelete="CASCADE"))
    building_id: Mapped[int] = mapped_column(ForeignKey("building.id", ondelete="CASCADE"))
    frame_index: Mapped[int] = mapped_column(Integer)
    frame_id: Mapped[int | None] = mapped_column(ForeignKey("frame.id", ondelete="SET NULL"))
    #: "refined", or "prior" when refinement was rejected (the refined pose is then the prior).
    status: Mapped[str] = mapped_column(Text)
    prior_center: Mapped[list[float] | None] = mapped_column(ARRAY(Double))
    prior_rotation: Mapped[list[float] | None] = mapped_column(ARRAY(Double))
    refined_center: Mapped[list[float]] = mapped_column(ARRAY(Double))
    #: `R_world_from_cam`, 9 values row by row.
    refined_rotation: Mapped[list[float]] = mapped_column(ARRAY(Double))
    #: the refined projection centre as a point (model SRID), for GIS.
    center: Mapped[Any | None] = mapped_column(_geom("POINTZ"))
    rms_px: Mapped[float | None] = mapped_column(Double)
    matches: Mapped[int] = mapped_column(Integer, default=0)


class Appearance(Base):
    """`app:Appearance`: of a building (`building_id`), of the city model (`building_id` NULL),
    imported from the file (`job_id` NULL) or produced by a job."""

    __tablename__ = "appearance"
    __table_args__ = (
        Index("ix_appearance_building_theme", "building_id", "theme"),
        Index("ix_appearance_model_theme", "city_model_id", "theme"),
        # one appearance per job and building: a result stored twice cannot leave two copies
        Index(
            "uq_appearance_job_building",
            "job_id",
            "building_id",
            unique=True,
            postgresql_where=text("job_id IS NOT NULL"),
        ),
    )

    id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    city_model_id: Mapped[int] = mapped_column(ForeignKey("city_model.id", ondelete="CASCADE"))
    building_id: Mapped[int | None] = mapped_column(ForeignKey("building.id", ondelete="CASCADE"))
    job_id: Mapped[uuid.UUID | None] = mapped_column(ForeignKey("job.id", ondelete="CASCADE"))
    theme: Mapped[str] = mapped_column(Text)
    gml_id: Mapped[str | None] = mapped_column(Text)
    ordinal: Mapped[int] = mapped_column(Integer, default=0)
    #: radiometry of the job's textures: `value = DN · scale + offset` in `unit`.
    radiometry: Mapped[dict[str, Any] | None] = mapped_column(JSONB)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), server_default=func.now())


class TexImage(Base):
    """A texture image (PNG bytes) owned by one appearance."""

    __tablename__ = "tex_image"
    __table_args__ = (
        UniqueConstraint("appearance_id", "uri", name="uq_tex_image_appearance_uri"),
        Index("ix_tex_image_sha256", "sha256"),
    )

    id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    appearance_id: Mapped[int] = mapped_column(ForeignKey("appearance.id", ondelete="CASCADE"))
    #: the `imageURI` relative to a results folder, e.g. `textures/BLDG_0815_0.png`.
    uri: Mapped[str] = mapped_column(Text)
    mime_type: Mapped[str] = mapped_column(Text, default="image/png")
    image: Mapped[bytes] = mapped_column(LargeBinary)
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    bit_depth: Mapped[int] = mapped_column(SmallInteger, default=16)
    radiometry_scale: Mapped[float | None] = mapped_column(Double)
    radiometry_offset: Mapped[float | None] = mapped_column(Double)
    radiometry_unit: Mapped[str | None] = mapped_column(Text)
    sha256: Mapped[str] = mapped_column(Text)


class SurfaceData(Base):
    """`app:_SurfaceData` of an appearance: a `ParameterizedTexture`, `X3DMaterial` or
    `GeoreferencedTexture` (the latter two kept from input appearances)."""

    __tablename__ = "surface_data"
    __table_args__ = (
        CheckConstraint(f"kind IN {SURFACE_DATA_KINDS!r}", name="ck_surface_data_kind"),
        Index("ix_surface_data_appearance", "appearance_id", "ordinal"),
        Index("ix_surface_data_tex_image", "tex_image_id"),
    )

    id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    appearance_id: Mapped[int] = mapped_column(ForeignKey("appearance.id", ondelete="CASCADE"))
    ordinal: Mapped[int] = mapped_column(Integer, default=0)
    kind: Mapped[str] = mapped_column(Text)
    gml_id: Mapped[str | None] = mapped_column(Text)
    is_front: Mapped[bool] = mapped_column(Boolean, default=True)
    # textures
    image_uri: Mapped[str | None] = mapped_column(Text)
    tex_image_id: Mapped[int | None] = mapped_column(ForeignKey("tex_image.id", ondelete="SET NULL"))
    mime_type: Mapped[str | None] = mapped_column(Text)
    texture_type: Mapped[str | None] = mapped_column(Text)
    wrap_mode: Mapped[str | None] = mapped_column(Text)
    border_color: Mapped[str | None] = mapped_column(Text)
    # X3DMaterial
    diffuse_color: Mapped[list[float] | None] = mapped_column(ARRAY(Double))
    specular_color: Mapped[list[float] | None] = mapped_column(ARRAY(Double))
    emissive_color: Mapped[list[float] | None] = mapped_column(ARRAY(Double))
    ambient_intensity: Mapped[float | None] = mapped_column(Double)
    shininess: Mapped[float | None] = mapped_column(Double)
    transparency: Mapped[float | None] = mapped_column(Double)
    is_smooth: Mapped[bool | None] = mapped_column(Boolean)
    # GeoreferencedTexture
    reference_point: Mapped[list[float] | None] = mapped_column(ARRAY(Double))
    orientation: Mapped[list[float] | None] = mapped_column(ARRAY(Double))
    prefer_world_file: Mapped[bool | None] = mapped_column(Boolean)


class TextureParam(Base):
    """One target polygon of a surface data item; for a `ParameterizedTexture` with the texture
    coordinates per ring (`tex_coords[i]` = `[[s, t], ...]` of ring `ring_ids[i]`, closing vertex
    included; s right, t up, (0, 0) lower-left of the image)."""

    __tablename__ = "texture_param"
    __table_args__ = (
        Index("ix_texture_param_surface_data", "surface_data_id", "ordinal"),
        Index("ix_texture_param_surface", "surface_id"),
    )

    id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    surface_data_id: Mapped[int] = mapped_column(ForeignKey("surface_data.id", ondelete="CASCADE"))
    ordinal: Mapped[int] = mapped_column(Integer, default=0)
    #: the target polygon's gml id (the `uri` without `#`), and the surface row when it resolves.
    target_gml_id: Mapped[str] = mapped_column(Text)
    surface_id: Mapped[int | None] = mapped_column(ForeignKey("surface.id", ondelete="CASCADE"))
    ring_ids: Mapped[list[str] | None] = mapped_column(ARRAY(Text))
    tex_coords: Mapped[list[Any] | None] = mapped_column(JSONB)


class SurfaceThermal(Base):
    """Thermal statistics of one surface in one appearance (theme/job); temperatures in kelvin
    (NULL when the radiometry unit is `counts`; the raw figures are kept in `temperature`)."""

    __tablename__ = "surface_thermal"
    __table_args__ = (
        UniqueConstraint("appearance_id", "surface_id", name="uq_surface_thermal"),
        Index("ix_surface_thermal_surface", "surface_id"),
    )

    id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    appearance_id: Mapped[int] = mapped_column(ForeignKey("appearance.id", ondelete="CASCADE"))
    surface_id: Mapped[int] = mapped_column(ForeignKey("surface.id", ondelete="CASCADE"))
    texels_total: Mapped[int] = mapped_column(Integer)
    texels_observed: Mapped[int] = mapped_column(Integer)
    observed_share: Mapped[float] = mapped_column(Double)
    frames_used: Mapped[list[int]] = mapped_column(ARRAY(Integer))
    resolution_m: Mapped[float | None] = mapped_column(Double)
    view_angle_deg: Mapped[float | None] = mapped_column(Double)
    mean_k: Mapped[float | None] = mapped_column(Double)
    median_k: Mapped[float | None] = mapped_column(Double)
    std_k: Mapped[float | None] = mapped_column(Double)
    min_k: Mapped[float | None] = mapped_column(Double)
    max_k: Mapped[float | None] = mapped_column(Double)
    p05_k: Mapped[float | None] = mapped_column(Double)
    p25_k: Mapped[float | None] = mapped_column(Double)
    p75_k: Mapped[float | None] = mapped_column(Double)
    p95_k: Mapped[float | None] = mapped_column(Double)
    #: the statistics as produced, in `unit`.
    temperature: Mapped[dict[str, Any]] = mapped_column(JSONB, default=dict)
    unit: Mapped[str | None] = mapped_column(Text)
    #: texels per metre of the surface's grid, best local resolution of its observations (m/px),
    #: mean observations per fused texel, why a surface the frames see got no texel (0009).
    resolution_px_per_m: Mapped[float | None] = mapped_column(Double)
    best_resolution_m: Mapped[float | None] = mapped_column(Double)
    mean_observations: Mapped[float | None] = mapped_column(Double)
    reason: Mapped[str | None] = mapped_column(Text)
    #: facade figures of the anomaly analysis (0010; docs/anomalies.md): typical temperature and
    #: its robust spread (kelvin), shares of the observed area above typical and in windows,
    #: heat-loss index (kelvin), numbers of windows and leak candidates.
    typical_k: Mapped[float | None] = mapped_column(Double)
    spread_k: Mapped[float | None] = mapped_column(Double)
    hot_share: Mapped[float | None] = mapped_column(Double)
    window_share: Mapped[float | None] = mapped_column(Double)
    heat_loss_index: Mapped[float | None] = mapped_column(Double)
    windows: Mapped[int | None] = mapped_column(Integer)
    leaks: Mapped[int | None] = mapped_column(Integer)
    #: the facade's GeoJSON Feature in CRS84 as the OGC API - Features service writes it, and the
    #: fingerprint of the definition that wrote it (0012; `db.facade_features`)
    feature: Mapped[str | None] = mapped_column(Text)
    feature_spec: Mapped[int | None] = mapped_column(Integer)


class ThermalAnomaly(Base):
    """A heat-leak candidate found by a job on one surface."""

    __tablename__ = "thermal_anomaly"
    __table_args__ = (
        Index("ix_thermal_anomaly_job_building", "job_id", "building_id"),
        Index("ix_thermal_anomaly_outline", "outline", postgresql_using="gist"),
        Index("ix_thermal_anomaly_building", "building_id"),
        Index("ix_thermal_anomaly_surface", "surface_id"),
        Index("ix_thermal_anomaly_appearance", "appearance_id"),
    )

    id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    job_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("job.id", ondelete="CASCADE"))
    appearance_id: Mapped[int | None] = mapped_column(ForeignKey("appearance.id", ondelete="CASCADE"))
    building_id: Mapped[int] = mapped_column(ForeignKey("building.id", ondelete="CASCADE"))
    surface_id: Mapped[int | None] = mapped_column(ForeignKey("surface.id", ondelete="CASCADE"))
    kind: Mapped[str] = mapped_column(Text, default="leak")
    outline: Mapped[Any | None] = mapped_column(_geom("POLYGONZ"))
    centre: Mapped[list[float]] = mapped_column(ARRAY(Double))
    area_m2: Mapped[float] = mapped_column(Double)
    peak_delta_k: Mapped[float] = mapped_column(Double)
    mean_delta_k: Mapped[float] = mapped_column(Double)
    #: the detector's stable id, distinct frames, best resolution (m/px) and confidence (0010).
    anomaly_id: Mapped[str | None] = mapped_column(Text)
    frames: Mapped[int | None] = mapped_column(Integer)
    best_resolution_m: Mapped[float | None] = mapped_column(Double)
    confidence: Mapped[float | None] = mapped_column(Double)

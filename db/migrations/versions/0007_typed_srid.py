"""Every geometry column typed with one SRID, the database's (as 3DCityDB keeps one SRID per
database), so that GDAL, QGIS and plain SQL see one declared CRS per layer and a scan never meets
mixed SRIDs.

The SRID is the `database_srid` attribute of the Alembic config (`db.migrations.upgrade(url,
srid=...)`, `citytherm db upgrade --srid`), else `-x srid=N` on the alembic command line, else
`CITYTHERM_DATABASE_SRID`, else 25832 (ETRS89 / UTM 32N). It must be a projected CRS in metres
that PostGIS knows. Rows already stored in another SRID are transformed (`ST_Transform`,
horizontal; heights kept); rows with SRID 0 (a model imported without a CRS by an older version)
stop the migration with a message naming the model. The GIS views are re-created with the typed
geometry columns (their comments kept). Downgrade leaves the columns untyped (SRID 0 typmod), the
coordinates as they are.

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-25 20:30:00
"""

from __future__ import annotations

import os
import re

from alembic import context, op
from sqlalchemy import text

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None

#: (table, column, PostGIS geometry type) of every geometry column
COLUMNS = (
    ("city_model", "envelope", "PolygonZ"),
    ("building", "footprint", "MultiPolygon"),
    ("building", "envelope", "PolygonZ"),
    ("surface", "geometry", "PolygonZ"),
    ("sequence", "trajectory", "LineStringZ"),
    ("frame", "prior_center", "PointZ"),
    ("frame_pose", "center", "PointZ"),
    ("thermal_anomaly", "outline", "PolygonZ"),
)
VIEWS = ("facade_thermal", "building_thermal")
DEFAULT_SRID = 25832


def target_srid() -> int:
    """The database SRID this migration types the columns with (see the module docstring)."""
    cfg = context.config
    value = cfg.attributes.get("database_srid") or context.get_x_argument(as_dictionary=True).get("srid")
    value = value or os.environ.get("CITYTHERM_DATABASE_SRID") or DEFAULT_SRID
    try:
        return int(str(value).upper().removeprefix("EPSG:"))
    except ValueError as exc:
        raise ValueError(f"database SRID: {value!r} is not an EPSG code") from exc


def _check_srid(srid: int) -> None:
    bind = op.get_bind()
    row = bind.execute(text("SELECT proj4text FROM spatial_ref_sys WHERE srid = :s"), {"s": srid}).first()
    if row is None:
        raise ValueError(f"database SRID {srid}: PostGIS does not know EPSG:{srid}")
    proj4 = row[0] or ""
    if "+proj=longlat" in proj4 or "+units=m" not in proj4:
        raise ValueError(f"database SRID {srid}: not a projected CRS in metres ({proj4.strip()})")


def _views() -> list[tuple[str, str, str | None]]:
    bind = op.get_bind()
    out = []
    for name in VIEWS:
        row = bind.execute(
            text("SELECT pg_get_viewdef(c.oid, true), obj_description(c.oid, 'pg_class') FROM pg_class c "
                 "WHERE c.relname = :v AND c.relkind = 'v'"),
            {"v": name},
        ).first()
        if row is not None:
            out.append((name, row[0], row[1]))
    return out


def _recreate(views: list[tuple[str, str, str | None]], srid: int | None) -> None:
    """Create the views again; with `srid`, their geometry casts typed with it, else untyped."""
    bind = op.get_bind()
    for name, body, comment in views:
        if srid is None:
            body = re.sub(r"geometry\((\w+),\s*\d+\)", r"geometry(\1)", body)
        else:
            body = re.sub(r"geometry\((\w+)\)", rf"geometry(\1,{srid})", body)
        bind.execute(text(f"CREATE VIEW {name} AS {body}"))
        if comment:
            comment = comment.replace("model SRID", "database SRID") if srid else comment.replace(
                "database SRID", "model SRID"
            )
            quoted = comment.replace("'", "''")
            bind.execute(text(f"COMMENT ON VIEW {name} IS '{quoted}'"))


def upgrade() -> None:
    srid = target_srid()
    _check_srid(srid)
    bind = op.get_bind()
    untyped = bind.execute(
        text("SELECT name FROM city_model m WHERE EXISTS (SELECT 1 FROM building b WHERE "
             "b.city_model_id = m.id AND (ST_SRID(b.envelope) = 0 OR ST_SRID(b.footprint) = 0))")
    ).scalars().all()
    if untyped:
        raise ValueError(
            f"city models without a CRS (SRID 0): {', '.join(untyped)}; delete them "
            "(citytherm model delete NAME) and import them again with --crs EPSG:xxxx"
        )
    views = _views()
    for name, _, _ in views:
        op.execute(f"DROP VIEW {name}")
    for table, column, gtype in COLUMNS:
        op.execute(
            f"ALTER TABLE {table} ALTER COLUMN {column} TYPE geometry({gtype}, {srid}) USING "
            f"CASE WHEN ST_SRID({column}) = {srid} THEN {column} "
            f"WHEN ST_SRID({column}) = 0 THEN ST_SetSRID({column}, {srid}) "
            f"ELSE ST_Transform({column}, {srid}) END"
        )
    _recreate(views, srid)


def downgrade() -> None:
    views = _views()
    for name, _, _ in views:
        op.execute(f"DROP VIEW {name}")
    for table, column, gtype in COLUMNS:
        op.execute(f"ALTER TABLE {table} ALTER COLUMN {column} TYPE geometry({gtype}) USING {column}")
    _recreate(views, None)

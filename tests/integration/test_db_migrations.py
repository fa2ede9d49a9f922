"""Alembic migrations: an empty PostGIS database goes up to head and back down to nothing, and the
migrated schema matches the SQLAlchemy models."""

from __future__ import annotations

from collections.abc import Iterator

import psycopg
import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from geoalchemy2 import Geometry

import db.service_models  # noqa: F401  (registers the service tables on Base.metadata)
from db.migrations import current_revision, downgrade, head_revision, upgrade
from db.models import Base
from db.session import make_engine
from tests.integration.conftest import PG_SERVER, TEST_DB

pytestmark = pytest.mark.integration

MIG_DB = f"{TEST_DB}_migrations"
TABLES = {
    "city_model", "building", "surface", "sequence", "frame", "job", "job_unit", "frame_pose", "appearance",
    "surface_data", "tex_image", "texture_param", "surface_thermal", "thermal_anomaly", "api_key",
    "model_import", "sequence_upload",
}  # fmt: skip
VIEWS = {"facade_thermal", "building_thermal", "thermal_anomalies", "surface_thermal_change"}


def _admin(sql: str) -> None:
    with psycopg.connect(f"{PG_SERVER}/postgres", autocommit=True) as conn:
        conn.execute("SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s", (MIG_DB,))
        conn.execute(sql)


@pytest.fixture()
def empty_db() -> Iterator[str]:
    """A fresh database with only the PostGIS extension."""
    _admin(f'DROP DATABASE IF EXISTS "{MIG_DB}"')
    _admin(f'CREATE DATABASE "{MIG_DB}"')
    url = f"{PG_SERVER}/{MIG_DB}"
    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute("CREATE EXTENSION IF NOT EXISTS postgis")
    yield url
    _admin(f'DROP DATABASE IF EXISTS "{MIG_DB}"')


def _relations(url: str) -> tuple[set[str], set[str]]:
    with psycopg.connect(url) as conn:
        tables = {r[0] for r in conn.execute("SELECT tablename FROM pg_tables WHERE schemaname = 'public'")}
        views = {r[0] for r in conn.execute("SELECT viewname FROM pg_views WHERE schemaname = 'public'")}
    return tables - {"spatial_ref_sys", "alembic_version"}, views - {"geography_columns", "geometry_columns"}


def _same_geometry_type(diff: object) -> bool:
    """Reflection reports typmod SRID 0 as unset: not a difference when type and dimension agree."""
    d = diff[0] if isinstance(diff, list) else diff
    if not (isinstance(d, tuple) and d[0] == "modify_type"):
        return False
    a, b = d[5], d[6]
    return (
        isinstance(a, Geometry)
        and isinstance(b, Geometry)
        and (a.geometry_type, a.dimension) == (b.geometry_type, b.dimension)
    )


def test_upgrade_then_downgrade_empty_database(empty_db: str) -> None:
    assert current_revision(empty_db) is None
    upgrade(empty_db)
    assert current_revision(empty_db) == head_revision()
    tables, views = _relations(empty_db)
    assert tables == TABLES
    assert views == VIEWS
    # the models and the migrated schema agree (no autogenerate differences)
    engine = make_engine(empty_db)
    try:
        with engine.connect() as conn:
            ctx = MigrationContext.configure(
                conn,
                opts={
                    "include_name": lambda name, type_, parents: (
                        type_ != "table" or name in Base.metadata.tables
                    )
                },
            )
            diffs = compare_metadata(ctx, Base.metadata)
    finally:
        engine.dispose()
    assert [d for d in diffs if not _same_geometry_type(d)] == []
    # the views are typed for GIS clients
    with psycopg.connect(empty_db) as conn:
        geo = dict(
            conn.execute(
                "SELECT f_table_name, type FROM geometry_columns WHERE f_table_name IN "
                "('facade_thermal', 'building_thermal')"
            ).fetchall()
        )
    assert geo == {"facade_thermal": "POLYGON", "building_thermal": "MULTIPOLYGON"}
    downgrade(empty_db, "base")
    assert current_revision(empty_db) is None
    assert _relations(empty_db) == (set(), set())
    upgrade(empty_db)  # and up again from scratch
    assert _relations(empty_db) == (TABLES, VIEWS)


def _model_with_box(conn: psycopg.Connection, name: str, srid: int, x: float, y: float) -> None:
    """A city model row and one building whose envelope is a box at (x, y) in `srid`."""
    mid = conn.execute(
        "INSERT INTO city_model (name, srs_name, srid, building_count, part_count, surface_count, state) "
        "VALUES (%s, %s, %s, 1, 0, 0, 'complete') RETURNING id",
        (name, f"EPSG:{srid}", srid),
    ).fetchone()[0]
    conn.execute(
        "INSERT INTO building (id, city_model_id, gml_id, is_part, ordinal, generated_id, attributes, "
        "envelope) VALUES (nextval('building_id_seq'), %s, 'B', false, 0, false, '{}', "
        "ST_SetSRID(ST_MakePolygon(ST_MakeLine(ARRAY[ST_MakePoint(%s, %s, 0), ST_MakePoint(%s + 1, %s, 0), "
        "ST_MakePoint(%s + 1, %s + 1, 10), ST_MakePoint(%s, %s, 0)])), %s))",
        (mid, x, y, x, y, x, y, x, y, srid),
    )


def test_typing_a_database_of_mixed_srids_transforms_the_other_rows(empty_db: str) -> None:
    """Revision 0007 on a database where models of two CRSs share untyped columns: the rows of the
    other CRS are transformed (PostGIS ST_Transform, heights kept), every column is typed; a model
    without a CRS (SRID 0) stops the migration and names it."""
    upgrade(empty_db, "0006")
    with psycopg.connect(empty_db) as conn:
        _model_with_box(conn, "berlin", 25833, 392000.0, 5820000.0)
        _model_with_box(conn, "nrw", 25832, 360000.0, 5660000.0)
        _model_with_box(conn, "nowhere", 0, 10.0, 20.0)
    with pytest.raises(ValueError, match="nowhere"):
        upgrade(empty_db, srid=25833)
    assert current_revision(empty_db) == "0006"
    with psycopg.connect(empty_db) as conn:
        conn.execute("DELETE FROM city_model WHERE name = 'nowhere'")
    upgrade(empty_db, srid=25833)
    with psycopg.connect(empty_db) as conn:
        srids = {r[0] for r in conn.execute("SELECT DISTINCT srid FROM geometry_columns")}
        rows = dict(
            conn.execute(
                "SELECT m.name, ARRAY[ST_X(p), ST_Y(p), ST_ZMax(b.envelope), ST_SRID(b.envelope)] "
                "FROM building b JOIN city_model m ON m.id = b.city_model_id, "
                "ST_PointN(ST_ExteriorRing(b.envelope), 1) p"
            ).fetchall()
        )
    assert srids == {25833}
    assert rows["berlin"] == [392000.0, 5820000.0, 10.0, 25833.0]  # already in the database SRID
    import pyproj

    x, y = pyproj.Transformer.from_crs(25832, 25833, always_xy=True).transform(360000.0, 5660000.0)
    nx, ny, nz, ns = rows["nrw"]
    assert (ns, nz) == (25833.0, 10.0) and abs(nx - x) < 1e-3 and abs(ny - y) < 1e-3
    assert nx < 0  # the Ruhr lies west of UTM zone 33's false origin

"""Alembic migrations: an empty PostGIS database goes up to head and back down to nothing, and the
migrated schema matches the SQLAlchemy models."""

from __future__ import annotations

from collections.abc import Iterator

import psycopg
import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from geoalchemy2 import Geometry

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
VIEWS = {"facade_thermal", "building_thermal"}


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

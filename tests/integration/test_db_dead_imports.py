"""Models left `importing` by dead imports (an older version's, which committed batch by batch and
dropped the spatial indexes), on a real PostGIS: the GIS views never show them, `citytherm db
repair` removes them (leaving a running import alone) and rebuilds a missing spatial index, and
the next import removes them too.
"""

from __future__ import annotations

from collections.abc import Iterator

import psycopg
import pytest
from typer.testing import CliRunner

from db.importer import import_citygml
from db.ops import IMPORT_MODEL_LOCK
from services.cli import app
from tests.conftest import DATA
from tests.integration.conftest import scalar

pytestmark = [pytest.mark.integration]


def _thermal_rows(conn: psycopg.Connection, model_id: int) -> None:
    """One textured surface with thermal statistics (what a job writes), for the GIS views."""
    sid, bid = conn.execute(
        "SELECT s.id, b.id FROM surface s JOIN building b ON b.id = s.building_id "
        "WHERE s.city_model_id = %s AND NOT b.is_part ORDER BY s.id LIMIT 1",
        (model_id,),
    ).fetchone()
    aid = conn.execute(
        "INSERT INTO appearance (city_model_id, building_id, theme, ordinal) "
        "VALUES (%s, %s, 'thermal-ir', 0) RETURNING id",
        (model_id, bid),
    ).fetchone()[0]
    sdid = conn.execute(
        "INSERT INTO surface_data (appearance_id, ordinal, kind, is_front) "
        "VALUES (%s, 0, 'ParameterizedTexture', true) RETURNING id",
        (aid,),
    ).fetchone()[0]
    conn.execute(
        "INSERT INTO texture_param (surface_data_id, ordinal, target_gml_id, surface_id) "
        "VALUES (%s, 0, 'x', %s)",
        (sdid, sid),
    )
    conn.execute(
        "INSERT INTO surface_thermal (appearance_id, surface_id, texels_total, texels_observed, "
        "observed_share, frames_used, mean_k, temperature) VALUES (%s, %s, 10, 5, 0.5, '{1}', 280.0, '{}')",
        (aid, sid),
    )


def _view_rows(url: str, model_id: int) -> tuple[int, int]:
    with psycopg.connect(url, autocommit=True) as c:
        return c.execute(
            "SELECT (SELECT count(*) FROM facade_thermal WHERE city_model_id = %(m)s), "
            "(SELECT count(*) FROM building_thermal WHERE city_model_id = %(m)s)",
            {"m": model_id},
        ).fetchone()


@pytest.fixture()
def dead_import(migrated_db, db_engine) -> Iterator[int]:
    """A model left `importing` by a dead import of an older version (which committed batch by
    batch and dropped the spatial indexes): a half-written model with thermal rows."""
    s = import_citygml(db_engine, DATA / "bavaria-1-building-citygml2-lod2.gml", name="faults-dead")
    with psycopg.connect(migrated_db) as c:
        _thermal_rows(c, s.model_id)
    assert _view_rows(migrated_db, s.model_id) == (1, 1)
    with psycopg.connect(migrated_db) as c:
        c.execute("UPDATE city_model SET state = 'importing' WHERE id = %s", (s.model_id,))
    yield s.model_id
    with psycopg.connect(migrated_db) as c:
        c.execute("DELETE FROM city_model WHERE id = %s", (s.model_id,))


def test_views_hide_and_repair_removes_a_dead_import(migrated_db, dead_import) -> None:
    m = dead_import
    assert _view_rows(migrated_db, m) == (0, 0)  # the views show complete models only
    with psycopg.connect(migrated_db, autocommit=True) as c:
        c.execute("DROP INDEX ix_surface_geometry")  # as an older version's import did
    runner = CliRunner()
    url = ["--database-url", migrated_db]
    res = runner.invoke(app, ["db", "repair", "--dry-run", *url])
    assert res.exit_code == 0, res.output
    out = " ".join(res.output.split())
    assert f"model faults-dead (id {m}, 'importing'): would remove (1 buildings, 0 parts, 84 surfaces)" in out
    assert "ix_surface_geometry on surface(geometry) missing: would rebuild" in out
    assert scalar(migrated_db, "SELECT count(*) FROM surface WHERE city_model_id = %s", (m,)) == 84
    # an import still running holds its model's lock: left alone
    with psycopg.connect(migrated_db, autocommit=True) as owner:
        owner.execute("SELECT pg_advisory_lock(%s, %s)", (IMPORT_MODEL_LOCK, m))
        res = runner.invoke(app, ["db", "repair", *url])
        assert res.exit_code == 0, res.output
        assert "left alone (import running)" in res.output
        assert scalar(migrated_db, "SELECT state FROM city_model WHERE id = %s", (m,)) == "importing"
    res = runner.invoke(app, ["db", "repair", *url])
    assert res.exit_code == 0, res.output
    out = " ".join(res.output.split())
    assert f"model faults-dead (id {m}, 'importing'): removed (1 buildings, 0 parts, 84 surfaces)" in out
    assert scalar(migrated_db, "SELECT count(*) FROM city_model WHERE id = %s", (m,)) == 0
    assert scalar(migrated_db, "SELECT count(*) FROM surface WHERE city_model_id = %s", (m,)) == 0
    assert scalar(migrated_db, "SELECT count(*) FROM building WHERE city_model_id = %s", (m,)) == 0
    assert scalar(
        migrated_db, "SELECT indisvalid FROM pg_index WHERE indexrelid = to_regclass('ix_surface_geometry')"
    )
    res = runner.invoke(app, ["db", "repair", *url])
    assert res.exit_code == 0 and "nothing to repair" in res.output


def test_next_import_removes_a_dead_import(migrated_db, db_engine, dead_import) -> None:
    s = import_citygml(db_engine, DATA / "fzk-haus-citygml3-lod2.gml", name="faults-next")
    assert s.removed_dead_imports == 1
    assert scalar(migrated_db, "SELECT count(*) FROM city_model WHERE id = %s", (dead_import,)) == 0
    assert scalar(migrated_db, "SELECT count(*) FROM city_model WHERE state <> 'complete'") == 0
    with psycopg.connect(migrated_db, autocommit=True) as c:
        c.execute("DELETE FROM city_model WHERE id = %s", (s.model_id,))

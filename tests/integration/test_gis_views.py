"""The GIS views on a real PostGIS: `building_thermal` carries the attributes a GIS filters on as
typed columns (from the building's JSONB as the real sample writes them)."""

from __future__ import annotations

import uuid

import pytest
from sqlalchemy import text
from sqlalchemy.orm import Session

from db.citygml.reader import read_model
from db.importer import import_citygml
from db.store import create_job, store_building_result
from tests.conftest import sample
from tests.integration.test_db_store_export import make_result
from workers.pipeline.geometry.manifest import Radiometry

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def textured(db_engine):
    """The Bavaria sample imported with one stored job result: (model name, model id, building)."""
    path = sample("bavaria-1-building-citygml2-lod2.gml")
    _, (building,) = read_model(path)
    name = f"gis-views-{uuid.uuid4().hex[:8]}"
    model_id = import_citygml(db_engine, path, name=name).model_id
    with Session(db_engine) as session:
        job = create_job(session, model_id=model_id, theme="tir-views")
        session.commit()
        store_building_result(session, job_id=job, model_id=model_id,
                              result=make_result(building, "tir-views", 3, Radiometry()))
    return name, model_id, building


COLUMNS = ("measured_height_m", "function", "year_of_construction", "roof_type", "storeys_above_ground")


def test_building_thermal_has_typed_attribute_columns(db_engine, textured) -> None:
    name, _, building = textured
    with db_engine.connect() as c:
        row = c.execute(
            text(f"SELECT {', '.join(COLUMNS)}, attributes FROM building_thermal WHERE model_name = :n"),
            {"n": name},
        ).mappings().one()
        types = dict(c.execute(
            text(
                "SELECT column_name, data_type FROM information_schema.columns "
                "WHERE table_name = 'building_thermal' AND column_name = ANY(:c)"
            ),
            {"c": [*COLUMNS, "attributes"]},
        ).all())
        picked = c.execute(
            text("SELECT count(*) FROM building_thermal WHERE model_name = :n AND measured_height_m > 30 "
                 "AND storeys_above_ground >= 6 AND roof_type = '3200'"),
            {"n": name},
        ).scalar_one()
    attrs = building.attributes
    assert row["measured_height_m"] == pytest.approx(attrs["measuredHeight"])  # 37.54 in the file
    assert row["function"] == attrs["function"] and row["roof_type"] == attrs["roofType"]
    assert row["storeys_above_ground"] == attrs["storeysAboveGround"] == 6
    assert row["year_of_construction"] is None  # the file has none
    assert row["attributes"]["measuredHeight"] == attrs["measuredHeight"]
    assert types == {
        "measured_height_m": "double precision",
        "function": "text",
        "year_of_construction": "integer",
        "roof_type": "text",
        "storeys_above_ground": "integer",
        "attributes": "jsonb",
    }
    assert picked == 1


@pytest.mark.parametrize(
    ("doc", "want"),
    [
        ('{"measuredHeight": "12.5", "storeysAboveGround": "3", "yearOfConstruction": "1905-01-01"}',
         (12.5, None, 1905, None, 3)),
        ('{"measuredHeight": "unknown", "storeysAboveGround": "2.5", "function": ["1000", "2000"]}',
         (None, "1000", None, None, None)),
        ('{"measuredHeight": 7, "yearOfConstruction": "ca. 1900", "roofType": 3100}',
         (7.0, None, None, "3100", None)),
    ],
)
def test_attribute_values_that_do_not_read_as_their_type_are_null(db_engine, textured, doc, want) -> None:
    """The view on attribute documents as other files write them (strings, arrays, dates): the
    building's JSONB replaced inside a transaction that is rolled back."""
    name, model_id, _ = textured
    with db_engine.connect() as c, c.begin() as tx:
        c.execute(
            text("UPDATE building SET attributes = CAST(:d AS jsonb) "
                 "WHERE city_model_id = :m AND NOT is_part"),
            {"d": doc, "m": model_id},
        )
        got = c.execute(
            text(f"SELECT {', '.join(COLUMNS)} FROM building_thermal WHERE model_name = :n"), {"n": name}
        ).one()
        tx.rollback()
    assert tuple(got) == want

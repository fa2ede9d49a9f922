"""One typed SRID per database (issue 13): two real models in different CRSs (Berlin, EPSG:25833;
NRW, EPSG:25832) in one database, read as GIS clients read it.

- every geometry column and view declares the database SRID (`geometry_columns`);
- GDAL (`ogrinfo`, an independent client) reports that CRS and an extent holding both models'
  real positions;
- a spatial query that scans (index scans off) works: no "mixed SRID" error;
- the NRW model's vertices are where PostGIS' own `ST_Transform` (PROJ through
  `spatial_ref_sys`, not our code path) puts the file's coordinates, heights kept;
- the export gives the NRW file's coordinates back in its own CRS;
- a file with no srsName is refused (naming the file and `--crs`) unless the CRS is given; an
  unknown CRS is refused; nothing is written for either.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import text

from db.citygml.reader import read_model
from db.errors import InputDataError
from db.export import export_citygml
from db.importer import ImportOptions, import_citygml
from tests.integration.conftest import TEST_SRID
from workers.pipeline.synth import BUNDLED_MODEL

pytestmark = pytest.mark.integration

DATA = Path(__file__).resolve().parents[1] / "data"
NRW = DATA / "nrw-tile-5659-citygml1-lod2.gml"
BAVARIA = DATA / "bavaria-1-building-citygml2-lod2.gml"


@pytest.fixture(scope="module")
def two_crs(db_engine):
    """The Berlin (25833) and NRW (25832) models imported into the test database."""
    berlin = import_citygml(db_engine, BUNDLED_MODEL, name="srid-berlin", replace=True)
    nrw = import_citygml(db_engine, NRW, name="srid-nrw", replace=True)
    return berlin, nrw


def _libpq(url: str) -> str:
    m = re.match(r"postgresql(?:\+\w+)?://(\w+)@([\w.]+):(\d+)/(\w+)", url)
    assert m, url
    user, host, port, db = m.groups()
    return f"PG:dbname={db} host={host} port={port} user={user}"


def test_every_geometry_column_and_view_has_the_database_srid(two_crs, db_engine) -> None:
    berlin, nrw = two_crs
    assert (berlin.srid, nrw.srid) == (25833, 25832)  # the models' own CRSs are kept
    with db_engine.connect() as c:
        rows = c.execute(
            text(
                "SELECT f_table_name, f_geometry_column, srid, type FROM geometry_columns "
                "WHERE f_table_schema = current_schema() ORDER BY 1, 2"
            )
        ).all()
        stored = c.execute(
            text(
                "SELECT DISTINCT ST_SRID(geometry) FROM surface WHERE city_model_id IN (:a, :b) "
                "UNION SELECT DISTINCT ST_SRID(footprint) FROM building WHERE city_model_id IN (:a, :b)"
            ),
            {"a": berlin.model_id, "b": nrw.model_id},
        ).scalars().all()
    layers = {(t, col): (srid, gtype) for t, col, srid, gtype in rows}
    expected = {
        ("city_model", "envelope"), ("building", "footprint"), ("building", "envelope"),
        ("surface", "geometry"), ("sequence", "trajectory"), ("frame", "prior_center"),
        ("frame_pose", "center"), ("thermal_anomaly", "outline"), ("facade_thermal", "geometry"),
        ("building_thermal", "footprint"),
    }  # fmt: skip
    assert expected <= set(layers)
    assert {srid for srid, _ in layers.values()} == {TEST_SRID}, layers
    assert layers[("facade_thermal", "geometry")][1] == "POLYGON"
    assert set(stored) == {TEST_SRID}


def test_ogrinfo_reports_the_crs_and_an_extent_holding_both_models(two_crs, migrated_db) -> None:
    out = subprocess.run(
        ["ogrinfo", "-ro", "-so", _libpq(migrated_db), "surface"],
        capture_output=True, text=True, timeout=60, check=True,
    ).stdout  # fmt: skip
    assert f'ID["EPSG",{TEST_SRID}]]' in out, out
    m = re.search(r"Extent: \(([-\d.]+), ([-\d.]+)\) - \(([-\d.]+), ([-\d.]+)\)", out)
    assert m, out
    x0, y0, x1, y1 = (float(v) for v in m.groups())
    # real positions, in the database SRID: Berlin's model as written (it is in 25833), NRW's
    # file coordinates transformed by PROJ (pyproj, the same library GDAL uses)
    import pyproj

    _, berlin = read_model(BUNDLED_MODEL)
    _, nrw = read_model(NRW)
    to_db = pyproj.Transformer.from_crs("EPSG:25832", f"EPSG:{TEST_SRID}", always_xy=True)
    points = []
    for b in berlin[:3]:
        points.append(next(b.iter_polygons()).exterior.coords[0, :2])
    for b in nrw[:3]:
        x, y = next(b.iter_polygons()).exterior.coords[0, :2]
        points.append(np.array(to_db.transform(x, y)))
    for x, y in points:
        assert x0 <= x <= x1 and y0 <= y <= y1, ((x, y), (x0, y0, x1, y1))
    # the two models lie about 300 km apart (Berlin and the Ruhr): the extent spans both
    assert x1 - x0 > 300_000


def test_a_scanning_spatial_query_meets_one_srid(two_crs, db_engine) -> None:
    berlin, nrw = two_crs
    with db_engine.connect() as c:
        c.execute(text("SET enable_indexscan = off"))
        c.execute(text("SET enable_bitmapscan = off"))
        c.execute(text("SET enable_seqscan = on"))
        plan = "\n".join(
            c.execute(
                text(
                    "EXPLAIN SELECT count(*) FROM surface WHERE ST_Intersects(geometry, "
                    "ST_Expand(ST_SetSRID(ST_MakePoint(0, 0), :s), 1e7))"
                ),
                {"s": TEST_SRID},
            ).scalars()
        )
        assert "Seq Scan" in plan and "Index" not in plan, plan
        n = c.execute(
            text(
                "SELECT count(*) FROM surface WHERE city_model_id IN (:a, :b) AND ST_Intersects(geometry, "
                "ST_Expand(ST_SetSRID(ST_MakePoint(0, 0), :s), 1e7))"
            ),
            {"a": berlin.model_id, "b": nrw.model_id, "s": TEST_SRID},
        ).scalar_one()
    assert n == berlin.surfaces + nrw.surfaces


def test_nrw_vertices_are_where_postgis_transforms_them(two_crs, db_engine) -> None:
    """Independent reference: PostGIS' ST_Transform of the file's own coordinates."""
    _, nrw = two_crs
    _, buildings = read_model(NRW)
    ours, ref, given = [], [], []
    with db_engine.connect() as c:
        for b in buildings[:20]:
            p = next(b.iter_polygons())
            got = c.execute(
                text(
                    "SELECT ST_X(pt), ST_Y(pt), ST_Z(pt) FROM (SELECT "
                    "ST_PointN(ST_ExteriorRing(s.geometry), 1) AS pt FROM surface s "
                    "WHERE s.city_model_id = :m AND s.gml_id = :g) q"
                ),
                {"m": nrw.model_id, "g": p.id},
            ).one()
            x, y, z = p.exterior.coords[0]
            want = c.execute(
                text(
                    "SELECT ST_X(t), ST_Y(t), ST_Z(t) FROM "
                    "ST_Transform(ST_SetSRID(ST_MakePoint(:x, :y, :z), 25832), :s) t"
                ),
                {"x": x, "y": y, "z": z, "s": TEST_SRID},
            ).one()
            ours.append(got)
            ref.append(want)
            given.append((x, y, z))
    ours_a, ref_a = np.array(ours), np.array(ref)
    assert np.max(np.abs(ours_a[:, :2] - ref_a[:, :2])) < 1e-3  # a millimetre
    np.testing.assert_array_equal(ours_a[:, 2], ref_a[:, 2])  # heights kept
    if TEST_SRID != 25832:  # transformed indeed: UTM 32 and 33 differ by hundreds of km here
        assert np.min(np.abs(ours_a[:, 0] - np.array(given)[:, 0])) > 1e5


def test_export_gives_the_models_own_coordinates_back(two_crs, db_engine, tmp_path) -> None:
    s = export_citygml(db_engine, tmp_path / "nrw", model="srid-nrw")
    header_in, b_in = read_model(NRW)
    header_out, b_out = read_model(s.path)
    assert header_out.srs_name == header_in.srs_name
    a = {p.id: p.exterior.coords for b in b_in for p in b.iter_polygons()}
    b = {p.id: p.exterior.coords for b in b_out for p in b.iter_polygons()}
    assert a.keys() == b.keys()
    assert all(a[k].shape == b[k].shape for k in a)
    worst = max(float(np.max(np.abs(a[k] - b[k]))) for k in a)
    assert worst <= 1e-6


def _without_srs(src: Path, dst: Path) -> Path:
    dst.write_text(re.sub(r'\s+srsName="[^"]*"', "", src.read_text(encoding="utf-8")), encoding="utf-8")
    return dst


def test_a_file_without_crs_is_refused_unless_named(db_engine, tmp_path) -> None:
    bare = _without_srs(BAVARIA, tmp_path / "bare.gml")
    assert "srsName" not in bare.read_text(encoding="utf-8")
    with pytest.raises(InputDataError, match=r"bare\.gml.*--crs"):
        import_citygml(db_engine, bare, name="srid-bare")
    with db_engine.connect() as c:
        assert c.execute(text("SELECT count(*) FROM city_model WHERE name = 'srid-bare'")).scalar_one() == 0
    s = import_citygml(db_engine, bare, name="srid-bare", options=ImportOptions(crs="EPSG:25832"))
    assert s.srid == 25832 and s.buildings == 1
    with db_engine.connect() as c:
        srs, srids = c.execute(
            text(
                "SELECT m.srs_name, array_agg(DISTINCT ST_SRID(s.geometry)) FROM city_model m "
                "JOIN surface s ON s.city_model_id = m.id WHERE m.name = 'srid-bare' GROUP BY m.srs_name"
            )
        ).one()
    assert srs == "EPSG:25832" and srids == [TEST_SRID]


def test_an_unknown_crs_is_refused(db_engine, tmp_path) -> None:
    odd = tmp_path / "odd.gml"
    odd.write_text(
        BAVARIA.read_text(encoding="utf-8").replace('srsName="EPSG:25832"', 'srsName="EPSG:999999"'),
        encoding="utf-8",
    )
    with pytest.raises(InputDataError, match=r"odd\.gml.*999999"):
        import_citygml(db_engine, odd, name="srid-odd")
    with db_engine.connect() as c:
        assert c.execute(text("SELECT count(*) FROM city_model WHERE name = 'srid-odd'")).scalar_one() == 0


def test_the_workers_load_a_transformed_model_in_its_own_crs(two_crs, db_engine) -> None:
    """What a job's prepare task reads (`db.model_load.iter_model_buildings`): the NRW model,
    stored in the database SRID, comes back in EPSG:25832 with the file's ids and vertices (to the
    micrometre), and a box in the model's CRS selects the buildings it meets."""
    from db.model_load import iter_model_buildings

    _, nrw = two_crs
    _, want = read_model(NRW)
    with db_engine.connect() as c:
        got = list(iter_model_buildings(c, nrw.model_id))
        first = next(want[0].iter_polygons()).exterior.coords
        x, y = float(first[0, 0]), float(first[0, 1])
        boxed = [b.id for b in iter_model_buildings(c, nrw.model_id, bbox=(x - 1, y - 1, x + 1, y + 1))]
    assert [b.id for b in got] == [b.id for b in want]
    a = {p.id: p.exterior.coords for b in want for p in b.iter_polygons()}
    b = {p.id: p.exterior.coords for b in got for p in b.iter_polygons()}
    assert a.keys() == b.keys() and all(a[k].shape == b[k].shape for k in a)
    assert max(float(np.max(np.abs(a[k] - b[k]))) for k in a) <= 1e-6
    assert want[0].id in boxed and 0 < len(boxed) < len(want)

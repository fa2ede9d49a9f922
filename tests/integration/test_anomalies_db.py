"""Thermal anomalies in the results folder and the database (issue 16), read by GDAL.

A synthetic drive past real Berlin buildings with planted leaks, run by the shipped job path:
`anomalies.geojson` opens in GDAL's GeoJSON driver with the model's CRS and 3D polygons; the
folder goes into PostGIS (`citytherm results import`) and the view `thermal_anomalies` gives the
same anomalies as typed POLYGON Z in the database SRID (GDAL's PostgreSQL driver reads it so),
`facade_thermal` the facade figures of report.json, and the export writes the same
`anomalies.geojson` and the same facade attributes in `textured.gml`.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from lxml import etree
from sqlalchemy import text

from db.citygml.reader import read_model
from db.citygml.validate import validate_citygml2
from db.export import export_citygml
from db.importer import import_citygml
from db.results_import import import_results
from db.synth_files import write_synthetic_package
from tests.integration.conftest import TEST_SRID
from workers.job import RunOptions
from workers.pipeline.geometry.polygons import fit_plane
from workers.pipeline.synth import BUNDLED_MODEL, ErrorOptions, SynthOptions, synthesize
from workers.pipeline.synth.thermal import ThermalOptions
from workers.run import run_job

pytestmark = pytest.mark.integration

GEN = "{http://www.opengis.net/citygml/generics/2.0}"


@pytest.fixture(scope="module")
def leaky_job(tmp_path_factory):
    """A 24-frame drive with about three planted leaks per building, true poses: (truth, folder)."""
    folder = tmp_path_factory.mktemp("leaky")
    _, buildings = read_model(BUNDLED_MODEL)
    res = synthesize(
        buildings,
        SynthOptions(
            n_frames=24,
            seed=3,
            buildings=2,
            frame_interval_s=0.2,
            errors=ErrorOptions(enabled=False),
            model_path=str(BUNDLED_MODEL),
            thermal=ThermalOptions(leaks_per_building=3.0),
        ),
    )
    pkg = write_synthetic_package(res, folder / "seq")
    out = folder / "out"
    run_job(BUNDLED_MODEL, pkg, out, RunOptions.build(resolution_px_per_m=10, refine=False, display=False))
    return res.truth, out


def _libpq(url: str) -> str:
    m = re.match(r"postgresql(?:\+\w+)?://(?:(?P<u>[^@:/]+)@)?(?P<h>[^:/]+)(?::(?P<p>\d+))?/(?P<d>\w+)", url)
    assert m, url
    return f"PG:host={m['h']} port={m['p'] or 5432} dbname={m['d']} user={m['u'] or 'postgres'}"


def test_anomalies_geojson_opens_in_gdal_with_the_model_crs_and_3d_polygons(leaky_job) -> None:
    _, out = leaky_job
    doc = json.loads((out / "anomalies.geojson").read_text())
    kinds = [f["properties"]["kind"] for f in doc["features"]]
    assert kinds.count("leak") >= 1, kinds
    info = subprocess.run(
        ["ogrinfo", "-ro", "-so", "-al", str(out / "anomalies.geojson")],
        capture_output=True, text=True, timeout=60, check=True,
    ).stdout  # fmt: skip
    assert "Geometry: 3D Polygon" in info, info
    assert 'ID["EPSG",25833]' in info, info  # the Berlin model's CRS (srsName EPSG:25833)
    assert f"Feature Count: {len(doc['features'])}" in info
    # every outline lies on its surface's plane
    _, buildings = read_model(BUNDLED_MODEL)
    polys = {p.id: p for b in buildings for p in b.iter_polygons()}
    for f in doc["features"]:
        ring = np.array(f["geometry"]["coordinates"][0])
        assert ring.shape[1] == 3 and np.array_equal(ring[0], ring[-1])
        plane = fit_plane(polys[f["properties"]["surface"]])
        assert np.abs((ring - plane.centroid) @ plane.normal).max() < 0.01, f["properties"]["id"]


def test_anomalies_and_facade_figures_in_postgis_as_a_gis_reads_them(
    leaky_job, db_engine, migrated_db, tmp_path
):
    _, out = leaky_job
    name = "anomalies-berlin"
    model_id = import_citygml(db_engine, BUNDLED_MODEL, name=name).model_id
    summary = import_results(db_engine, out, model=name)
    doc = json.loads((out / "anomalies.geojson").read_text())
    assert summary.anomalies == len(doc["features"])
    with db_engine.connect() as c:
        rows = c.execute(
            text(
                "SELECT anomaly_id, kind, peak_delta_k, frames, ST_NDims(geometry) AS nd, "
                "ST_SRID(geometry) AS srid FROM thermal_anomalies WHERE job_id = :j ORDER BY anomaly_id"
            ),
            {"j": summary.job_id},
        ).mappings().all()  # fmt: skip
        typed = c.execute(
            text(
                "SELECT type, srid, coord_dimension FROM geometry_columns "
                "WHERE f_table_name = 'thermal_anomalies'"
            )
        ).one()
        figures = dict(
            c.execute(
                text(
                    "SELECT surface_gml_id, typical_k FROM facade_thermal "
                    "WHERE job_id = :j AND typical_k IS NOT NULL"
                ),
                {"j": summary.job_id},
            ).all()
        )
    assert tuple(typed) == ("POLYGON", TEST_SRID, 3)
    want = sorted((f["properties"]["id"], f["properties"]["kind"]) for f in doc["features"])
    assert [(r["anomaly_id"], r["kind"]) for r in rows] == want
    assert {(r["nd"], r["srid"]) for r in rows} == {(3, TEST_SRID)}
    report = json.loads((out / "report.json").read_text())
    typical = {
        s["id"]: s["typical"]
        for b in report["buildings"]
        for s in b["surfaces"]
        if s.get("typical") is not None
    }
    assert figures and set(figures) <= set(typical)
    for sid, t in figures.items():
        assert t == pytest.approx(typical[sid], abs=1e-9)
    # GDAL's PostgreSQL driver: the view is a typed 3D polygon layer in the database SRID
    info = subprocess.run(
        ["ogrinfo", "-ro", "-so", _libpq(migrated_db), "thermal_anomalies"],
        capture_output=True, text=True, timeout=60, check=True,
    ).stdout  # fmt: skip
    assert "Geometry: 3D Polygon" in info, info
    assert f'ID["EPSG",{TEST_SRID}]]' in info, info
    # the export gives the same anomalies and facade attributes back, in the model CRS
    exp = export_citygml(db_engine, tmp_path / "export", model=model_id, job_id=summary.job_id)
    back = json.loads((tmp_path / "export" / "anomalies.geojson").read_text())
    assert exp.anomalies == len(doc["features"])
    by_id = {f["properties"]["id"]: f for f in doc["features"]}
    for f in back["features"]:
        g = by_id[f["properties"]["id"]]
        np.testing.assert_allclose(f["geometry"]["coordinates"], g["geometry"]["coordinates"], atol=1e-6)
        assert f["properties"]["peak_delta_k"] == pytest.approx(g["properties"]["peak_delta_k"], abs=1e-12)
    assert validate_citygml2(exp.path) == []
    assert _surface_attributes(exp.path) == _surface_attributes(out / "textured.gml")


def _surface_attributes(path: Path) -> dict[str, dict[str, str]]:
    """Generic attributes of every thematic surface, by the id of its first polygon."""
    tree = etree.parse(str(path), etree.XMLParser(resolve_entities=False, no_network=True))
    out: dict[str, dict[str, str]] = {}
    for surf in tree.iter("{http://www.opengis.net/citygml/building/2.0}WallSurface",
                          "{http://www.opengis.net/citygml/building/2.0}RoofSurface"):  # fmt: skip
        attrs = {el.get("name"): el.findtext(f"{GEN}value") for el in surf if el.tag.startswith(GEN)}
        poly = next(surf.iter("{http://www.opengis.net/gml}Polygon"))
        if attrs:
            out[poly.get("{http://www.opengis.net/gml}id")] = attrs
    return out

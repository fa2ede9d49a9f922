"""Results folders into the city model database (issue 13, part 3), on real PostGIS.

`citytherm run --database`, `citytherm results import` and the units' own results stored directly
(`store_building_result`, as the service stores them) give the same rows: appearances, texture
coordinates, 16-bit tiles (bytes), radiometry, statistics, poses with their priors. Re-running
either writes the same rows again (no duplicates); a folder whose buildings or polygons are not in
the model is refused with nothing written; the export gives back the tiles byte for byte.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import uuid

import numpy as np
import pytest
from sqlalchemy import text
from sqlalchemy.orm import Session
from typer.testing import CliRunner

import workers.job
from db.citygml.reader import read_model
from db.errors import InputDataError
from db.export import export_citygml
from db.importer import import_citygml
from db.jobs import create_job
from db.results_folder.read import ResultsReadError, read_building_results, read_results_folder
from db.results_import import import_results, results_job_id
from db.store import store_building_result
from services.cli import app
from tests.conftest import DATA
from tests.integration.conftest import TEST_SRID
from tests.unit.texture_package import write_scene
from tests.unit.texture_scene import box_building, look_at
from workers.job import RunOptions, ingest
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import ParameterizedTexture
from workers.pipeline.geometry.manifest import Accuracy
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.transform import CrsTransform
from workers.pipeline.results import BuildingResult
from workers.run import run_job

pytestmark = pytest.mark.integration

CAM = Camera(240, 192, 220.0, 220.0, 119.5, 95.5, k1=-0.05)
MODEL = "results-db-city"
#: refinement on, without the sequence stages: the units call the (stand-in) refiner
OPTIONS = RunOptions.build(resolution_px_per_m=10, refine=True, calibrate=False, orient=False)
CLI_OPTIONS = ["--resolution", "10", "--no-calibrate", "--no-orient"]


class _Refined:
    """What the refiner hands back per frame (`orientation.building`'s record)."""

    def __init__(self, frame: int, pose: Pose, status: str) -> None:
        self.frame, self.pose, self.status = frame, pose, status
        self.rms_px, self.matches = 0.25 + frame, 10 + frame


def stand_in_refiner(camera, building, raycaster, frames, frame_source, prior, accuracy, **_):
    """Fast, deterministic orientation: B1's even frames 'refined' 1 cm east of the prior, its odd
    frames rejected; B2's orientation fails (every frame keeps its prior)."""
    if building.id == "B2":
        raise RuntimeError("no edges")
    out = {}
    for f in frames:
        if f % 2 == 0:
            east = Pose(prior[f].R_world_from_cam, prior[f].center + np.array([0.01, 0.0, 0.0]))
            out[f] = _Refined(f, east, "refined")
        else:
            out[f] = _Refined(f, prior[f], "prior")
    return out


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("results-db")
    buildings = [box_building("B1", 0, 0, 12, 8, 7, holes=True), box_building("B2", 16, 0, 24, 6, 5)]
    buildings.append(box_building("FAR", 500, 500, 505, 505, 5))  # never seen
    poses = [look_at([-3 + 3.0 * k, -15, 1.6], [0 + 3.0 * k, 0, 3.5]) for k in range(9)]
    # the poses are exact, and the manifest says so: frames the stand-in refiner leaves at their
    # priors still texture (`UnitOptions.max_prior_px`)
    exact = Accuracy(np.full(3, 0.01), np.full(3, 0.01))
    gml, pkg = write_scene(folder, buildings, CAM, poses, accuracy=exact)
    model_gml = folder / f"{MODEL}.gml"  # the model's name is the file's stem
    shutil.copy(gml, model_gml)
    return folder, model_gml, pkg


@pytest.fixture(scope="module")
def cli_run(scene, migrated_db):
    """`citytherm run --database` (model imported by it), with the stand-in refiner."""
    folder, gml, pkg = scene
    out = folder / "run-out"
    orig = workers.job.run_building_unit
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(workers.job, "run_building_unit", lambda unit, refiner=None: orig(unit, stand_in_refiner))
        res = CliRunner().invoke(
            app,
            [
                "run",
                str(gml),
                str(pkg),
                "-o",
                str(out),
                *CLI_OPTIONS,
                "--database",
                "--database-url",
                migrated_db,
            ],
        )
    assert res.exit_code == 0, res.output
    assert f"imported {gml}" in res.output and "job " in res.output
    return out, res.output


def _model_id(engine, name: str = MODEL) -> int:
    with engine.connect() as c:
        return c.execute(text("SELECT id FROM city_model WHERE name = :n"), {"n": name}).scalar_one()


ROWS = {
    "appearance": (
        "SELECT b.gml_id, a.theme, a.gml_id, a.ordinal, a.radiometry::text FROM appearance a "
        "JOIN building b ON b.id = a.building_id WHERE a.job_id = :j"
    ),
    "surface_data": (
        "SELECT b.gml_id, sd.ordinal, sd.kind, sd.gml_id, sd.is_front, sd.image_uri, sd.mime_type, "
        "sd.texture_type, sd.wrap_mode, sd.border_color, ti.uri FROM surface_data sd "
        "JOIN appearance a ON a.id = sd.appearance_id JOIN building b ON b.id = a.building_id "
        "LEFT JOIN tex_image ti ON ti.id = sd.tex_image_id WHERE a.job_id = :j"
    ),
    "texture_param": (
        "SELECT sd.gml_id, tp.ordinal, tp.target_gml_id, s.gml_id, tp.ring_ids, tp.tex_coords::text "
        "FROM texture_param tp JOIN surface_data sd ON sd.id = tp.surface_data_id "
        "JOIN appearance a ON a.id = sd.appearance_id LEFT JOIN surface s ON s.id = tp.surface_id "
        "WHERE a.job_id = :j"
    ),
    "tex_image": (
        "SELECT b.gml_id, ti.uri, ti.mime_type, ti.width, ti.height, ti.bit_depth, "
        "ti.radiometry_scale, ti.radiometry_offset, ti.radiometry_unit, ti.sha256, "
        "encode(sha256(ti.image), 'hex') FROM tex_image ti JOIN appearance a ON a.id = ti.appearance_id "
        "JOIN building b ON b.id = a.building_id WHERE a.job_id = :j"
    ),
    "surface_thermal": (
        "SELECT s.gml_id, st.texels_total, st.texels_observed, st.observed_share, st.frames_used, "
        "st.resolution_m, st.view_angle_deg, st.mean_k, st.median_k, st.std_k, st.min_k, st.max_k, "
        "st.p05_k, st.p25_k, st.p75_k, st.p95_k, st.temperature::text, st.unit FROM surface_thermal st "
        "JOIN appearance a ON a.id = st.appearance_id JOIN surface s ON s.id = st.surface_id "
        "WHERE a.job_id = :j"
    ),
    "frame_pose": (
        "SELECT b.gml_id, fp.frame_index, fp.status, fp.prior_center, fp.prior_rotation, "
        "fp.refined_center, fp.refined_rotation, ST_AsEWKT(fp.center), fp.rms_px, fp.matches "
        "FROM frame_pose fp JOIN building b ON b.id = fp.building_id WHERE fp.job_id = :j"
    ),
    "thermal_anomaly": (
        "SELECT b.gml_id, s.gml_id, ta.kind, ST_AsEWKT(ta.outline), ta.centre, ta.area_m2, "
        "ta.peak_delta_k, ta.mean_delta_k FROM thermal_anomaly ta JOIN building b ON b.id = ta.building_id "
        "LEFT JOIN surface s ON s.id = ta.surface_id WHERE ta.job_id = :j"
    ),
    "job_unit": (
        "SELECT b.gml_id, u.status, u.error FROM job_unit u JOIN building b ON b.id = u.building_id "
        "WHERE u.job_id = :j"
    ),
}


def raw_rows(engine, job_id, table: str) -> list[tuple]:
    """A job's rows of one table (`ROWS`), by content, sorted."""
    with engine.connect() as c:
        return sorted((tuple(r) for r in c.execute(text(ROWS[table]), {"j": job_id}).all()), key=repr)


def job_rows(engine, job_id) -> dict[str, list[str]]:
    """Every row a job has, by content (gml ids instead of row ids; repr, so NaN equals NaN)."""
    return {table: [repr(r) for r in raw_rows(engine, job_id, table)] for table in ROWS}


TABLES = (
    "city_model",
    "building",
    "surface",
    "job",
    "job_unit",
    "appearance",
    "surface_data",
    "texture_param",
    "tex_image",
    "surface_thermal",
    "frame_pose",
    "thermal_anomaly",
)


def table_counts(engine) -> dict[str, int]:
    with engine.connect() as c:
        return {t: c.execute(text(f"SELECT count(*) FROM {t}")).scalar_one() for t in TABLES}


def test_run_database_results_import_and_the_units_results_give_the_same_rows(
    scene, cli_run, db_engine, migrated_db, tmp_path
):
    _, gml, pkg = scene
    out, _ = cli_run
    engine = db_engine
    model_id = _model_id(engine)
    run_job_id = results_job_id(model_id, out)
    from_run = job_rows(engine, run_job_id)
    assert [len(from_run[k]) for k in ("appearance", "tex_image", "surface_thermal", "job_unit")] == [
        2,
        2,
        12,
        2,
    ]
    assert all("'successful'" in r for r in from_run["job_unit"])
    # the stand-in's poses, with the manifest-only priors of orientation.json
    poses = raw_rows(engine, run_job_id, "frame_pose")
    assert {p[0] for p in poses} == {"B1", "B2"}
    for b, frame, status, prior_c, _, refined_c, *_ in poses:
        assert status == ("refined" if b == "B1" and frame % 2 == 0 else "prior"), (b, frame)
        shift = np.array(refined_c) - np.array(prior_c)
        np.testing.assert_allclose(shift, [0.01, 0, 0] if status == "refined" else 0, atol=1e-9)
    # the radiometry went through report.json into the appearance and the images
    assert all('"unit": "K"' in r and '"scale": 0.01' in r for r in from_run["appearance"])

    # `citytherm results import` of the same files (another folder: another job) gives the same rows
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    res = CliRunner().invoke(
        app, ["results", "import", str(copy), "--model", MODEL, "--database-url", migrated_db]
    )
    assert res.exit_code == 0, res.output
    import_job_id = results_job_id(model_id, copy)
    assert import_job_id != run_job_id and str(import_job_id) in res.output.replace("\n", "")
    assert job_rows(engine, import_job_id) == from_run

    # the units' results as they came out of the run, stored directly (as the service does)
    results: list[BuildingResult] = []
    run_job(gml, pkg, tmp_path / "mem", OPTIONS, refiner=stand_in_refiner, on_result=results.append)
    ingested = ingest(gml, pkg, OPTIONS)
    priors = dict(zip(ingested.frame_indices, ingested.priors, strict=True))
    with Session(engine) as session:
        mem_job = create_job(session, model_id=model_id, theme="thermal-ir")
        session.commit()
        for r in results:
            store_building_result(session, job_id=mem_job, model_id=model_id, result=r, priors=priors)
    mem_rows = job_rows(engine, mem_job)
    for table in ROWS:
        if table != "job_unit":  # this job has no units
            assert mem_rows[table] == from_run[table], table

    # and the reader gives back exactly what the units produced
    _, back = read_building_results(out)
    for got, exp in zip(back, sorted(results, key=lambda r: r.building_id), strict=True):
        assert got.building_id == exp.building_id
        assert [t.name for t in got.tiles] == [t.name for t in exp.tiles]
        for tg, te in zip(got.tiles, exp.tiles, strict=True):
            np.testing.assert_array_equal(tg.dn, te.dn)
        assert [(s.polygon_id, dict(s.temperature), s.frames_used) for s in got.surfaces] == [
            (s.polygon_id, dict(s.temperature), s.frames_used) for s in exp.surfaces
        ]
        for pg, pe in zip(got.poses, exp.poses, strict=True):
            assert (pg.frame, pg.status, pg.matches) == (pe.frame, pe.status, pe.matches)
            np.testing.assert_array_equal(pg.pose.center, pe.pose.center)
            np.testing.assert_array_equal(pg.pose.R_world_from_cam, pe.pose.R_world_from_cam)


def test_rerunning_writes_the_same_rows(scene, cli_run, db_engine, migrated_db):
    _, gml, pkg = scene
    out, _ = cli_run
    engine = db_engine
    job_id = results_job_id(_model_id(engine), out)
    before, counts = job_rows(engine, job_id), table_counts(engine)
    # the same folder imported again: the same job, replaced
    s = import_results(engine, out, model=MODEL)
    assert s.job_id == job_id and not s.created and s.status == "successful" and s.buildings == 2
    assert job_rows(engine, job_id) == before and table_counts(engine) == counts
    # the whole run again into the same folder (the model is there now: not imported again)
    orig = workers.job.run_building_unit
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(workers.job, "run_building_unit", lambda unit, refiner=None: orig(unit, stand_in_refiner))
        res = CliRunner().invoke(
            app,
            [
                "run",
                str(gml),
                str(pkg),
                "-o",
                str(out),
                *CLI_OPTIONS,
                "--database",
                "--database-url",
                migrated_db,
            ],
        )
    assert res.exit_code == 0, res.output
    assert "imported" not in res.output and "replaced" in res.output
    assert job_rows(engine, job_id) == before and table_counts(engine) == counts
    with engine.connect() as c:
        job = c.execute(
            text("SELECT status, results_location, theme FROM job WHERE id = :j"), {"j": job_id}
        ).one()
    assert tuple(job) == ("successful", str(out.resolve()), "thermal-ir")


def test_a_folder_whose_buildings_are_not_in_the_model_is_refused(cli_run, db_engine, migrated_db, tmp_path):
    out, _ = cli_run
    engine = db_engine
    url = ["--database-url", migrated_db]
    runner = CliRunner()
    res = runner.invoke(
        app, ["import", str(DATA / "bavaria-1-building-citygml2-lod2.gml"), "--name", "rdb-other", *url]
    )
    assert res.exit_code == 0, res.output
    counts = table_counts(engine)
    res = runner.invoke(app, ["results", "import", str(out), "--model", "rdb-other", *url])
    assert res.exit_code == 1
    msg = " ".join(res.output.split())
    assert "not imported" in msg and "2 of its 2 buildings are not in city model 'rdb-other'" in msg
    assert "'B1'" in msg and "'B2'" in msg and "nothing written" in msg
    assert table_counts(engine) == counts
    # a building of the right id whose polygons differ: refused too, naming building and polygon
    bad = tmp_path / "bad"
    shutil.copytree(out, bad)
    rep = json.loads((bad / "report.json").read_text())
    rep["buildings"][1]["surfaces"][0]["id"] = "B2_no_such_wall"
    (bad / "report.json").write_text(json.dumps(rep))
    res = runner.invoke(app, ["results", "import", str(bad), "--model", MODEL, *url])
    msg = " ".join(res.output.split())
    assert res.exit_code == 1 and "building 'B2' refers to polygons" in msg and "'B2_no_such_wall'" in msg
    assert table_counts(engine) == counts
    # an unknown model, a folder that is not one, a report without radiometry (older citytherm)
    res = runner.invoke(app, ["results", "import", str(out), "--model", "no-such-model", *url])
    assert res.exit_code == 1 and "not found" in res.output
    res = runner.invoke(app, ["results", "import", str(tmp_path), "--model", MODEL, *url])
    assert res.exit_code == 1 and "report.json" in res.output and "missing" in res.output
    del rep["radiometry"]
    (bad / "report.json").write_text(json.dumps(rep))
    with pytest.raises(ResultsReadError, match="'radiometry' missing"):
        read_results_folder(bad)
    assert table_counts(engine) == counts


def test_anomalies_of_the_folder_are_stored(cli_run, db_engine, tmp_path):
    """anomalies.geojson (when detection ran) goes into thermal_anomaly with its building, surface
    and outline."""
    out, _ = cli_run
    folder = tmp_path / "with-anomalies"
    shutil.copytree(out, folder)
    _, (b1, _) = read_model(folder / "textured.gml")
    wall = next(p for p in b1.iter_polygons() if p.id == "B1_w0")
    ring = wall.exterior.coords[:3].tolist() + wall.exterior.coords[:1].tolist()
    feature = {
        "type": "Feature",
        "geometry": {"type": "Polygon", "coordinates": [ring]},
        "properties": {
            "building": "B1",
            "surface": "B1_w0",
            "centre": np.mean(ring[:3], axis=0).tolist(),
            "area_m2": 1.25,
            "peak_delta_k": 3.5,
            "mean_delta_k": 2.0,
            "kind": "leak",
        },
    }
    doc = {"type": "FeatureCollection", "features": [feature]}
    (folder / "anomalies.geojson").write_text(json.dumps(doc))
    s = import_results(db_engine, folder, model=MODEL)
    assert s.anomalies == 1
    (row,) = raw_rows(db_engine, s.job_id, "thermal_anomaly")
    assert row[:3] == ("B1", "B1_w0", "leak") and row[5:] == (1.25, 3.5, 2.0)
    # the outline in the database SRID: transformed back, the model's coordinates (EPSG:25832)
    ewkt = row[3]
    assert ewkt.startswith(f"SRID={TEST_SRID};POLYGON((")
    stored = np.array([[float(v) for v in xyz.split()] for xyz in ewkt.split("((")[1].rstrip(")").split(",")])
    back = CrsTransform(f"EPSG:{TEST_SRID}", "EPSG:25832").points(stored)
    np.testing.assert_allclose(back, np.array(ring), atol=1e-6)
    np.testing.assert_array_equal(row[4], np.mean(ring[:3], axis=0))


def test_export_gives_back_the_tiles_byte_for_byte(cli_run, db_engine, tmp_path):
    out, _ = cli_run
    job_id = results_job_id(_model_id(db_engine), out)
    exp = export_citygml(db_engine, tmp_path / "export", model=MODEL, job_id=job_id, theme="thermal-ir")
    assert exp.buildings == 2 and exp.textures == 2
    for name in ("textures/B1_0.png", "textures/B2_0.png"):
        data = (tmp_path / "export" / name).read_bytes()
        assert data == (out / name).read_bytes()
        with db_engine.connect() as c:
            sha = c.execute(
                text(
                    "SELECT ti.sha256 FROM tex_image ti JOIN appearance a ON a.id = ti.appearance_id "
                    "WHERE a.job_id = :j AND ti.uri = :u"
                ),
                {"j": job_id, "u": name},
            ).scalar_one()
        assert sha == hashlib.sha256(data).hexdigest()
    # the exported appearance is the folder's: same texture ids, images and coordinates
    _, got = read_model(tmp_path / "export" / "textured.gml")
    rf = read_results_folder(out)
    for b in got:
        (app_got,) = [a for a in b.appearances if a.theme == "thermal-ir"]
        app_in = rf.appearances[b.id]
        assert app_got.id == app_in.id
        for sg, si in zip(app_got.surface_data, app_in.surface_data, strict=True):
            assert isinstance(sg, ParameterizedTexture) and isinstance(si, ParameterizedTexture)
            assert (sg.id, sg.image_uri) == (si.id, si.image_uri)
            for tg, ti in zip(sg.targets, si.targets, strict=True):
                assert tg.polygon_id == ti.polygon_id and list(tg.ring_coords) == list(ti.ring_coords)
                for rid, st in ti.ring_coords.items():
                    np.testing.assert_array_equal(tg.ring_coords[rid], st)


def test_a_job_id_of_another_model_is_refused(cli_run, db_engine):
    out, _ = cli_run
    other = import_citygml(db_engine, DATA / "bavaria-1-building-citygml2-lod2.gml", name="rdb-job-other")
    with Session(db_engine) as session:
        jid = create_job(session, model_id=other.model_id, job_id=uuid.uuid4())
        session.commit()
    counts = table_counts(db_engine)
    with pytest.raises(InputDataError, match="belongs to city model"):
        import_results(db_engine, out, model=MODEL, job_id=jid)
    assert table_counts(db_engine) == counts


def test_a_folder_imported_again_with_fewer_buildings_leaves_the_job_with_its_buildings(
    cli_run, db_engine, tmp_path
):
    """The job mirrors its folder: a building the folder no longer has (a run with --buildings
    into the same folder, say) leaves the job; one that failed this time is a failed unit."""
    out, _ = cli_run
    folder = tmp_path / "fewer"
    shutil.copytree(out, folder)
    first = import_results(db_engine, folder, model=MODEL)
    assert first.buildings == 2 and first.status == "successful"
    rep = json.loads((folder / "report.json").read_text())
    rep["buildings"] = [b for b in rep["buildings"] if b["id"] == "B1"]
    rep["failed"] = [{"id": "B2", "error": "RuntimeError: out of memory"}]
    (folder / "report.json").write_text(json.dumps(rep))
    orient = json.loads((folder / "orientation.json").read_text())
    for f in orient["frames"]:
        f["refined"] = [r for r in f["refined"] if r["building"] == "B1"]
    (folder / "orientation.json").write_text(json.dumps(orient))
    anomalies = json.loads((folder / "anomalies.geojson").read_text())
    anomalies["features"] = [f for f in anomalies["features"] if f["properties"]["building"] == "B1"]
    (folder / "anomalies.geojson").write_text(json.dumps(anomalies))
    again = import_results(db_engine, folder, model=MODEL)
    assert again.job_id == first.job_id and (again.buildings, again.failed) == (1, 1)
    rows = job_rows(db_engine, first.job_id)
    assert {r.split(",")[0] for t in ("appearance", "frame_pose", "tex_image") for r in rows[t]} == {"('B1'"}
    assert raw_rows(db_engine, first.job_id, "job_unit") == [
        ("B1", "successful", None),
        ("B2", "failed", "RuntimeError: out of memory"),
    ]
    with db_engine.connect() as c:
        assert (
            c.execute(text("SELECT status FROM job WHERE id = :j"), {"j": first.job_id}).scalar_one()
            == "successful"
        )

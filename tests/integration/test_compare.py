"""`citytherm compare` (issue 16, item 6) on results folders made by the real pipeline: two
synthetic surveys of the same Berlin buildings, B with walls and roofs a known offset warmer
than A (same seed: the same scene otherwise), at different texel resolutions, with the outside
air temperature in their manifests. The change per facade, its normalisation by the air
temperature, the ΔT textures (CityGML 2.0, schema-valid), the refusals, and the same figures
from the database (`--db`, the `surface_thermal_change` view)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from sqlalchemy import Engine, text
from typer.testing import CliRunner

from db.citygml.reader import read_model
from db.citygml.validate import validate_citygml2
from db.importer import import_citygml
from db.results_import import import_results
from db.synth_files import write_synthetic_package
from services.cli import app
from tests.integration.conftest import TEST_SRID
from workers.pipeline.change import DELTA_RADIOMETRY
from workers.pipeline.synth import (
    BUNDLED_MODEL,
    ErrorOptions,
    SensorOptions,
    SynthOptions,
    ThermalOptions,
    default_camera,
    synthesize,
)

pytestmark = pytest.mark.integration

OFFSET_K = 1.5  # B's walls and roofs against A's
AIR_C = (-2.0, 1.0)  # outside air of A and B: normalised change = 1.5 - 3.0 = -1.5 K
RESOLUTION = (5, 8)  # texels per metre of A and B
#: the buildings whose walls the drive sees well (the others of the cluster: a few texels at most)
SEEN = "BLDG_0003000f001c079c,BLDG_0003000e00a4fcbf,BLDG_0003000e002837ac"
RUN = ["--no-refine", "--no-display", "--workers", "1", "--buildings", SEEN]


def _survey(folder: Path, name: str, offset: float, air_c: float, res: int, year: int) -> Path:
    """A synthetic drive past two buildings (no GNSS/INS errors) in the winter of `year`, its
    walls and roofs `offset` kelvin warmer than the generator's defaults, run by `citytherm run`
    at `res` texels per metre."""
    _, buildings = read_model(BUNDLED_MODEL)
    thermal = ThermalOptions(wall_k=276.0 + offset, roof_k=271.0 + offset)
    options = SynthOptions(n_frames=12, seed=5, buildings=2, frame_interval_s=0.9, thermal=thermal,
                           camera=default_camera(320, 256, 45.0), errors=ErrorOptions(enabled=False),
                           sensor=SensorOptions(supersample=1), model_path=str(BUNDLED_MODEL))  # fmt: skip
    pkg = write_synthetic_package(synthesize(buildings, options), folder / f"seq-{name}")
    manifest = json.loads((pkg / "sequence.json").read_text())
    manifest["conditions"] = {
        "air_temperature_c": air_c,
        "recorded_at": f"{year}-01-15T21:00:00Z",
    }
    (pkg / "sequence.json").write_text(json.dumps(manifest))
    out = folder / f"run-{name}"
    res_ = CliRunner().invoke(
        app, ["run", str(BUNDLED_MODEL), str(pkg), "-o", str(out), "--resolution", str(res), *RUN]
    )
    assert res_.exit_code == 0, res_.output
    return out


@pytest.fixture(scope="module")
def surveys(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("compare")
    a = _survey(folder, "a", 0.0, AIR_C[0], RESOLUTION[0], 2025)
    b = _survey(folder, "b", OFFSET_K, AIR_C[1], RESOLUTION[1], 2026)
    return a, b  # A the earlier survey


def _compare(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(app, ["compare", *args], env={"COLUMNS": "1000"})
    return res.exit_code, " ".join(res.output.split())


def _walls(doc: dict) -> list[dict]:
    """Surfaces well observed by both surveys."""
    return [s for b in doc["buildings"] for s in b["surfaces"] if s["observed_both_share"] > 0.2]


def _resolutions(folder: Path) -> dict[str, float]:
    rep = json.loads((folder / "report.json").read_text())
    return {s["id"]: s["resolution_px_per_m"] for b in rep["buildings"] for s in b["surfaces"]}


def test_folders_give_the_known_offset_and_valid_change_textures(
    surveys: tuple[Path, Path], tmp_path: Path
) -> None:
    a, b = surveys
    assert json.loads((a / "report.json").read_text())["conditions"]["air_temperature_c"] == AIR_C[0]
    out = tmp_path / "change"
    code, output = _compare(str(a), str(b), "-o", str(out))
    assert code == 0, output
    doc = json.loads((out / "change.json").read_text())
    assert doc["format"] == "citytherm-change/1" and doc["theme"] == "thermal-change"
    assert doc["radiometry"] == {"unit": "K", "scale": 0.001, "offset": -32.0}
    assert doc["a"]["folder"] == str(a) and doc["b"]["conditions"]["air_temperature_c"] == AIR_C[1]
    walls = _walls(doc)
    assert len(walls) >= 3, doc["summary"]
    res_a, res_b = _resolutions(a), _resolutions(b)
    for s in walls:
        assert abs(s["delta_typical_k"] - OFFSET_K) < 0.1, s
        assert abs(s["delta_median_k"] - OFFSET_K) < 0.1, s
        assert abs(s["normalised_delta_k"] - (OFFSET_K - (AIR_C[1] - AIR_C[0]))) < 0.1, s
        assert s["delta_p05_k"] <= s["delta_median_k"] <= s["delta_p95_k"]
        # re-sampled at the finer of the two surfaces' grids (resolution follows the frames)
        assert s["resolution_px_per_m"] == pytest.approx(max(res_a[s["id"]], res_b[s["id"]]))
    assert any(res_a[s["id"]] != res_b[s["id"]] for s in walls)
    assert validate_citygml2(out / "change.gml") == []
    _, back = read_model(out / "change.gml")
    themes = {app.theme for bld in back for app in bld.appearances}
    assert themes == {"thermal-change"}
    tiles = sorted((out / "textures").glob("*.png"))
    assert tiles and {t for b_ in doc["buildings"] for t in b_["tiles"]} == {
        f"textures/{p.name}" for p in tiles
    }
    dn = np.concatenate([cv2.imread(str(p), cv2.IMREAD_UNCHANGED).ravel() for p in tiles])
    values = DELTA_RADIOMETRY.physical(dn[dn > 0])
    assert abs(float(np.median(values)) - OFFSET_K) < 0.1
    assert not list(tmp_path.glob(".change.partial-*"))


def test_bad_input_is_refused_naming_it_and_nothing_is_written(
    surveys: tuple[Path, Path], tmp_path: Path
) -> None:
    a, b = surveys
    out = tmp_path / "out"
    broken = tmp_path / "no-report"
    shutil.copytree(b, broken)
    (broken / "report.json").unlink()
    code, output = _compare(str(a), str(broken), "-o", str(out))
    assert code != 0 and "report.json" in output and "missing" in output, output
    other = tmp_path / "other-model"  # B's results on a model whose first wall moved by 1 m
    shutil.copytree(b, other)
    gml = (other / "textured.gml").read_text()
    first = re.search(r"<gml:posList[^>]*>\s*([-\d.]+)", gml)
    moved = f"{float(first.group(1)) + 1.0!r}"
    (other / "textured.gml").write_text(gml[: first.start(1)] + moved + gml[first.end(1) :])
    code, output = _compare(str(a), str(other), "-o", str(out))
    assert code != 0 and "not the same city model" in output and "textured.gml" in output, output
    code, output = _compare("--db", "not-a-uuid", "0b9e4c1e-0000-4000-8000-000000000000", "-o", str(out))
    assert code != 0 and "not-a-uuid" in output, output
    assert not out.exists() and not list(tmp_path.glob(".out.partial-*"))
    occupied = tmp_path / "occupied"
    occupied.mkdir()
    (occupied / "notes.txt").write_text("mine")
    code, output = _compare(str(a), str(b), "-o", str(occupied))
    assert code != 0 and "not an empty folder" in output, output
    assert [p.name for p in occupied.iterdir()] == ["notes.txt"]


def test_database_jobs_give_the_same_change_and_the_view(
    surveys: tuple[Path, Path], db_engine: Engine, migrated_db: str, tmp_path: Path
) -> None:
    a, b = surveys
    model = import_citygml(db_engine, BUNDLED_MODEL, name="compare-berlin")
    jobs = [str(import_results(db_engine, f, model=model.model_id).job_id) for f in (a, b)]
    out = tmp_path / "db-change"
    code, output = _compare("--db", *jobs, "-o", str(out), "--database-url", migrated_db)
    assert code == 0, output
    doc = json.loads((out / "change.json").read_text())
    assert doc["a"]["job"] == jobs[0] and doc["a"]["conditions"]["air_temperature_c"] == AIR_C[0]
    code, output = _compare(str(a), str(b), "-o", str(tmp_path / "folders"))
    assert code == 0, output
    folders = json.loads((tmp_path / "folders" / "change.json").read_text())
    by_id = {s["id"]: s for s in _walls(folders)}
    for s in _walls(doc):
        assert s["delta_typical_k"] == pytest.approx(by_id[s["id"]]["delta_typical_k"], abs=1e-6)
        assert s["delta_median_k"] == pytest.approx(by_id[s["id"]]["delta_median_k"], abs=1e-3)
    assert validate_citygml2(out / "change.gml") == []
    with db_engine.connect() as c:
        rows = (
            c.execute(
                text(
                    "SELECT id, surface_gml_id, delta_typical_k, ST_SRID(geometry) AS srid "
                    "FROM surface_thermal_change WHERE job_a = :a AND job_b = :b"
                ),
                {"a": jobs[0], "b": jobs[1]},
            )
            .mappings()
            .all()
        )
        srid = c.execute(
            text("SELECT srid FROM geometry_columns WHERE f_table_name = 'surface_thermal_change'")
        ).scalar_one()
        unknown = "0b9e4c1e-0000-4000-8000-000000000000"
    assert srid == TEST_SRID and rows and {r["srid"] for r in rows} == {TEST_SRID}
    assert len({r["id"] for r in rows}) == len(rows)  # a key for GIS clients
    view = {r["surface_gml_id"]: r["delta_typical_k"] for r in rows}
    for pid, s in by_id.items():
        assert view[pid] == pytest.approx(s["delta_typical_k"], abs=1e-6)
    # as service jobs: conditions from their sequences' manifests; B recorded before A this time
    with db_engine.connect() as c:
        for jid, air, year in zip(jobs, AIR_C, (2025, 2024), strict=True):
            cond = {"air_temperature_c": air, "recorded_at": f"{year}-01-15T21:00:00Z"}
            sid = c.execute(
                text(
                    "INSERT INTO sequence (name, manifest, storage_location, frame_count, srid) "
                    "VALUES (:n, CAST(:m AS jsonb), '-', 0, 0) RETURNING id"
                ),
                {"n": f"compare-{jid}", "m": json.dumps({"conditions": cond})},
            ).scalar_one()
            c.execute(text("UPDATE job SET sequence_id = :s WHERE id = :j"), {"s": sid, "j": jid})
        swapped = (
            c.execute(
                text(
                    "SELECT surface_gml_id, delta_typical_k, normalised_delta_k, air_temperature_a_k, "
                    "time_a FROM surface_thermal_change WHERE job_a = :b AND job_b = :a"
                ),
                {"a": jobs[0], "b": jobs[1]},
            )
            .mappings()
            .all()
        )
        c.rollback()
    assert {r["surface_gml_id"] for r in swapped} == set(view)
    for r in swapped:
        assert r["delta_typical_k"] == pytest.approx(-view[r["surface_gml_id"]], abs=1e-9)
        expected = -view[r["surface_gml_id"]] + (AIR_C[1] - AIR_C[0])
        assert r["normalised_delta_k"] == pytest.approx(expected, abs=1e-9)
        assert r["air_temperature_a_k"] == pytest.approx(AIR_C[1] + 273.15) and r["time_a"].year == 2024
    code, output = _compare(
        "--db", jobs[0], unknown, "-o", str(tmp_path / "x"), "--database-url", migrated_db
    )
    assert code != 0 and unknown in output and "no such job" in output, output

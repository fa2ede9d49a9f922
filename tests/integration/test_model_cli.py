"""`citytherm model list` and `citytherm model delete` on real PostGIS (issue 13, part 4): the list
shows every model with its appearance themes (imported and the jobs') and jobs; a delete is
refused while a job of the model is accepted or running, and otherwise removes the model with its
appearances, textures and jobs, and nothing of any other model."""

from __future__ import annotations

import json
import shutil
import uuid

import pytest
from sqlalchemy import text
from sqlalchemy.orm import Session
from typer.testing import CliRunner

from db.jobs import create_job, dismiss_job, set_job_status
from services.cli import app
from tests.conftest import DATA
from tests.unit.texture_package import write_scene
from tests.unit.texture_scene import box_building, look_at
from workers.pipeline.geometry.camera import Camera

pytestmark = pytest.mark.integration

CAM = Camera(240, 192, 220.0, 220.0, 119.5, 95.5)
TEXTURED = "model-cli-scene"
MOABIT = "model-cli-moabit"

#: rows of a model, per table (what a delete must remove, and only that)
MODEL_ROWS = {
    "city_model": "SELECT count(*) FROM city_model WHERE id = :m",
    "building": "SELECT count(*) FROM building WHERE city_model_id = :m",
    "surface": "SELECT count(*) FROM surface WHERE city_model_id = :m",
    "job": "SELECT count(*) FROM job WHERE city_model_id = :m",
    "job_unit": "SELECT count(*) FROM job_unit u JOIN job j ON j.id = u.job_id WHERE j.city_model_id = :m",
    "appearance": "SELECT count(*) FROM appearance WHERE city_model_id = :m",
    "surface_data": (
        "SELECT count(*) FROM surface_data sd JOIN appearance a ON a.id = sd.appearance_id "
        "WHERE a.city_model_id = :m"
    ),
    "texture_param": (
        "SELECT count(*) FROM texture_param tp JOIN surface_data sd ON sd.id = tp.surface_data_id "
        "JOIN appearance a ON a.id = sd.appearance_id WHERE a.city_model_id = :m"
    ),
    "tex_image": (
        "SELECT count(*) FROM tex_image ti JOIN appearance a ON a.id = ti.appearance_id "
        "WHERE a.city_model_id = :m"
    ),
    "surface_thermal": (
        "SELECT count(*) FROM surface_thermal st JOIN appearance a ON a.id = st.appearance_id "
        "WHERE a.city_model_id = :m"
    ),
    "frame_pose": (
        "SELECT count(*) FROM frame_pose fp JOIN job j ON j.id = fp.job_id WHERE j.city_model_id = :m"
    ),
}


def model_rows(engine, model_id: int) -> dict[str, int]:
    with engine.connect() as c:
        return {t: c.execute(text(sql), {"m": model_id}).scalar_one() for t, sql in MODEL_ROWS.items()}


def table_counts(engine) -> dict[str, int]:
    with engine.connect() as c:
        return {t: c.execute(text(f"SELECT count(*) FROM {t}")).scalar_one() for t in MODEL_ROWS}


@pytest.fixture(scope="module")
def models(tmp_path_factory, migrated_db, db_engine):
    """Two models: a small scene textured by `citytherm run --database --model` (theme
    thermal-ir, one successful job) and the Moabit sample with its own appearances."""
    folder = tmp_path_factory.mktemp("model-cli")
    poses = [look_at([-3 + 2.0 * k, -15, 1.6], [0 + 2.0 * k, 0, 3.5]) for k in range(4)]
    gml, pkg = write_scene(folder, [box_building("H1", 0, 0, 8, 6, 6)], CAM, poses)
    url = ["--database-url", migrated_db]
    runner = CliRunner()
    res = runner.invoke(
        app,
        [
            "run",
            str(gml),
            str(pkg),
            "-o",
            str(folder / "out"),
            "--no-refine",
            "--resolution",
            "5",
            "--database",
            "--model",
            TEXTURED,
            *url,
        ],
    )
    assert res.exit_code == 0, res.output
    moabit = folder / f"{MOABIT}.gml"
    shutil.copy(DATA / "berlin-moabit-textured-citygml2-lod2.gml", moabit)
    res = runner.invoke(app, ["import", str(moabit), *url])
    assert res.exit_code == 0, res.output
    with db_engine.connect() as c:
        ids = dict(
            c.execute(
                text("SELECT name, id FROM city_model WHERE name IN (:a, :b)"), {"a": TEXTURED, "b": MOABIT}
            ).all()
        )
    return ids


def test_model_list_shows_models_with_their_themes_and_jobs(models, migrated_db):
    runner = CliRunner()
    res = runner.invoke(app, ["model", "list", "--json", "--database-url", migrated_db])
    assert res.exit_code == 0, res.output
    doc = {m["name"]: m for m in json.loads(res.output)}
    scene = doc[TEXTURED]
    assert scene["id"] == models[TEXTURED] and (scene["srs_name"], scene["srid"]) == ("EPSG:25832", 25832)
    assert (scene["buildings"], scene["parts"], scene["state"]) == (1, 0, "complete")
    assert scene["themes"] == {"thermal-ir": 1} and scene["jobs"] == {"successful": 1}
    moabit = doc[MOABIT]
    assert moabit["themes"] == {"Eignung Photovoltaik": 1, "Eignung Solarthermie": 1, "rgbTexture": 1}
    assert moabit["jobs"] == {} and moabit["buildings"] >= 1
    # the human-readable list says the same
    res = runner.invoke(app, ["model", "list", "--database-url", migrated_db])
    assert res.exit_code == 0, res.output
    block = res.output[res.output.index(TEXTURED) :]
    assert "CRS EPSG:25832 (SRID 25832)" in block and "1 buildings, 0 parts" in block
    assert "themes: thermal-ir (1)" in block and "jobs: successful (1)" in block
    assert "themes: Eignung Photovoltaik (1), Eignung Solarthermie (1), rgbTexture (1)" in res.output


def test_model_delete_is_refused_while_a_job_runs_and_removes_the_model_otherwise(
    models, migrated_db, db_engine
):
    runner = CliRunner()
    url = ["--database-url", migrated_db]
    mid = models[TEXTURED]
    with Session(db_engine) as session:
        job = create_job(session, model_id=mid, theme="thermal-ir", job_id=uuid.uuid4())
        session.commit()
    before, own = table_counts(db_engine), model_rows(db_engine, mid)
    assert own["tex_image"] == 1 and own["surface_thermal"] == 6 and own["job"] == 2 and own["job_unit"] == 1
    for status in ("accepted", "running"):
        if status == "running":
            with Session(db_engine) as session:
                set_job_status(session, job_id=job, status="running")
                session.commit()
        res = runner.invoke(app, ["model", "delete", TEXTURED, "--yes", *url])
        msg = " ".join(res.output.split())
        assert res.exit_code == 1, res.output
        assert f"not deleted: city model '{TEXTURED}' has 1 job(s) in progress: {job} ({status})" in msg
        assert table_counts(db_engine) == before
    # asked first: no means no
    with Session(db_engine) as session:
        dismiss_job(session, job_id=job)
        session.commit()
    res = runner.invoke(app, ["model", "delete", TEXTURED, *url], input="n\n")
    assert res.exit_code == 1 and "Aborted" in res.output
    assert table_counts(db_engine) == before
    res = runner.invoke(app, ["model", "delete", TEXTURED, *url], input="y\n")
    assert res.exit_code == 0, res.output
    assert (
        f"deleted city model {TEXTURED} (id {mid}): 1 buildings, 1 appearances, 1 texture images, 2 jobs"
        in (" ".join(res.output.split()))
    )
    assert model_rows(db_engine, mid) == dict.fromkeys(MODEL_ROWS, 0)
    assert table_counts(db_engine) == {
        t: before[t] - own[t] for t in MODEL_ROWS
    }  # nothing of any other model
    res = runner.invoke(app, ["model", "list", "--json", *url])
    assert TEXTURED not in {m["name"] for m in json.loads(res.output)}
    res = runner.invoke(app, ["model", "delete", TEXTURED, "--yes", *url])
    assert res.exit_code == 1 and "not found" in res.output


def test_model_delete_by_id_removes_imported_appearances_and_images(models, migrated_db, db_engine):
    mid = models[MOABIT]
    own = model_rows(db_engine, mid)
    assert own["appearance"] == 3 and own["texture_param"] > 0
    before = table_counts(db_engine)
    res = CliRunner().invoke(app, ["model", "delete", str(mid), "-y", "--database-url", migrated_db])
    assert res.exit_code == 0, res.output
    assert model_rows(db_engine, mid) == dict.fromkeys(MODEL_ROWS, 0)
    assert table_counts(db_engine) == {t: before[t] - own[t] for t in MODEL_ROWS}

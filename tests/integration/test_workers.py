"""The service's workers end to end: two real `citytherm worker` processes (Celery, prefork) on the
test PostGIS database and Redis db, a synthetic drive past the bundled Berlin model.

A job submitted with `workers.submit.submit_job` runs to `successful` with the same rows and the
same results folder as `citytherm run` (+ `results import`) on the same inputs, also with
refinement (calibrated, its frames decoded ahead by the idle worker); workers killed
with SIGKILL in the middle of a unit cost nothing but time (the sweeper queues the unit again);
a dismissed job gets nothing more written; a package with a missing frame fails its job with a
message naming the file, without retries.
"""

from __future__ import annotations

import json
import re
import shutil
import time
import uuid
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import redis
from sqlalchemy import text
from sqlalchemy.orm import Session

from db.citygml.reader import read_model
from db.importer import import_citygml
from db.results_import import import_results
from db.sequence_package import read_manifest
from db.sequences import register_sequence
from db.synth_files import write_synthetic_package
from tests.integration.test_results_db import job_rows
from workers.celery_app import QUEUE, app
from workers.job import RunOptions
from workers.pipeline.synth import BUNDLED_MODEL, ErrorOptions, SynthOptions, synthesize
from workers.run import run_job
from workers.submit import dismiss, submit_job

pytestmark = pytest.mark.integration

MODEL = "berlin-workers"
#: the drive's buildings the tests texture: one large unit (16 frames), three small ones
BUILDINGS = (
    "BLDG_0003000f001c079c",
    "BLDG_0003000f0008f903",
    "DEB_LOD2_UUID_223c804e-ed2e-4970-b42b-df3fcc4e8b30",
    "DEB_LOD2_UUID_bdba8cdc-80d7-457e-b484-b3c503bab56f",
)
OPTIONS = RunOptions.build(resolution_px_per_m=10, refine=False, display=False, buildings=BUILDINGS)
#: a safety net for waits on the workers, never an assertion on time
PATIENCE_S = 240.0


@dataclass(frozen=True)
class Scene:
    folder: Path
    package: Path
    model_id: int
    sequence_id: int
    cluster: tuple[str, ...]


def _register(db_engine: Any, name: str, package: Path) -> int:
    manifest = read_manifest(package, check_frames=False)
    with Session(db_engine) as s:
        sid = register_sequence(
            s,
            name=name,
            manifest=manifest,
            manifest_json=json.loads((package / "sequence.json").read_text()),
            storage_location=str(package.resolve()),
            srid=25833,
        )
        s.commit()
    return sid


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory, db_engine: Any) -> Scene:
    """A 16-frame error-free drive past the Berlin model (`citytherm synth`'s generator), the
    model imported, the package registered as a sequence."""
    folder = tmp_path_factory.mktemp("workers-scene")
    _, buildings = read_model(BUNDLED_MODEL)
    opts = SynthOptions(
        n_frames=16,
        seed=3,
        buildings=3,
        frame_interval_s=0.2,
        errors=ErrorOptions(enabled=False),
        model_path=str(BUNDLED_MODEL),
    )
    res = synthesize(buildings, opts)
    package = write_synthetic_package(res, folder / "seq")
    model_id = import_citygml(db_engine, BUNDLED_MODEL, name=MODEL).model_id
    return Scene(folder, package, model_id, _register(db_engine, "drive", package), tuple(res.truth.cluster))


@pytest.fixture(scope="module")
def reference(scene: Scene, db_engine: Any) -> tuple[Path, uuid.UUID]:
    """`citytherm run --database` on the same inputs: the results folder, and its job in the
    database (`results import`)."""
    out = scene.folder / "run-out"
    run_job(BUNDLED_MODEL, scene.package, out, OPTIONS)
    return out, import_results(db_engine, out, model=MODEL).job_id


def wait_for(what: str, cond: Callable[[], Any]) -> Any:
    """Poll `cond` until it returns something true (a safety deadline, not a timing check)."""
    deadline = time.monotonic() + PATIENCE_S
    while time.monotonic() < deadline:
        got = cond()
        if got:
            return got
        time.sleep(0.05)
    raise AssertionError(f"gave up waiting for {what}")


def job_row(db_engine: Any, job_id: uuid.UUID) -> dict[str, Any]:
    with db_engine.connect() as c:
        return dict(c.execute(text("SELECT * FROM job WHERE id = :j"), {"j": job_id}).mappings().one())


def units(db_engine: Any, job_id: uuid.UUID) -> dict[str, dict[str, Any]]:
    """The job's units by building gml id."""
    with db_engine.connect() as c:
        rows = c.execute(
            text(
                "SELECT b.gml_id, u.status, u.attempts, u.task_id, u.error FROM job_unit u "
                "JOIN building b ON b.id = u.building_id WHERE u.job_id = :j"
            ),
            {"j": job_id},
        ).mappings()
        return {r["gml_id"]: dict(r) for r in rows}


def appearances(db_engine: Any, job_id: uuid.UUID) -> dict[str, int]:
    """Appearances of the job per building gml id."""
    with db_engine.connect() as c:
        rows = c.execute(
            text(
                "SELECT b.gml_id, count(*) FROM appearance a JOIN building b ON b.id = a.building_id "
                "WHERE a.job_id = :j GROUP BY b.gml_id"
            ),
            {"j": job_id},
        ).all()
    return {g: int(n) for g, n in rows}


def finished(db_engine: Any, job_id: uuid.UUID) -> dict[str, Any]:
    """Wait until the job is final (and, unless it failed before its units or was dismissed,
    until its results folder is written); returns its row."""

    def done() -> dict[str, Any] | None:
        j = job_row(db_engine, job_id)
        if j["status"] in ("dismissed",) or (j["status"] == "failed" and j["stage"] != "units"):
            return j
        if j["status"] in ("successful", "failed") and j["results_location"]:
            return j
        return None

    return wait_for(f"job {job_id} to finish", done)


def submit(
    db_engine: Any, scene: Scene, options: RunOptions = OPTIONS, sequence_id: int | None = None
) -> uuid.UUID:
    with Session(db_engine) as s:
        return submit_job(
            s, model_id=scene.model_id, sequence_id=sequence_id or scene.sequence_id, options=options
        )


def _gml(path: Path) -> str:
    """textured.gml without its time stamps."""
    return re.sub(r"<core:creationDate>[^<]*</core:creationDate>", "", path.read_text(encoding="utf-8"))


def test_a_submitted_job_gives_what_citytherm_run_gives(scene, reference, celery_workers, db_engine):
    celery_workers.ensure()
    run_out, run_job_id = reference
    job_id = submit(db_engine, scene)
    job = finished(db_engine, job_id)
    assert job["status"] == "successful", job
    assert job["stage"] == "finish" and job["progress"] == 1.0
    us = units(db_engine, job_id)
    assert set(us) == set(BUILDINGS)
    assert all(u["status"] == "successful" and u["attempts"] == 1 for u in us.values()), us
    assert appearances(db_engine, job_id) == dict.fromkeys(BUILDINGS, 1)
    assert_same_results(db_engine, job, run_out, run_job_id)


def assert_same_results(db_engine: Any, job: dict[str, Any], run_out: Path, run_job_id: uuid.UUID) -> None:
    """The job (its row) gave what `citytherm run` wrote to `run_out` and `results import`ed as
    `run_job_id`."""
    job_id = job["id"]
    # the same rows as `citytherm run --database` (appearances, texture coordinates, the 16-bit
    # tiles byte for byte, statistics, poses with their priors, anomalies, units)
    assert job_rows(db_engine, job_id) == job_rows(db_engine, run_job_id)
    # and the same results folder, written by the same writer
    out = Path(job["results_location"])
    tiles = sorted(p.relative_to(run_out) for p in (run_out / "textures").rglob("*.png"))
    assert tiles and tiles == sorted(p.relative_to(out) for p in (out / "textures").rglob("*.png"))
    for t in tiles:
        assert (out / t).read_bytes() == (run_out / t).read_bytes(), t
    assert _gml(out / "textured.gml") == _gml(run_out / "textured.gml")
    assert json.loads((out / "orientation.json").read_text()) == json.loads(
        (run_out / "orientation.json").read_text()
    )
    rep, run_rep = (json.loads((d / "report.json").read_text()) for d in (out, run_out))
    assert [b["id"] for b in rep["buildings"]] == [b["id"] for b in run_rep["buildings"]]
    assert rep["buildings_processed"] == run_rep["buildings_processed"] == len(BUILDINGS)
    assert rep["buildings_textured"] == run_rep["buildings_textured"] >= 1
    with zipfile.ZipFile(out.parent / "results.zip") as z:
        assert sorted(z.namelist()) == sorted(
            p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()
        )


def test_a_calibrated_job_decodes_its_frames_ahead_and_gives_what_citytherm_run_gives(
    scene, celery_workers, db_engine
):
    """With refinement the prepare task calibrates and queues `citytherm.prefetch_frames` first,
    which the idle worker runs (`workers.service_frames`); the results stay those of `citytherm
    run`."""
    celery_workers.ensure()
    options = RunOptions.build(resolution_px_per_m=10, refine=True, display=False, buildings=BUILDINGS)
    assert options.calibrate
    run_out = scene.folder / "run-out-calibrated"
    run_job(BUNDLED_MODEL, scene.package, run_out, options)
    run_job_id = import_results(db_engine, run_out, model=MODEL).job_id
    job_id = submit(db_engine, scene, options)
    job = finished(db_engine, job_id)
    assert job["status"] == "successful", job
    assert set(units(db_engine, job_id)) == set(BUILDINGS)
    assert_same_results(db_engine, job, run_out, run_job_id)
    logs = "".join(celery_workers.log(n) for n in celery_workers.names).splitlines()
    spans = [json.loads(ln.split("task-span ", 1)[1]) for ln in logs if "task-span " in ln]
    prefetch = [
        sp["result"]
        for sp in spans
        if sp["task"] == "citytherm.prefetch_frames" and sp["args"] == [str(job_id)]
    ]
    # decoded while the job calibrated, or taken up after it (then nothing is done)
    assert len(prefetch) == 1 and (prefetch[0].startswith("decoded ") or prefetch[0] == "late"), prefetch


def _running(db_engine: Any, job_id: uuid.UUID) -> str | None:
    """A building whose unit is `running`, or None."""
    return next((g for g, u in units(db_engine, job_id).items() if u["status"] == "running"), None)


def _kill_in_a_unit(db_engine: Any, job_id: uuid.UUID, celery_workers: Any) -> str | None:
    """SIGKILL every worker while a unit of the job runs, then start them again (as a supervisor
    would); the building whose unit was still `running` after the kill, or None if every unit
    ended first (a unit ends between the look and the kill). Waits for the job's units only while
    the job runs."""
    while job_row(db_engine, job_id)["status"] in ("accepted", "running"):
        building = _running(db_engine, job_id)
        if building is None:
            time.sleep(0.02)
            continue
        for name in celery_workers.names:  # the one running it, and the one that would take it
            celery_workers.kill(name)
        still = units(db_engine, job_id)[building]["status"] == "running"
        celery_workers.ensure()
        if still:
            return building
    return None


def test_a_worker_killed_in_a_unit_costs_only_time(scene, reference, celery_workers, db_engine):
    """Killed while a unit runs, the workers restart; the sweeper finds the unit lost (its
    heartbeat stale) and queues it again; the job ends with the rows of `citytherm run`. A unit
    can end between the look and the kill: then another job is tried."""
    celery_workers.ensure()
    _, run_job_id = reference
    for _ in range(5):
        job_id = submit(db_engine, scene)
        killed = _kill_in_a_unit(db_engine, job_id, celery_workers)
        job = finished(db_engine, job_id)
        if killed is not None:
            break
    else:
        pytest.fail("in 5 jobs, every unit ended before the workers could be killed in its middle")
    assert job["status"] == "successful", job
    us = units(db_engine, job_id)
    assert all(u["status"] == "successful" for u in us.values()), us
    assert us[killed]["attempts"] >= 2  # it ran again, after the sweeper found it lost
    assert appearances(db_engine, job_id) == dict.fromkeys(BUILDINGS, 1)
    assert job_rows(db_engine, job_id) == job_rows(db_engine, run_job_id)


def _settled(db_engine: Any, job_id: uuid.UUID) -> bool:
    """No unit of the job running, nothing queued, no task of the job on a worker."""
    if any(u["status"] == "running" for u in units(db_engine, job_id).values()):
        return False
    if redis.Redis.from_url(app.conf.broker_url).llen(QUEUE):
        return False
    ids = {u["task_id"] for u in units(db_engine, job_id).values()}
    insp = app.control.inspect(timeout=0.5)
    for found in (insp.active() or {}, insp.reserved() or {}):
        if any(t["id"] in ids for tasks in found.values() for t in tasks):
            return False
    return True


def test_a_dismissed_job_gets_nothing_more(scene, celery_workers, db_engine, service_env):
    celery_workers.ensure()
    job_id = submit(
        db_engine,
        scene,
        RunOptions.build(resolution_px_per_m=10, refine=False, display=False, buildings=scene.cluster),
    )

    def midway() -> bool:
        states = [u["status"] for u in units(db_engine, job_id).values()]
        return "successful" in states and "accepted" in states

    wait_for("a job half done", midway)
    folder = Path(service_env["CITYTHERM_STORAGE_DIR"]) / "jobs" / str(job_id)
    assert any((folder / "units").iterdir())  # the payloads of the units still to run
    with Session(db_engine) as s:
        dismiss(s, job_id=job_id)
    assert not (folder / "units").exists() and not (folder / "prepared.pkl").exists()
    before_units, before_apps = units(db_engine, job_id), appearances(db_engine, job_id)
    assert job_row(db_engine, job_id)["status"] == "dismissed"
    assert not any(u["status"] in ("accepted", "running") for u in before_units.values())
    wait_for("the workers to settle", lambda: _settled(db_engine, job_id))
    after_units = units(db_engine, job_id)
    assert appearances(db_engine, job_id) == before_apps
    assert after_units == before_units  # no unit ran (or counted an attempt) after the dismissal
    dismissed = [g for g, u in after_units.items() if u["status"] == "dismissed"]
    assert dismissed and not set(dismissed) & set(before_apps)
    assert job_row(db_engine, job_id)["status"] == "dismissed"


def test_a_package_with_a_missing_frame_fails_without_retries(scene, celery_workers, db_engine, tmp_path):
    celery_workers.ensure()
    broken = tmp_path / "broken"
    shutil.copytree(scene.package, broken)
    sequence_id = _register(db_engine, "broken", broken)
    missing = read_manifest(broken, check_frames=False).frames[3].file
    (broken / missing).unlink()  # lost from the storage after the sequence was registered
    job_id = submit(db_engine, scene, sequence_id=sequence_id)
    job = finished(db_engine, job_id)
    assert job["status"] == "failed", job
    assert missing in job["message"], job["message"]
    assert units(db_engine, job_id) == {}
    logs = "".join(celery_workers.log(n) for n in celery_workers.names)
    assert not [line for line in logs.splitlines() if "prepare_job" in line and "retry" in line.lower()]

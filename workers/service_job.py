"""The work of the service's Celery tasks (`docs/service.md`); `workers/tasks.py` only wraps it.

In: ids (job uuid as a string, building gml id, model import id), the settings of the process
(`db.settings.Settings`, environment `CITYTHERM_*`), PostGIS and the storage directory. Out: rows
(job and unit states, results through `db.store`), files under `jobs/<job id>/`, further tasks.

- `prepare_job`: the stages of `citytherm run` before the units (`workers.job`: ingest over the
  model's buildings from PostGIS, calibrate (queueing `citytherm.prefetch_frames` first: another
  worker decodes the frames meanwhile, `workers.service_frames`), orient with its windows as tasks
  (`workers.service_windows`), plan; the plan rests on the calibrated priors alone, so when the
  task waits for windows other workers orient it plans then and gives each unit its part of
  the orientation afterwards, `with_sequence`: the same units); one pickled `BuildingUnit` per
  building (`jobs/<id>/units/<name>.pkl`), what `finish` needs (`prepared.pkl`) and the
  manifest-only priors (`priors.pkl`, frame index -> `Pose`, for `frame_pose`); then one
  `job_unit` per building with the id of the task queued for it, and the tasks, the costliest
  first (`unit_cost`: the workers take them in that order, so that no large unit is left alone
  at the end while the other workers idle; the order changes no result).
- `run_unit`: claims the unit (`db.jobs.claim_unit`), runs it (`workers.job.run_unit`), stores
  the result in one transaction in which the job row is locked `FOR SHARE` and checked (a
  dismissed job gets nothing more), keeping its tiles and its result without pixels on the
  storage for the finish in that transaction (`workers.service_results`), then finishes the job
  when it was the last.
- `finish_job`: the results folder (`workers.job.finish`, the writer of `citytherm run`) from the
  results the units kept (a building whose unit kept none: loaded from PostGIS), and its zip (the
  sweeper, model imports and failed tasks: `service_upkeep`).

Prepare and finish run once per job at a time: each holds a session-level advisory lock on its
own connection (released when its process dies), a second delivery finds it held and returns.
Errors: bad input (`BAD_INPUT`) fails the job (or import) with its message, never retried;
transient errors (`TRANSIENT`) propagate so that the task retries with backoff; anything else
fails the job as `<type>: <message>`.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
import uuid
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import kombu.exceptions
import numpy as np
import redis.exceptions
import sqlalchemy.exc
from sqlalchemy import text
from sqlalchemy.orm import Session

from db import jobs
from db.citygml import CityGMLError
from db.errors import InputDataError
from db.import_signals import ImportInterrupted
from db.model_load import ModelBuildingIds, iter_model_buildings, near_box
from db.result_load import load_building_result
from db.results_folder.write import write_tile
from db.sequence_package import PackageError
from db.store import store_building_result
from workers import service_storage as storage
from workers.celery_app import stale_after_s
from workers.job import (
    Calibrated,
    Ingested,
    Oriented,
    Planned,
    RunError,
    RunOptions,
    UnitFailure,
    calibrate,
    finish,
    ingest_buildings,
    orient,
    plan,
    scene_caster,
)
from workers.job import run_unit as run_building
from workers.pipeline.geometry.citymodel import ModelHeader
from workers.pipeline.geometry.crs import UnknownCRSError, same_horizontal
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.transform import CrsTransformError
from workers.pipeline.options import OptionsError
from workers.pipeline.results import BuildingResult
from workers.pipeline.units import BuildingUnit
from workers.run import without_pixels
from workers.service_process import engine, job_dir, job_lock, send, settings
from workers.service_results import keep_result, kept_dir, kept_result
from workers.service_windows import celery_window_map

log = logging.getLogger(__name__)

#: errors worth a retry: the database, the broker or the storage was away for a moment
TRANSIENT: tuple[type[BaseException], ...] = (
    *(sqlalchemy.exc.OperationalError, sqlalchemy.exc.InterfaceError, sqlalchemy.exc.DisconnectionError),
    *(sqlalchemy.exc.TimeoutError, redis.exceptions.ConnectionError, redis.exceptions.TimeoutError),
    *(kombu.exceptions.OperationalError, OSError, ImportInterrupted),
)
#: bad input: the job (or import) fails with the message, no retry
BAD_INPUT: tuple[type[BaseException], ...] = (
    *(InputDataError, PackageError, CityGMLError, RunError, OptionsError, CrsTransformError, UnknownCRSError),
)


def max_deliveries() -> int:
    """How often a prepare, finish or import task is delivered before its job or import fails."""
    return int(settings().task_max_retries) + 2


def fail_job(job_id: uuid.UUID, message: str, error: str | None = None) -> None:
    """Mark a job that is not final yet `failed` with `message` (what API clients read) and
    `error` (the full text, for operators; default: the message)."""
    with Session(engine()) as s:
        if jobs.lock_job(s, job_id=job_id).status not in jobs.FINAL_STATES:
            message, error = message[:2000], (error or message)[:8000]
            jobs.set_job_status(s, job_id=job_id, status="failed", message=message, error=error)
        s.commit()


def public_message(exc: BaseException) -> str:
    """What a client is told: the message of bad input (it names the file or field), else only
    the kind of error (the full text, which may hold SQL or server names, goes to `error_detail`)."""
    if isinstance(exc, BAD_INPUT):
        return str(exc)
    return f"internal error ({type(exc).__name__}); the operators find it in the worker log"


def error_detail(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"


# -- prepare -------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Prepared:
    """What `prepare_job` keeps for `finish_job` (`prepared.pkl`): the stages' results as
    `workers.job.finish` takes them (the units without occluders and sequence data, the
    orientation as its report), the stage timings (s) and the package as reported."""

    ingested: Ingested
    calibrated: Calibrated
    oriented: Oriented
    planned: Planned
    timings: dict[str, float]
    package: str


def _stage(job_id: uuid.UUID, stage: str) -> None:
    with Session(engine()) as s:
        jobs.set_stage(s, job_id=job_id, stage=stage)
        s.commit()


def with_sequence(planned: Planned, oriented: Oriented) -> Planned:
    """`planned` (the plan stage without the sequence orientation: it plans from the calibrated
    priors alone) with each unit's part of `oriented` (`SequenceOrientation.for_frames`): what
    `plan` with `oriented` gives."""
    so = oriented.orientation
    if so is None:
        return planned
    units = tuple(replace(u, sequence=so.for_frames(u.frames)) for u in planned.units)
    return Planned(units, planned.warning)


def _run_stages(job: jobs.JobRecord) -> tuple[Prepared, tuple[Any, ...], dict[int, Pose]]:
    """ingest, calibrate, orient, plan for `job` (as `workers.run.run_job` runs them)."""
    options = RunOptions.from_dict(job.options)
    timings: dict[str, float] = {}
    with engine().connect() as conn:
        m = conn.execute(
            text("SELECT id, name, srs_name, state, citygml_version, gml_name FROM city_model WHERE id = :m"),
            {"m": job.city_model_id},
        ).one()
        seq_sql = "SELECT name, storage_location, srs_name FROM sequence WHERE id = :s"
        seq = conn.execute(text(seq_sql), {"s": job.sequence_id}).first()
        if m.state != "complete":
            raise InputDataError(f"city model {m.name!r} is {m.state}, not complete")
        if seq is None:
            raise RunError(f"job {job.id} has no sequence")
        in_model = (seq.srs_name or "").strip().lower() == "model"  # positions in the model's CRS
        if not in_model and not (seq.srs_name and m.srs_name and same_horizontal(seq.srs_name, m.srs_name)):
            raise RunError(
                f"the sequence's CRS {seq.srs_name} differs from the city model's CRS {m.srs_name}: "
                "a job runs in the model's CRS; record the sequence in it"
            )
        package = storage.storage_path(settings().storage_dir, seq.storage_location)
        header = ModelHeader(version=m.citygml_version or "2.0", srs_name=m.srs_name, name=m.gml_name)

        def near(priors: Any, reach: float) -> Iterator[Any]:
            box = near_box(conn, m.id, [p.center for p in priors], reach) if len(priors) else None
            return iter_model_buildings(conn, m.id, bbox=box) if box else iter([])

        t0 = time.perf_counter()
        ingested = ingest_buildings(
            header, near, package, options, city_model=m.name, model_ids=ModelBuildingIds(conn, m.id)
        )
        timings["ingest"] = time.perf_counter() - t0
    caster = None
    if options.refine and options.calibrate:
        _stage(job.id, "calibrate")
        if ingested.buildings:  # an idle worker decodes the frames meanwhile (`service_frames`)
            send("citytherm.prefetch_frames", str(job.id))
        t0 = time.perf_counter()
        caster = scene_caster(ingested)
        calibrated = calibrate(ingested, options, caster)
        timings["calibrate"] = time.perf_counter() - t0
    else:
        calibrated = calibrate(ingested, options)
    _stage(job.id, "orient")
    t0 = time.perf_counter()
    early: list[tuple[Planned, float]] = []  # planned while other workers orient windows (s)

    def plan_early() -> None:
        t = time.perf_counter()
        without = plan(ingested, calibrated, Oriented(None, {"run": False}), options)
        early.append((without, time.perf_counter() - t))

    windows = celery_window_map(job.id, idle=plan_early)
    oriented = orient(ingested, calibrated, options, caster=caster, map_windows=windows)
    planning = early[0][1] if early else 0.0
    if oriented.report.get("run"):
        timings["orient"] = time.perf_counter() - t0 - planning
    _stage(job.id, "plan")
    t0 = time.perf_counter()
    planned = with_sequence(early[0][0], oriented) if early else plan(ingested, calibrated, oriented, options)
    timings["plan"] = planning + time.perf_counter() - t0
    light = Planned(tuple(replace(u, occluders=(), sequence=None) for u in planned.units), planned.warning)
    kept = Prepared(ingested, calibrated, Oriented(None, oriented.report), light, timings, str(seq.name))
    priors = {f.index: p for f, p in zip(ingested.manifest.frames, ingested.priors, strict=True)}
    return kept, planned.units, priors


def prepare_job(job_id: str) -> str:
    """The prepare task (module docstring). Returns what it did: `queued <n> units`, `skipped`
    (final, or prepared already), `busy` (another delivery prepares it) or `failed`."""
    jid = uuid.UUID(str(job_id))
    with job_lock("prepare", jid) as got:
        if not got:
            return "busy"
        with Session(engine()) as s:
            job = jobs.lock_job(s, job_id=jid)
            if job.status in jobs.FINAL_STATES or job.stage not in jobs.PRE_UNIT_STAGES:
                return "skipped"
            if jobs.count_delivery(s, job_id=jid) > max_deliveries():
                s.commit()
                fail_job(jid, f"prepare gave up after {max_deliveries()} deliveries (its worker died)")
                return "failed"
            if job.status == "accepted":
                jobs.set_job_status(s, job_id=jid, status="running")
            jobs.set_stage(s, job_id=jid, stage="ingest")
            s.commit()
        try:
            kept, units, priors = _run_stages(job)
            payloads = [(storage.unit_path(settings().storage_dir, jid, u.building.id), u) for u in units]
            storage.write_pickles([*payloads, (job_dir(jid) / "priors.pkl", priors),
                                   (job_dir(jid) / "prepared.pkl", kept)])  # fmt: skip
        except TRANSIENT:
            raise
        except Exception as exc:  # bad input, or a stage that cannot go on: the job fails
            log.info("job %s failed in prepare: %s", jid, exc)
            fail_job(jid, public_message(exc), error_detail(exc))
            return "failed"
        tasks = {gml_id: str(uuid.uuid4()) for gml_id in dispatch_order(units)}
        with Session(engine()) as s:
            now = jobs.lock_job(s, job_id=jid)
            if now.status in jobs.FINAL_STATES or now.stage not in jobs.PRE_UNIT_STAGES:
                return "skipped"  # dismissed meanwhile, or another delivery wrote the units
            jobs.add_units(s, job_id=jid, building_gml_ids=list(tasks))
            jobs.set_unit_tasks(s, job_id=jid, task_ids=tasks)
            jobs.set_stage(s, job_id=jid, stage="units")
            s.commit()
    for gml_id, task_id in tasks.items():
        send("citytherm.run_unit", str(jid), gml_id, task_id=task_id)
    if not tasks:
        after_units(jid)
    return f"queued {len(tasks)} units"


# -- units ---------------------------------------------------------------------------------------
#: `unit_cost` weights: CPU seconds per million texels of the building's surfaces, per frame (a
#: least-squares fit over the 23 units of the service bench's drive past the Berlin model, 0.2-4.2
#: CPU s each on a loaded machine, correlation 0.92; only their ratio matters for the order)
COST_PER_MEGATEXEL_S = 0.8
COST_PER_FRAME_S = 0.04


def polygon_area_m2(coords: np.ndarray) -> float:
    """Area (m²) of a planar polygon ring `(N, 3)` (model CRS, metres; closed or not)."""
    v = np.asarray(coords, dtype=np.float64)
    v = v - v[0]  # local origin: projected coordinates are large
    return 0.5 * float(np.linalg.norm(np.cross(v[:-1], v[1:]).sum(axis=0)))


def unit_cost(unit: BuildingUnit) -> float:
    """A rough estimate of a unit's CPU seconds, for the order in which its task is queued: texels
    of its surfaces at the unit's resolution (holes ignored) and frames (`COST_PER_*`)."""
    res = float(unit.options.texel.resolution_px_per_m)
    area = sum(polygon_area_m2(p.exterior.coords) for p in unit.building.iter_polygons())
    return COST_PER_MEGATEXEL_S * area * res * res / 1e6 + COST_PER_FRAME_S * len(unit.frames)


def dispatch_order(units: Iterable[BuildingUnit]) -> list[str]:
    """The units' building ids, costliest first (`unit_cost`; plan order among equals): with
    prefetch 1 the workers take the tasks in the order they are queued, and the longest first
    keeps the last ones short (the longest-processing-time rule)."""
    ranked = sorted(enumerate(units), key=lambda iu: (-unit_cost(iu[1]), iu[0]))
    return [u.building.id for _, u in ranked]


def after_units(job_id: uuid.UUID) -> str:
    """`finish_job_if_done`; queue the finish task when this call finished the job. Returns the
    job's status."""
    with Session(engine()) as s:
        before = jobs.lock_job(s, job_id=job_id).status
        status = jobs.finish_job_if_done(s, job_id=job_id)
        s.commit()
    if before not in jobs.FINAL_STATES and status in ("successful", "failed"):
        send("citytherm.finish_job", str(job_id))
    return status


def run_unit(job_id: str, building_gml_id: str, *, task_id: str) -> str:
    """The unit task (module docstring) as delivery `task_id`. Returns what it did: `stored`,
    `failed` (the unit raised; recorded), or the claim's refusal (`final`, `dismissed`, `busy`,
    `exhausted`)."""
    jid = uuid.UUID(str(job_id))
    st = settings()
    with Session(engine()) as s:
        decision = jobs.claim_unit(
            s,
            job_id=jid,
            building_gml_id=building_gml_id,
            task_id=task_id,
            stale_after_s=stale_after_s(st.unit_timeout_s),
            max_attempts=st.task_max_retries + 1,
        )
        s.commit()
    if decision == "exhausted":
        after_units(jid)
    if decision != "run":
        return decision
    unit = storage.read_pickle(storage.unit_path(st.storage_dir, jid, building_gml_id))
    priors = storage.read_pickle(job_dir(jid) / "priors.pkl")
    result = run_building(unit)
    with Session(engine()) as s:
        job = jobs.lock_job(s, job_id=jid, share=True)  # a dismissal waits for this transaction
        status = jobs.unit_status(s, job_id=jid, building_gml_id=building_gml_id)
        if job.status in jobs.FINAL_STATES or status is None or status in jobs.FINAL_STATES:
            return "dismissed" if job.status in jobs.FINAL_STATES else "final"
        if isinstance(result, UnitFailure):
            failed = {"status": "failed", "error": result.error}
            jobs.set_unit_status(s, job_id=jid, building_gml_id=building_gml_id, **failed)
        else:  # the unit becomes successful in this transaction
            model = job.city_model_id
            store_building_result(s, job_id=jid, model_id=model, result=result, priors=priors, commit=False)
            keep_result(jid, result)  # for the finish (`service_results`); a dismissal waits for it
        s.commit()
    after_units(jid)
    return "failed" if isinstance(result, UnitFailure) else "stored"


# -- finish --------------------------------------------------------------------------------------
def _stored_results(
    s: Session, job: jobs.JobRecord, kept: Prepared, out: Path
) -> tuple[list[BuildingResult], list[UnitFailure], int]:
    """The job's stored results, plan order, tiles in `out` and dropped from memory: each as its
    unit task kept it (`service_results`), else loaded from PostGIS; its failed units
    (`UnitFailure`); how many were loaded from PostGIS."""
    rows = s.execute(
        text(
            "SELECT b.gml_id, u.status, u.error FROM job_unit u JOIN building b ON b.id = u.building_id "
            "WHERE u.job_id = :j"
        ),
        {"j": job.id},
    ).all()
    state = {g: (st, err) for g, st, err in rows}
    results: list[BuildingResult] = []
    failures: list[UnitFailure] = []
    loaded = 0
    for u in kept.planned.units:
        st, err = state.get(u.building.id, ("missing", None))
        if st == "successful":
            gml_id = u.building.id
            mine = kept_result(job.id, gml_id, out)
            if mine is not None:
                results.append(mine)
                continue
            r = load_building_result(s, job_id=job.id, model_id=job.city_model_id, building_gml_id=gml_id)
            for tile in r.tiles:
                write_tile(out, tile)
            results.append(without_pixels(r))
            loaded += 1
        elif st == "failed":
            failures.append(UnitFailure(u.building.id, err or "failed"))
    return results, failures, loaded


def finish_job(job_id: str) -> str:
    """The finish task: `jobs/<id>/results/` (built aside and renamed into place) and
    `results.zip`, then `job.results_location`. Returns `written`, `skipped` (not finished by its
    units, or written already) or `busy`."""
    jid = uuid.UUID(str(job_id))
    with job_lock("finish", jid) as got:
        if not got:
            return "busy"
        with Session(engine()) as s:
            job = jobs.lock_job(s, job_id=jid)
            done = job.results_location is not None and Path(job.results_location).is_dir()
            if job.status not in ("successful", "failed") or job.stage not in ("units", "finish") or done:
                return "skipped"
            if jobs.count_delivery(s, job_id=jid) > 2 * max_deliveries():  # prepare's and finish's
                jobs.note_results_failed(s, job_id=jid, error="finish gave up: its worker died each time")
                s.commit()
                return "failed"
            jobs.set_stage(s, job_id=jid, stage="finish")
            s.commit()
        t0, c0 = time.perf_counter(), time.process_time()
        parts: dict[str, float] = {}  # wall seconds of the finish's parts (its `finish-parts` line)
        kept: Prepared = storage.read_pickle(job_dir(jid) / "prepared.pkl")
        out, build = job_dir(jid) / "results", job_dir(jid) / f".tmp-results-{uuid.uuid4().hex}"
        try:
            build.mkdir(parents=True)
            with Session(engine()) as s:
                results, failures, n_loaded = _stored_results(s, job, kept, build)
                units_s = s.execute(
                    text(
                        "SELECT EXTRACT(EPOCH FROM max(finished_at) - min(started_at)) FROM job_unit "
                        "WHERE job_id = :j"
                    ),
                    {"j": jid},
                ).scalar()
            timings = {**kept.timings, "units": float(units_s or 0.0)}
            parts["gather"] = time.perf_counter() - t0
            options = RunOptions.from_dict(job.options)
            finish(build, kept.ingested, kept.calibrated, kept.oriented, kept.planned, results, failures,
                   options, timings, package=kept.package)
            shutil.rmtree(out, ignore_errors=True)
            os.replace(build, out)
        finally:
            shutil.rmtree(build, ignore_errors=True)
        parts["write"] = time.perf_counter() - t0 - parts["gather"]
        storage.zip_folder(out, job_dir(jid) / "results.zip")
        parts["zip"] = time.perf_counter() - t0 - parts["gather"] - parts["write"]
        mounting = json.loads((out / "orientation.json").read_text(encoding="utf-8")).get("mounting")
        with Session(engine()) as s:
            jobs.set_job_results(s, job_id=jid, location=str(out), timings_s=timings, mounting=mounting)
            s.commit()
        # the unit payloads and kept results served their purpose (results and rows are written)
        shutil.rmtree(job_dir(jid) / "units", ignore_errors=True)
        shutil.rmtree(kept_dir(jid), ignore_errors=True)
        (job_dir(jid) / "priors.pkl").unlink(missing_ok=True)
    line = {"job": str(jid), **{k: round(v, 3) for k, v in parts.items()}, "kept": len(results) - n_loaded,
            "loaded": n_loaded, "wall_s": round(time.perf_counter() - t0, 3),
            "cpu_s": round(time.process_time() - c0, 3)}  # fmt: skip
    log.info("finish-parts %s", json.dumps(line))
    return "written"

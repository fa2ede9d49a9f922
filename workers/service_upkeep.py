"""The service's upkeep (`docs/service.md`), beside the job stages of `workers.service_job`: the
sweeper, model imports, and the failure of a task that gave up. `workers/tasks.py` only wraps it.

In: ids, the process's settings, PostGIS and the storage directory. Out: rows (job, unit and
import states), further tasks.
"""

from __future__ import annotations

import logging
import uuid
from pathlib import Path
from typing import Any

from sqlalchemy import text
from sqlalchemy.orm import Session

from db import jobs
from db.errors import InputDataError, ModelExistsError
from db.importer import import_citygml
from db.service_models import ModelImport
from db.service_records import get_model_import, imports_to_requeue, remove_abandoned_uploads
from workers.celery_app import stale_after_s
from workers.service_job import (
    TRANSIENT,
    after_units,
    engine,
    error_detail,
    fail_job,
    max_deliveries,
    public_message,
    send,
    settings,
)

__all__ = ["gave_up", "import_model", "sweep"]

log = logging.getLogger(__name__)


def sweep() -> dict[str, int]:
    """The sweeper (`docs/service.md`): finish jobs whose units are all final; queue again the
    finish of final jobs without results, the prepare of jobs stuck before their units, and the
    units whose worker died (`running`, heartbeat older than `stale_after_s`) or whose message
    was lost (`accepted`, queued as long ago); remove abandoned uploads. Returns counts."""
    st = settings()
    stale = stale_after_s(st.unit_timeout_s)
    counts = dict.fromkeys(("finished", "finish", "prepare", "units", "imports", "uploads"), 0)
    with Session(engine()) as s:
        done = jobs.jobs_to_sweep(s, which="done", older_than_s=0.0)
        s.commit()
    for jid in done:
        counts["finished"] += after_units(jid) in ("successful", "failed")
    for which, task in (("results", "citytherm.finish_job"), ("prepare", "citytherm.prepare_job")):
        with Session(engine()) as s:
            ids = jobs.jobs_to_sweep(s, which=which, older_than_s=stale)
            s.commit()
        for jid in ids:
            send(task, str(jid))
        counts["finish" if which == "results" else "prepare"] = len(ids)
    with Session(engine()) as s:
        units = jobs.requeue_units(s, stale_after_s=stale, queued_after_s=stale)
        s.commit()
    for jid, gml_id, task_id in units:
        send("citytherm.run_unit", str(jid), gml_id, task_id=task_id)
    counts["units"] = len(units)
    with Session(engine()) as s:
        imports = imports_to_requeue(s, older_than_s=stale)
        s.commit()
    for import_id in imports:
        send("citytherm.import_model", import_id)
    counts["imports"] = len(imports)
    with Session(engine()) as s:
        counts["uploads"] = len(remove_abandoned_uploads(s, st).sequence_uploads)
    if any(counts.values()):
        log.info("sweep: %s", counts)
    return counts


def _set_import(import_id: int, *, status: str, message: str | None, model_id: int | None = None) -> None:
    with Session(engine()) as s:
        row = get_model_import(s, import_id=import_id, lock=True)
        row.status, row.message, row.city_model_id = status, message, model_id
        row.progress = 1.0 if status == "ready" else row.progress
        row.updated_at = s.execute(text("SELECT now()")).scalar_one()
        s.commit()


def import_model(import_id: int) -> str:
    """The import task: `model_import.upload_path` into the database as `model_import.name`
    (`db.importer.import_citygml`); the import becomes `ready` with its city model, or `failed`
    with the message; the upload is removed. Returns the new status (or `skipped`)."""
    with Session(engine()) as s:
        row: ModelImport = get_model_import(s, import_id=int(import_id))
        status, name, upload = row.status, row.name, row.upload_path
    if status != "importing":
        return "skipped"
    path = Path(upload) if upload else None
    with Session(engine()) as s:
        count = "UPDATE model_import SET attempts = attempts + 1 WHERE id = :i RETURNING attempts"
        deliveries = int(s.execute(text(count), {"i": int(import_id)}).scalar_one())
        s.commit()
    if deliveries > max_deliveries():
        _set_import(import_id, status="failed", message=f"import gave up after {max_deliveries()} deliveries")
        if path is not None:
            path.unlink(missing_ok=True)
        return "failed"
    try:
        if path is None or not path.is_file():
            raise InputDataError(f"the upload of city model {name!r} is missing ({upload})")
        model_id = import_citygml(engine(), path, name=name).model_id
    except ModelExistsError:  # an earlier delivery imported it and died before saying so
        with engine().connect() as conn:
            found = conn.execute(text("SELECT id FROM city_model WHERE name = :n"), {"n": name}).scalar()
        if found is None:  # another delivery is importing it right now (the name lock is held)
            return "busy"
        model_id = int(found)
    except TRANSIENT:
        raise
    except Exception as exc:
        log.info("import %s failed: %s", import_id, error_detail(exc))
        _set_import(import_id, status="failed", message=public_message(exc)[:2000])
        if path is not None:
            path.unlink(missing_ok=True)
        return "failed"
    _set_import(import_id, status="ready", message=None, model_id=model_id)
    path.unlink(missing_ok=True)
    return "ready"


def gave_up(task: str, args: tuple[Any, ...], exc: BaseException) -> None:
    """Record the failure of a task that ran out of retries (or raised unexpectedly): its job,
    unit or import fails with the error. Best effort: the database may be what is away."""
    message = f"gave up after retries: {error_detail(exc)}"[:2000]  # for operators (error columns)
    public = f"gave up after retries: {public_message(exc)}"[:2000]  # for API clients
    try:
        if task == "citytherm.run_unit":
            jid = uuid.UUID(str(args[0]))
            with Session(engine()) as s:
                gml_id, failed = str(args[1]), {"status": "failed", "error": message}
                jobs.set_unit_status(s, job_id=jid, building_gml_id=gml_id, **failed)
                s.commit()
            after_units(jid)
        elif task == "citytherm.prepare_job":
            fail_job(uuid.UUID(str(args[0])), public, message)
        elif task == "citytherm.finish_job":  # the job is final: its results are what failed
            with Session(engine()) as s:
                jobs.note_results_failed(s, job_id=uuid.UUID(str(args[0])), error=message)
                s.commit()
        elif task == "citytherm.import_model":
            _set_import(int(args[0]), status="failed", message=public)
    except Exception:
        log.exception("could not record the failure of %s%r", task, args)

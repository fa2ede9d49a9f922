"""What the HTTP API calls to start and stop work (`docs/service.md`): submit a job, dismiss
it, queue a model import. Keyword-only, ids in and out; tasks are queued by name through the
Celery app (`workers.celery_app`), so the API process imports no task code.

A job's row is committed before its first task is queued: the task always finds it, and a queue
that was away leaves an `accepted` job that the sweeper queues again.
"""

from __future__ import annotations

import logging
import shutil
import uuid

from sqlalchemy.orm import Session

from db.jobs import FINAL_STATES, create_job, dismiss_job, lock_job, unit_task_ids
from db.settings import Settings
from workers.celery_app import app
from workers.job import RunOptions
from workers.service_storage import job_dir

__all__ = ["dismiss", "queue_model_import", "submit_job"]

log = logging.getLogger(__name__)


def submit_job(session: Session, *, model_id: int, sequence_id: int, options: RunOptions) -> uuid.UUID:
    """Create the job (status `accepted`, `options.to_dict()` stored, theme `options.theme`),
    commit, and queue `citytherm.prepare_job`. Returns the job id."""
    job_id = create_job(
        session, model_id=model_id, sequence_id=sequence_id, theme=options.theme, options=options.to_dict()
    )
    session.commit()
    try:
        app.send_task("citytherm.prepare_job", args=(str(job_id),))
    except Exception:  # the broker is away: the job is recorded, the sweeper queues it later
        log.warning("job %s accepted, not queued (broker away): the sweeper queues it", job_id, exc_info=True)
    return job_id


def dismiss(session: Session, *, job_id: uuid.UUID) -> None:
    """Dismiss the job (`db.jobs.dismiss_job`: its pending units too; stored results stay),
    commit, then revoke the tasks of its units: queued ones are dropped when delivered, running
    ones are terminated (a running unit that is not stopped in time finds the job dismissed when
    it stores, and writes nothing). Raises `NotFoundError`, `StateError` (already final)."""
    job = lock_job(session, job_id=job_id)
    tasks = unit_task_ids(session, job_id=job_id) if job.status not in FINAL_STATES else []
    dismiss_job(session, job_id=job_id)
    session.commit()
    # a dismissed job never finishes: its unit payloads and the results its units kept for the
    # finish go now (a queued unit finds the job dismissed before it would read one; the stored
    # results stay)
    folder = job_dir(Settings().storage_dir, job_id)
    shutil.rmtree(folder / "units", ignore_errors=True)
    shutil.rmtree(folder / "kept", ignore_errors=True)
    for name in ("priors.pkl", "prepared.pkl"):
        (folder / name).unlink(missing_ok=True)
    queued = [t for t, status in tasks if status == "accepted"]
    running = [t for t, status in tasks if status == "running"]
    try:
        if queued:
            app.control.revoke(queued)
        if running:
            app.control.revoke(running, terminate=True, signal="SIGTERM")
    except Exception:  # the broker is away: the units find the job dismissed and write nothing
        log.warning("job %s dismissed; its tasks not revoked (broker away)", job_id, exc_info=True)


def queue_model_import(import_id: int) -> None:
    """Queue `citytherm.import_model` for a `model_import` whose upload is stored."""
    app.send_task("citytherm.import_model", args=(int(import_id),))

"""The Celery tasks of the service (`docs/service.md`): thin wrappers, ids as arguments; the work
is in `workers.service_job`, `workers.service_windows`, `workers.service_frames` and
`workers.service_upkeep`.

Every task retries transient errors (`service_job.TRANSIENT`: database, broker, storage) with
exponential backoff (jittered, at most 300 s apart), at most `Settings.task_max_retries` times
(`workers.celery_app` annotations), and never bad input (`service_job.BAD_INPUT`, which the work
records as the job's or import's failure itself). A task that gives up records its failure
(`service_upkeep.gave_up`).

Every task run leaves one log line `task-span {json}` (logger `workers.tasks`, INFO): task name,
arguments (ids), worker process id, start and end (Unix time, s), wall and CPU seconds of the
process (`time.process_time`: all its threads) and the task's return value: the timeline of a job
over the workers (`bench/service.py` reads it from the worker logs).
"""

from __future__ import annotations

import json
import logging
import os
import time
from typing import Any

from celery import Task
from celery.signals import task_postrun, task_prerun, worker_process_init

from workers import service_frames, service_job, service_upkeep, service_windows
from workers.celery_app import app
from workers.pool import cap_library_threads

log = logging.getLogger(__name__)

#: per task id: (Unix time, process CPU seconds) when it started in this process
_STARTED: dict[str, tuple[float, float]] = {}


@worker_process_init.connect
def preload(**_: Any) -> None:
    """Each pool process imports the pipeline and Open3D (about 3 s) when it starts, as
    `citytherm run` preloads its process pool, so that no job waits for it; and caps the
    threads of OpenCV and Open3D as `citytherm worker --threads` asked (`pool.cap_library_threads`;
    OpenBLAS and OpenMP were capped by the environment the worker started with)."""
    import open3d  # noqa: F401

    import workers.pipeline.units  # noqa: F401

    cap_library_threads()


@task_prerun.connect
def task_started(task_id: str | None = None, **_: Any) -> None:
    """Note when a task starts in this process (its `task-span` line, module docstring)."""
    if task_id is not None:
        _STARTED[task_id] = (time.time(), time.process_time())


@task_postrun.connect
def task_ended(
    task_id: str | None = None, task: Task | None = None, args: Any = None, retval: Any = None, **_: Any
) -> None:
    """Log the task's `task-span` line (module docstring)."""
    started = _STARTED.pop(task_id, None) if task_id is not None else None
    if started is None or task is None:
        return
    end, cpu = time.time(), time.process_time()
    span = {
        "task": task.name,
        "args": [str(a) for a in (args or ())],
        "pid": os.getpid(),
        "start": round(started[0], 3),
        "end": round(end, 3),
        "wall_s": round(end - started[0], 3),
        "cpu_s": round(cpu - started[1], 3),
        "result": str(retval)[:80],
    }
    log.info("task-span %s", json.dumps(span))


class ServiceTask(Task):
    """Base of the citytherm tasks: autoretry for transient errors, failure recorded."""

    autoretry_for = service_job.TRANSIENT
    dont_autoretry_for = service_job.BAD_INPUT
    retry_backoff = 2
    retry_backoff_max = 300
    retry_jitter = True

    def on_failure(self, exc: BaseException, task_id: str, args: Any, kwargs: Any, einfo: Any) -> None:
        """Out of retries, or an unexpected error: the job, unit or import fails with it."""
        service_upkeep.gave_up(self.name, tuple(args or ()), exc)


@app.task(base=ServiceTask, name="citytherm.import_model")
def import_model(import_id: int) -> str:
    """Import the stored CityGML upload of model import `import_id`."""
    return service_upkeep.import_model(int(import_id))


@app.task(base=ServiceTask, name="citytherm.prepare_job")
def prepare_job(job_id: str) -> str:
    """Ingest, calibrate, orient and plan job `job_id`; queue its units."""
    return service_job.prepare_job(job_id)


@app.task(base=ServiceTask, name="citytherm.orient_window")
def orient_window(job_id: str, k: int) -> str:
    """Run window `k` of job `job_id`'s sequence orientation (its prepare task merges them)."""
    return service_windows.orient_window_task(job_id, int(k))


@app.task(base=ServiceTask, name="citytherm.prefetch_frames")
def prefetch_frames(job_id: str) -> str:
    """Decode job `job_id`'s frames into this process's frame cache while its prepare task
    calibrates (best effort, never retried)."""
    return service_frames.prefetch_frames(job_id)


@app.task(base=ServiceTask, bind=True, name="citytherm.run_unit")
def run_unit(self: Task, job_id: str, building_gml_id: str) -> str:
    """Run and store one building unit of job `job_id`."""
    return service_job.run_unit(job_id, building_gml_id, task_id=str(self.request.id))


@app.task(base=ServiceTask, name="citytherm.finish_job")
def finish_job(job_id: str) -> str:
    """Write the results folder of job `job_id` and its zip."""
    return service_job.finish_job(job_id)


@app.task(base=ServiceTask, name="citytherm.sweep")
def sweep() -> dict[str, int]:
    """Find lost work in the database and queue it again; remove abandoned uploads."""
    return service_upkeep.sweep()

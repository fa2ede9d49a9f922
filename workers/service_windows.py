"""The orient stage's windows as Celery tasks (issue 18 item 3, issue 14's speed-up).

In: a job id, the window tasks of its sequence orientation
(`pipeline.orientation.sequence_windows.WindowTask`, planned by the prepare task), the storage
directory and PostGIS (advisory locks). Out: one `WindowResult` per window, merged by the prepare
task as `citytherm run` merges them (`sequence.merge_windows`).

How (`celery_window_map`, the prepare task's `map_windows`): the prepare task writes every window
task to `jobs/<id>/windows/<k>.task.pkl` and queues `citytherm.orient_window(job id, k)` for each
(ids only); then it works through the windows itself, in order, taking every window no other worker
holds, and waits for the others (looking for their results every `LOOK_S`, trying their locks
every `POLL_S`). Whoever runs window k holds the session-level advisory lock
`citytherm-window-<k>:<job id>` (`service_process.job_lock`) and writes
`jobs/<id>/windows/<k>.result.pkl` atomically before releasing it; a window whose result exists is
never run again; each run of a window logs a `window-span {json}` line (window, job, process, start
and end in Unix time, CPU seconds; the timeline `bench/service.py` draws). So a window runs once at
a time and its result is reused by a repeated delivery of the prepare task; a worker SIGKILLed in a
window drops its connection and so its lock, and the prepare task (or another delivery) runs that
window. A window that raises in a window task is run again by the prepare task, where it raises
into the orient stage as it would in `citytherm run`. No chord and no result backend: completion is
decided from the results on the shared storage by the one prepare task that waits for them, and the
job's state stays in PostGIS.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from sqlalchemy import text
from sqlalchemy.orm import Session

from db import jobs
from workers import service_storage as storage
from workers.pipeline.orientation.sequence import WindowMap, WindowResult, WindowTask, orient_window
from workers.service_process import engine, job_dir, job_lock, send

log = logging.getLogger(__name__)

#: seconds between two tries of the locks of windows other workers hold (a dead holder's lock is
#: free then) ...
POLL_S = 0.2
#: ... and between two looks for their results on the storage (no database query), so that the
#: merge follows the last window at once
LOOK_S = 0.02


def windows_dir(job_id: uuid.UUID) -> Path:
    """The folder of this job's window tasks and results."""
    return job_dir(job_id) / "windows"


def _task_path(job_id: uuid.UUID, k: int) -> Path:
    return windows_dir(job_id) / f"{int(k)}.task.pkl"


def _result_path(job_id: uuid.UUID, k: int) -> Path:
    return windows_dir(job_id) / f"{int(k)}.result.pkl"


def _stored(job_id: uuid.UUID, k: int) -> WindowResult | None:
    path = _result_path(job_id, k)
    return storage.read_pickle(path) if path.exists() else None


def _take(
    job_id: uuid.UUID, task: WindowTask, function: Callable[[WindowTask], WindowResult]
) -> WindowResult | None:
    """Window `task`'s result: stored, or run here under its lock and stored; None while another
    worker holds the lock."""
    done = _stored(job_id, task.index)
    if done is not None:
        return done
    with job_lock(f"window-{task.index}", job_id) as got:
        if not got:
            return None
        done = _stored(job_id, task.index)  # finished between the look and the lock
        if done is None:
            t0, c0 = time.time(), time.process_time()
            done = function(task)
            storage.write_pickle(_result_path(job_id, task.index), done)
            span = {"window": task.index, "job": str(job_id), "pid": os.getpid(),
                    "start": round(t0, 3), "end": round(time.time(), 3),
                    "cpu_s": round(time.process_time() - c0, 3)}  # fmt: skip
            log.info("window-span %s", json.dumps(span))
    return done


def _until_a_result(job_id: uuid.UUID, pending: list[int], wait_s: float) -> None:
    """Sleep until one of the `pending` windows has a stored result, at most `wait_s` seconds
    (a look every `LOOK_S`)."""
    end = time.monotonic() + wait_s
    while not any(_result_path(job_id, k).exists() for k in pending):
        left = end - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(LOOK_S, left))


def celery_window_map(
    job_id: uuid.UUID, poll_s: float = POLL_S, idle: Callable[[], None] | None = None
) -> WindowMap:
    """The prepare task's `map_windows` for job `job_id` (module docstring): results in window
    order, once all are there. A single window runs here without tasks. The window files are
    removed when the results have been read (or a window raised here: the orient stage fails as
    in `citytherm run`). `idle` is called once, the first time this process has no window left
    to take and waits for windows other workers hold (the prepare task plans its units then)."""

    def run(
        function: Callable[[WindowTask], WindowResult], items: Iterable[WindowTask]
    ) -> Iterator[WindowResult]:
        tasks = list(items)
        if len(tasks) <= 1:
            yield from map(function, tasks)
            return
        for t in tasks:
            storage.write_pickle(_task_path(job_id, t.index), t)
        for t in tasks:
            if not _result_path(job_id, t.index).exists():
                send("citytherm.orient_window", str(job_id), t.index)
        results: dict[int, WindowResult] = {}
        waiting = idle
        try:
            while len(results) < len(tasks):
                for t in tasks:
                    if t.index not in results and (r := _take(job_id, t, function)) is not None:
                        results[t.index] = r
                if len(results) < len(tasks):
                    if waiting is not None:
                        waiting, call = None, waiting
                        call()
                    else:
                        _until_a_result(job_id, [t.index for t in tasks if t.index not in results], poll_s)
        finally:  # merged, or the stage failed: window tasks still queued find nothing to do
            shutil.rmtree(windows_dir(job_id), ignore_errors=True)
        for t in tasks:
            yield results[t.index]

    return run


def job_status(job_id: uuid.UUID) -> str | None:
    """The job's status (None: no such job)."""
    with Session(engine()) as s:
        return s.execute(text("SELECT status FROM job WHERE id = :j"), {"j": job_id}).scalar()


def orient_window_task(job_id: str, k: int) -> str:
    """The window task: run window `k` of job `job_id` unless it is done, held, gone (the
    prepare task merged the windows already) or the job is final. Returns `oriented`, `done`,
    `busy`, `gone` or `skipped`."""
    jid = uuid.UUID(str(job_id))
    if _result_path(jid, k).exists():
        return "done"
    status = job_status(jid)
    if status is None or status in jobs.FINAL_STATES:
        return "skipped"
    path = _task_path(jid, k)
    if not path.exists():
        return "gone"
    try:
        task: WindowTask = storage.read_pickle(path)
    except FileNotFoundError:  # removed by the prepare task meanwhile
        return "gone"
    return "oriented" if _take(jid, task, orient_window) is not None else "busy"

"""What every service task of this process shares: its settings, its database engine (one per
process: a forked worker makes its own), the job folders on the shared storage, queueing a task
by name, and the advisory lock a task holds on a job (`job_lock`). Below `workers.service_job`
and `workers.service_windows`, which both build on it.
"""

from __future__ import annotations

import functools
import os
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, text

from db.session import make_engine
from db.settings import Settings
from workers import service_storage as storage
from workers.celery_app import app


# -- the process's settings, database and storage ----------------------------------------------
@functools.cache
def settings() -> Settings:
    """This process's settings (read once, from the environment)."""
    return Settings()


_ENGINE: dict[int, Engine] = {}
_INHERITED: list[Engine] = []  # a parent's engines: kept, so their connections are never closed here


def engine() -> Engine:
    """This process's database engine (a forked worker process makes its own)."""
    pid = os.getpid()
    if pid not in _ENGINE:
        _INHERITED.extend(_ENGINE.values())
        _ENGINE.clear()
        _ENGINE[pid] = make_engine(settings())
    return _ENGINE[pid]


def job_dir(job_id: uuid.UUID | str) -> Path:
    """This job's folder in the storage directory."""
    return storage.job_dir(settings().storage_dir, job_id)


def send(name: str, *args: Any, task_id: str | None = None) -> str:
    """Queue task `name` with `args` (ids only); returns its task id."""
    return str(app.send_task(name, args=args, task_id=task_id or str(uuid.uuid4())).id)


@contextmanager
def job_lock(kind: str, job_id: uuid.UUID) -> Iterator[bool]:
    """A session-level advisory lock `citytherm-<kind>:<job id>` on a connection of its own, held
    while the block runs; yields False when another session holds it."""
    with engine().connect() as conn:
        key = {"k": f"citytherm-{kind}:{job_id}"}
        got = bool(conn.execute(text("SELECT pg_try_advisory_lock(hashtext(:k))"), key).scalar())
        conn.commit()
        try:
            yield got
        finally:
            if got:
                try:
                    conn.execute(text("SELECT pg_advisory_unlock(hashtext(:k))"), key)
                    conn.commit()
                except Exception:  # closing the connection releases it
                    conn.invalidate()

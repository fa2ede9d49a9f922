"""`citytherm worker`: a Celery worker of the service (prefork), in this process.

    citytherm worker [--concurrency N] [--threads T] [--queues citytherm] [--beat/--no-beat] [--loglevel INFO]

Reads the same settings as every entry point (`CITYTHERM_DATABASE_URL`, `CITYTHERM_REDIS_URL`,
`CITYTHERM_STORAGE_DIR`, `CITYTHERM_UNIT_TIMEOUT_S`, ...; `db.settings.Settings`). `--beat` also
runs the sweeper's schedule (Celery beat embedded, every `CITYTHERM_SWEEP_INTERVAL_S`): give it
to exactly one worker of a deployment. Equivalent to `celery -A workers.celery_app worker`.

Library threads (issue 14): each worker process runs one task at a time, and OpenBLAS, OpenMP,
OpenCV and Open3D would each start a thread per core in it, so N worker processes on N cores
oversubscribe them. `--threads T` (`CITYTHERM_WORKER_THREADS`; default cores // concurrency, at
least 1; 0: no cap) caps each library at T threads per process. OpenBLAS and OpenMP read their
caps from the environment when they load, and this command's process has loaded numpy already
(the CLI imports it), so the worker runs in a fresh interpreter started with the capped
environment (`os.execve`, same process id) before the pipeline is imported; its pool processes
cap OpenCV and Open3D when they start (`workers.pool.cap_library_threads`).
"""

from __future__ import annotations

import os
import socket
import sys

import typer

from db.settings import get_settings
from workers.pool import THREADS_VAR, library_thread_env


def library_threads(threads: int | None, concurrency: int, cores: int | None = None) -> int:
    """Threads per library and worker process: `threads` when given (0: no cap), else
    cores // concurrency, at least 1."""
    if threads is not None:
        if threads < 0:
            raise typer.BadParameter(f"--threads must be >= 0, got {threads}")
        return threads
    return max(1, (cores or os.cpu_count() or 1) // max(1, concurrency))


def worker(
    concurrency: int | None = typer.Option(
        None, "--concurrency", "-c", help="Worker processes (default: CITYTHERM_WORKER_CONCURRENCY)."
    ),
    threads: int | None = typer.Option(
        None,
        "--threads",
        help="Library threads per process (default: CITYTHERM_WORKER_THREADS, else cores // concurrency; "
        "0: no cap).",
    ),
    queues: str = typer.Option("citytherm", "--queues", "-Q", help="Comma-separated queues to consume."),
    beat: bool = typer.Option(False, "--beat/--no-beat", help="Also run the sweeper (one worker)."),
    loglevel: str = typer.Option("INFO", "--loglevel", "-l", help="Log level."),
    hostname: str | None = typer.Option(None, "--hostname", "-n", help="Node name (default: unique)."),
) -> None:
    """Start a Celery worker (prefork) that runs the service's tasks."""
    from workers.celery_app import SWEEP_QUEUE, configure

    settings = get_settings()
    n = concurrency if concurrency is not None else settings.worker_concurrency
    if n < 1:
        raise typer.BadParameter(f"--concurrency must be >= 1, got {n}")
    cap = library_threads(threads if threads is not None else settings.worker_threads, n)
    if beat and SWEEP_QUEUE not in queues.split(","):
        queues = f"{queues},{SWEEP_QUEUE}"  # the sweeper's tasks, apart from the work's backlog
    argv = [
        "worker",
        f"--concurrency={n}",
        "--pool=prefork",
        f"--queues={queues}",
        f"--loglevel={loglevel}",
        f"--hostname={hostname or f'citytherm-{os.getpid()}@{socket.gethostname()}'}",
        "--without-gossip",
        "--without-mingle",
    ]
    if beat:
        storage = settings.storage_dir.resolve()
        storage.mkdir(parents=True, exist_ok=True)
        argv += ["--beat", f"--schedule={storage / 'celerybeat-schedule'}"]
    if cap > 0 and os.environ.get(THREADS_VAR) != str(cap):
        # a fresh interpreter whose libraries load with the caps (module docstring)
        env = {**os.environ, **library_thread_env(cap)}
        os.execve(sys.executable, [sys.executable, "-m", "celery", "-A", "workers.celery_app", *argv], env)
    configure(settings).worker_main(argv)


def register(root: typer.Typer) -> None:
    """Add `citytherm worker` to the root app."""
    root.command("worker")(worker)

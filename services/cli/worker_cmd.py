"""`citytherm worker`: a Celery worker of the service (prefork), in this process.

    citytherm worker [--concurrency N] [--queues citytherm] [--beat/--no-beat] [--loglevel INFO]

Reads the same settings as every entry point (`CITYTHERM_DATABASE_URL`, `CITYTHERM_REDIS_URL`,
`CITYTHERM_STORAGE_DIR`, `CITYTHERM_UNIT_TIMEOUT_S`, ...; `db.settings.Settings`). `--beat` also
runs the sweeper's schedule (Celery beat embedded, every `CITYTHERM_SWEEP_INTERVAL_S`): give it
to exactly one worker of a deployment. Equivalent to `celery -A workers.celery_app worker`.
"""

from __future__ import annotations

import os
import socket

import typer

from db.settings import get_settings


def worker(
    concurrency: int | None = typer.Option(
        None, "--concurrency", "-c", help="Worker processes (default: CITYTHERM_WORKER_CONCURRENCY)."
    ),
    queues: str = typer.Option("citytherm", "--queues", "-Q", help="Comma-separated queues to consume."),
    beat: bool = typer.Option(False, "--beat/--no-beat", help="Also run the sweeper (one worker)."),
    loglevel: str = typer.Option("INFO", "--loglevel", "-l", help="Log level."),
    hostname: str | None = typer.Option(None, "--hostname", "-n", help="Node name (default: unique)."),
) -> None:
    """Start a Celery worker (prefork) that runs the service's tasks."""
    from workers.celery_app import SWEEP_QUEUE, configure

    settings = get_settings()
    app = configure(settings)
    n = concurrency if concurrency is not None else settings.worker_concurrency
    if n < 1:
        raise typer.BadParameter(f"--concurrency must be >= 1, got {n}")
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
    app.worker_main(argv)


def register(root: typer.Typer) -> None:
    """Add `citytherm worker` to the root app."""
    root.command("worker")(worker)

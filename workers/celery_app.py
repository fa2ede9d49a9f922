"""The Celery app of the citytherm workers (`docs/service.md`): Redis broker, no result backend.

`celery -A workers.celery_app worker` (or `citytherm worker`) finds the module-level `app`. Its
configuration comes from `db.settings.Settings` (environment `CITYTHERM_*`) when the app is
first configured (first use: sending a task, starting a worker), not when this module is imported;
`configure(settings)` sets it explicitly (the API and tests call it with their own settings).

Delivery: tasks carry ids only; PostGIS is the record of every state, so results are ignored
(`task_ignore_result`, no backend). A task is acknowledged after it ran (`task_acks_late`) and
given back to the queue when its worker process dies (`task_reject_on_worker_lost`); each worker
process reserves one message at a time (`worker_prefetch_multiplier = 1`). Redis gives an
unacknowledged message of a worker that vanished to another after `visibility_timeout`, which is
above the longest task time limit, so a long task is never delivered twice while it runs; the
sweeper (`citytherm.sweep`, every `sweep_interval_s`) finds lost work sooner from the database.

Time limits (seconds, from `unit_timeout_s` = T): a building unit gets a soft limit of T (the unit
then fails with `SoftTimeLimitExceeded`) and a hard limit of T + `grace_s(T)`; the sweeper takes a
unit `running` for longer than that as lost. Prepare, orientation windows, finish and model
imports get 4 T.

The sweeper runs from Celery beat: `citytherm worker --beat` embeds it in one worker (`-B`); run
exactly one beat per deployment (a second one only sweeps twice: the sweep locks what it
re-queues with `SKIP LOCKED`, so it does no harm).
"""

from __future__ import annotations

from typing import Any

from celery import Celery

from db.settings import Settings

__all__ = [
    "QUEUE", "SWEEP_QUEUE", "TASK_NAMES", "app", "celery_config", "configure", "grace_s", "stale_after_s"
]  # fmt: skip

#: the queue of the work (imports, prepares, units, finishes)
QUEUE = "citytherm"
#: the sweeper's own queue, consumed by the `--beat` worker beside QUEUE: a backlog of units in
#: QUEUE never delays (or expires) a sweep
SWEEP_QUEUE = "citytherm-sweep"
TASK_NAMES = (
    "citytherm.import_model",
    "citytherm.prepare_job",
    "citytherm.orient_window",
    "citytherm.prefetch_frames",
    "citytherm.run_unit",
    "citytherm.finish_job",
    "citytherm.sweep",
)


def grace_s(unit_timeout_s: float) -> float:
    """Seconds between a unit's soft and hard time limit: a tenth of the timeout, 5 to 60 s."""
    return min(60.0, max(5.0, 0.1 * float(unit_timeout_s)))


def stale_after_s(unit_timeout_s: float) -> float:
    """Age in seconds of a unit's heartbeat after which its task is certainly over (the hard
    time limit has passed) and the unit is taken as lost: T + 2 * grace."""
    return float(unit_timeout_s) + 2.0 * grace_s(unit_timeout_s)


def celery_config(settings: Settings) -> dict[str, Any]:
    """The Celery configuration (lower-case setting names) for `settings`; see the module
    docstring for the choices."""
    unit = float(settings.unit_timeout_s)
    long = 4.0 * unit
    limits = {"soft_time_limit": long, "time_limit": long + grace_s(long)}
    retries = int(settings.task_max_retries)
    annotations = {
        "citytherm.run_unit": {
            "soft_time_limit": unit,
            "time_limit": unit + grace_s(unit),
            "max_retries": retries,
        },
        "citytherm.prepare_job": {**limits, "max_retries": retries},
        "citytherm.orient_window": {**limits, "max_retries": retries},
        "citytherm.prefetch_frames": {**limits, "max_retries": 0},
        "citytherm.finish_job": {**limits, "max_retries": retries},
        "citytherm.import_model": {**limits, "max_retries": retries},
        "citytherm.sweep": {"soft_time_limit": 300.0, "time_limit": 360.0, "max_retries": 0},
    }
    return {
        "broker_url": settings.redis_url,
        "broker_connection_retry_on_startup": True,
        "broker_transport_options": {"visibility_timeout": int(long + grace_s(long) + 600)},
        "result_backend": None,
        "task_ignore_result": True,
        "task_acks_late": True,
        "task_reject_on_worker_lost": True,
        "task_acks_on_failure_or_timeout": True,
        "worker_prefetch_multiplier": 1,
        # a pool process imports the pipeline and Open3D when it starts (`workers.tasks`): give it
        # the time that takes on a loaded machine before its parent gives up on it
        "worker_proc_alive_timeout": 120.0,
        "task_default_queue": QUEUE,
        "task_routes": {"citytherm.sweep": {"queue": SWEEP_QUEUE}},
        "task_serializer": "json",
        "accept_content": ["json"],
        "task_annotations": annotations,
        "worker_hijack_root_logger": False,
        "worker_send_task_events": False,
        "beat_schedule": {
            "citytherm-sweep": {
                "task": "citytherm.sweep",
                "schedule": float(settings.sweep_interval_s),
                "options": {"expires": float(settings.sweep_interval_s)},
            }
        },
        "timezone": "UTC",
    }


def configure(settings: Settings | None = None) -> Celery:
    """Configure `app` from `settings` (default: read from the environment now), replacing an
    earlier configuration and dropping broker connections made with it. Returns the app."""
    conf = celery_config(settings or Settings())
    app.conf.update(conf)
    app._pool = None  # connections of an earlier broker URL
    return app


app = Celery("citytherm", include=["workers.tasks"])
# read on first use (a promise): importing this module reads no settings
app.add_defaults(lambda: celery_config(Settings()))

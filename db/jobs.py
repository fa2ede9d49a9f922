"""Job records in the database: jobs and their building units (OGC API Processes states); the
sequences they read are registered by `db.sequences`.

In: a `Session` (the caller's unit of work commits; these helpers never commit). Out: rows of
`job` and `job_unit`. PostGIS is the record of job state; a queue only carries
ids. States: accepted -> running -> successful | failed, and dismissed from any unfinished state.
A unit's success is written by `db.store.store_building_result` in the same transaction as its
result; `finish_job_if_done` then decides the job's outcome from the units (never from the queue).
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy import text
from sqlalchemy.orm import Session

from db.errors import CityDBError, NotFoundError

__all__ = [
    "FINAL_STATES",
    "PRE_UNIT_STAGES",
    "JobRecord",
    "StateError",
    "add_units",
    "claim_unit",
    "count_delivery",
    "create_job",
    "dismiss_job",
    "finish_job_if_done",
    "job_counts",
    "jobs_to_sweep",
    "lock_job",
    "note_results_failed",
    "requeue_units",
    "set_job_results",
    "set_job_status",
    "set_stage",
    "set_unit_status",
    "set_unit_tasks",
    "unit_status",
    "unit_task_ids",
]

FINAL_STATES = ("successful", "failed", "dismissed")
_ALLOWED = {
    "accepted": {"running", "failed", "dismissed"},
    "running": {"successful", "failed", "dismissed"},
}


class StateError(CityDBError):
    """A state change that the job or unit's current state does not allow."""

    status_code = 409


def _uuid(job_id: uuid.UUID | str) -> uuid.UUID:
    return job_id if isinstance(job_id, uuid.UUID) else uuid.UUID(str(job_id))


def create_job(
    session: Session,
    *,
    model_id: int,
    theme: str = "thermal-ir",
    sequence_id: int | None = None,
    options: Mapping[str, Any] | None = None,
    job_id: uuid.UUID | None = None,
) -> uuid.UUID:
    """Insert a job (status `accepted`) and return its id."""
    jid = job_id or uuid.uuid4()
    session.execute(
        text(
            "INSERT INTO job (id, city_model_id, sequence_id, theme, status, progress, options, timings_s) "
            "VALUES (:id, :m, :seq, :theme, 'accepted', 0, CAST(:opt AS jsonb), '{}'::jsonb)"
        ),
        {
            "id": jid,
            "m": model_id,
            "seq": sequence_id,
            "theme": theme,
            "opt": json.dumps(dict(options or {})),
        },
    )
    return jid


def add_units(
    session: Session, *, job_id: uuid.UUID | str, building_gml_ids: Sequence[str] | None = None
) -> int:
    """Create `accepted` units for the given top-level buildings of the job's model (all when None);
    existing units are kept. Returns the number of units the job has."""
    jid = _uuid(job_id)
    sql = (
        "INSERT INTO job_unit (job_id, building_id, status, progress, attempts, timings_s) "
        "SELECT j.id, b.id, 'accepted', 0, 0, '{}'::jsonb FROM job j JOIN building b "
        "ON b.city_model_id = j.city_model_id AND NOT b.is_part WHERE j.id = :j"
    )
    params: dict[str, Any] = {"j": jid}
    if building_gml_ids is not None:
        sql += " AND b.gml_id = ANY(:g)"
        params["g"] = list(building_gml_ids)
    session.execute(text(sql + " ON CONFLICT ON CONSTRAINT uq_job_unit_job_building DO NOTHING"), params)
    return int(
        session.execute(text("SELECT count(*) FROM job_unit WHERE job_id = :j"), {"j": jid}).scalar_one()
    )


def set_job_status(
    session: Session,
    *,
    job_id: uuid.UUID | str,
    status: str,
    message: str | None = None,
    error: str | None = None,
) -> None:
    """Move a job to `status` (checked against the allowed transitions); sets the timestamps."""
    jid = _uuid(job_id)
    row = session.execute(text("SELECT status FROM job WHERE id = :j FOR UPDATE"), {"j": jid}).first()
    if row is None:
        raise NotFoundError(f"job {jid} not found")
    if row[0] != status and status not in _ALLOWED.get(row[0], set()):
        raise StateError(f"job {jid} is {row[0]}: cannot become {status}")
    session.execute(
        text(
            "UPDATE job SET status = :s, message = COALESCE(:msg, message), "
            "error = COALESCE(:err, error), "
            "started_at = CASE WHEN :s = 'running' THEN COALESCE(started_at, now()) ELSE started_at END, "
            "finished_at = CASE WHEN :s IN ('successful', 'failed', 'dismissed') THEN now() "
            "ELSE finished_at END, "
            "progress = CASE WHEN :s = 'successful' THEN 1 ELSE progress END, updated_at = now() "
            "WHERE id = :j"
        ),
        {"j": jid, "s": status, "msg": message, "err": error},
    )


def set_unit_status(
    session: Session,
    *,
    job_id: uuid.UUID | str,
    building_gml_id: str,
    status: str,
    error: str | None = None,
) -> None:
    """Mark one unit `running` (counts an attempt) or `failed` (with the error); a unit that is
    final stays as it is (a late duplicate delivery cannot undo a stored result)."""
    if status not in ("running", "failed"):
        raise StateError(f"units become successful through store_building_result, not {status!r}")
    res = session.execute(
        text(
            "UPDATE job_unit u SET status = :s, error = :err, "
            "attempts = attempts + CASE WHEN :s = 'running' THEN 1 ELSE 0 END, "
            "started_at = CASE WHEN :s = 'running' THEN now() ELSE started_at END, "
            "finished_at = CASE WHEN :s = 'failed' THEN now() ELSE finished_at END "
            "FROM building b WHERE u.building_id = b.id AND u.job_id = :j AND b.gml_id = :g "
            "AND NOT b.is_part AND u.status IN ('accepted', 'running')"
        ),
        {"j": _uuid(job_id), "g": building_gml_id, "s": status, "err": error},
    )
    if res.rowcount == 0:  # type: ignore[attr-defined]
        exists = session.execute(
            text(
                "SELECT 1 FROM job_unit u JOIN building b ON b.id = u.building_id "
                "WHERE u.job_id = :j AND b.gml_id = :g"
            ),
            {"j": _uuid(job_id), "g": building_gml_id},
        ).first()
        if exists is None:
            raise NotFoundError(f"job {job_id} has no unit for building {building_gml_id!r}")


def job_counts(session: Session, *, job_id: uuid.UUID | str) -> dict[str, int]:
    """Number of units per status (every status present, zeros included)."""
    rows = session.execute(
        text("SELECT status, count(*) FROM job_unit WHERE job_id = :j GROUP BY status"), {"j": _uuid(job_id)}
    ).all()
    out = dict.fromkeys(("accepted", "running", "successful", "failed", "dismissed"), 0)
    out.update({s: int(n) for s, n in rows})
    return out


def finish_job_if_done(session: Session, *, job_id: uuid.UUID | str) -> str:
    """Update the job's progress from its units; when none is pending any more, finish it:
    `successful` if at least one unit succeeded, else `failed`. Returns the job's status."""
    jid = _uuid(job_id)
    status = session.execute(text("SELECT status FROM job WHERE id = :j FOR UPDATE"), {"j": jid}).scalar()
    if status is None:
        raise NotFoundError(f"job {jid} not found")
    c = job_counts(session, job_id=jid)
    total = sum(c.values())
    done = c["successful"] + c["failed"] + c["dismissed"]
    session.execute(
        text("UPDATE job SET progress = :p, updated_at = now() WHERE id = :j"),
        {"j": jid, "p": done / total if total else 1.0},
    )
    if status in FINAL_STATES or c["accepted"] + c["running"] > 0:
        return str(status)
    final = "successful" if c["successful"] > 0 or total == 0 else "failed"
    if status == "accepted":
        set_job_status(session, job_id=jid, status="running")
    set_job_status(
        session,
        job_id=jid,
        status=final,
        message=f"{c['successful']} of {total} buildings textured, {c['failed']} failed",
    )
    return final


def dismiss_job(session: Session, *, job_id: uuid.UUID | str) -> None:
    """Dismiss a job and its pending units (stored results stay); a job dismissed already stays
    as it was."""
    jid = _uuid(job_id)
    if session.execute(text("SELECT status FROM job WHERE id = :j"), {"j": jid}).scalar() == "dismissed":
        return
    set_job_status(session, job_id=jid, status="dismissed")
    session.execute(
        text(
            "UPDATE job_unit SET status = 'dismissed', finished_at = now() "
            "WHERE job_id = :j AND status IN ('accepted', 'running')"
        ),
        {"j": jid},
    )


# -- the service's task bookkeeping (workers/service_job.py) ---------------------------------------
#: a job's stages before its units exist (`job.stage`)
PRE_UNIT_STAGES = ("accepted", "ingest", "calibrate", "orient", "plan")
_SKIP = "FOR UPDATE SKIP LOCKED"


@dataclass(frozen=True)
class JobRecord:
    """The columns of a `job` row the workers use."""

    id: uuid.UUID
    status: str
    stage: str
    city_model_id: int
    sequence_id: int | None
    theme: str
    options: dict[str, Any]
    results_location: str | None


def lock_job(session: Session, *, job_id: uuid.UUID | str, share: bool = False) -> JobRecord:
    """The job row, locked `FOR UPDATE` (or `FOR SHARE`: a dismissal, which updates the row,
    then waits until this transaction ends). Raises `NotFoundError`."""
    row = session.execute(
        text(
            "SELECT id, status, stage, city_model_id, sequence_id, theme, options, results_location "
            f"FROM job WHERE id = :j FOR {'SHARE' if share else 'UPDATE'}"
        ),
        {"j": _uuid(job_id)},
    ).first()
    if row is None:
        raise NotFoundError(f"job {job_id} not found")
    return JobRecord(row[0], row[1], row[2], int(row[3]), row[4], row[5], dict(row[6] or {}), row[7])


def set_stage(session: Session, *, job_id: uuid.UUID | str, stage: str) -> None:
    """Set the job's current stage (`accepted`, `ingest`, ..., `units`, `finish`)."""
    session.execute(
        text("UPDATE job SET stage = :s, updated_at = now() WHERE id = :j"), {"j": _uuid(job_id), "s": stage}
    )


def set_job_results(
    session: Session, *, job_id: uuid.UUID | str, location: str, timings_s: Mapping[str, float],
    mounting: Mapping[str, Any] | None,
) -> None:
    """Record the job's results folder, its stage timings and the estimated mounting."""
    session.execute(
        text(
            "UPDATE job SET results_location = :loc, timings_s = CAST(:t AS jsonb), "
            "mounting = CAST(:mnt AS jsonb), updated_at = now() WHERE id = :j"
        ),
        {
            "j": _uuid(job_id),
            "loc": location,
            "t": json.dumps({k: float(v) for k, v in timings_s.items()}),
            "mnt": json.dumps(dict(mounting)) if mounting is not None else None,
        },
    )


def set_unit_tasks(session: Session, *, job_id: uuid.UUID | str, task_ids: Mapping[str, str]) -> None:
    """Record the Celery task id each unit is queued with (top-level building gml id -> task id);
    `heartbeat_at` becomes now: the time it was queued, until it starts running."""
    if not task_ids:
        return
    session.execute(
        text(
            "UPDATE job_unit u SET task_id = :t, heartbeat_at = now() FROM building b "
            "WHERE u.building_id = b.id AND u.job_id = :j AND b.gml_id = :g AND NOT b.is_part "
            "AND u.status = 'accepted'"
        ),
        [{"j": _uuid(job_id), "g": g, "t": t} for g, t in task_ids.items()],
    )


def claim_unit(
    session: Session,
    *,
    job_id: uuid.UUID | str,
    building_gml_id: str,
    task_id: str,
    stale_after_s: float,
    max_attempts: int,
) -> str:
    """Decide whether the delivery `task_id` of a unit runs it, with the job row locked
    `FOR SHARE` and the unit `FOR UPDATE`. Returns:

    - `run`: the unit is now `running` under `task_id` (attempt counted, heartbeat now);
    - `final`: the unit is final already; `dismissed`: the job is final (dismissed or failed);
    - `busy`: another delivery runs it (status `running`, another task id, heartbeat younger than
      `stale_after_s` seconds);
    - `exhausted`: it started `max_attempts` times already (its worker died or it ran past the
      time limit each time): it is now `failed`.
    Raises `NotFoundError` for an unknown job or unit."""
    job = lock_job(session, job_id=job_id, share=True)
    if job.status in FINAL_STATES:
        return "dismissed"
    row = session.execute(
        text(
            "SELECT u.id, u.status, u.task_id, u.attempts, "
            "COALESCE(u.heartbeat_at > now() - make_interval(secs => :stale), false) "
            "FROM job_unit u JOIN building b ON b.id = u.building_id "
            "WHERE u.job_id = :j AND b.gml_id = :g AND NOT b.is_part FOR UPDATE OF u"
        ),
        {"j": job.id, "g": building_gml_id, "stale": float(stale_after_s)},
    ).first()
    if row is None:
        raise NotFoundError(f"job {job.id} has no unit for building {building_gml_id!r}")
    uid, status, current, attempts, fresh = row
    if status in FINAL_STATES:
        return "final"
    if status == "running" and current != task_id and fresh:
        return "busy"
    if attempts >= max_attempts:
        sql = "UPDATE job_unit SET status = 'failed', finished_at = now(), error = :e WHERE id = :u"
        why = f"given up after {attempts} attempts: its worker died or it ran out of time"
        session.execute(text(sql), {"u": uid, "e": why})
        return "exhausted"
    sql = "UPDATE job_unit SET status = 'running', attempts = attempts + 1, started_at = now(), "
    sql += "heartbeat_at = now(), task_id = :t, error = NULL WHERE id = :u"
    session.execute(text(sql), {"u": uid, "t": task_id})
    return "run"


def unit_status(session: Session, *, job_id: uuid.UUID | str, building_gml_id: str) -> str | None:
    """A unit's status, locked `FOR UPDATE` (None when the job has no such unit)."""
    return session.execute(
        text(
            "SELECT u.status FROM job_unit u JOIN building b ON b.id = u.building_id "
            "WHERE u.job_id = :j AND b.gml_id = :g AND NOT b.is_part FOR UPDATE OF u"
        ),
        {"j": _uuid(job_id), "g": building_gml_id},
    ).scalar()


def requeue_units(
    session: Session, *, stale_after_s: float, queued_after_s: float, limit: int = 1000
) -> list[tuple[uuid.UUID, str, str]]:
    """Units to queue again, of jobs `running` in stage `units`: `running` with a heartbeat older
    than `stale_after_s` seconds (their worker died), and `accepted` ones queued (or never
    queued) longer than `queued_after_s` ago (their message was lost). Rows other sweepers hold
    are skipped (`SKIP LOCKED`). Each gets a new task id, status `accepted` and a fresh
    `heartbeat_at`. Returns (job id, building gml id, new task id); commit before sending."""
    rows = session.execute(
        text(
            "SELECT u.id, u.job_id, b.gml_id FROM job_unit u JOIN job j ON j.id = u.job_id "
            "JOIN building b ON b.id = u.building_id WHERE j.status = 'running' AND j.stage = 'units' "
            "AND ((u.status = 'running' AND COALESCE(u.heartbeat_at, u.started_at, j.updated_at) "
            "< now() - make_interval(secs => :stale)) OR (u.status = 'accepted' AND "
            "COALESCE(u.heartbeat_at, j.updated_at) < now() - make_interval(secs => :queued))) "
            "ORDER BY u.id LIMIT :n FOR UPDATE OF u SKIP LOCKED"
        ),
        {"stale": float(stale_after_s), "queued": float(queued_after_s), "n": int(limit)},
    ).all()
    out = [(r[1], str(r[2]), str(uuid.uuid4())) for r in rows]
    if rows:
        session.execute(
            text(
                "UPDATE job_unit SET status = 'accepted', task_id = :t, heartbeat_at = now() WHERE id = :u"
            ),
            [{"u": r[0], "t": t} for r, (_, _, t) in zip(rows, out, strict=True)],
        )
    return out


def jobs_to_sweep(session: Session, *, which: str, older_than_s: float, limit: int = 100) -> list[uuid.UUID]:
    """Jobs the sweeper acts on, locked (`SKIP LOCKED`), `updated_at` set to now (so one is taken
    again only after another `older_than_s` seconds):

    - `done`: `running` in stage `units` with every unit final (`finish_job_if_done` decides);
    - `results`: final after their units (stage `units` or `finish`) without a results folder,
      last touched more than `older_than_s` seconds ago (their finish task was lost);
    - `prepare`: `accepted` or `running` before their units (`PRE_UNIT_STAGES`), last touched
      more than `older_than_s` seconds ago (their prepare task was lost)."""
    cond = {
        "done": "j.status = 'running' AND j.stage = 'units' AND NOT EXISTS (SELECT 1 FROM job_unit u "
        "WHERE u.job_id = j.id AND u.status IN ('accepted', 'running'))",
        "results": "j.status IN ('successful', 'failed') AND j.stage IN ('units', 'finish') "
        "AND j.results_location IS NULL AND j.error IS NULL "
        "AND j.updated_at < now() - make_interval(secs => :old)",
        "prepare": "j.status IN ('accepted', 'running') AND j.stage = ANY(:pre) "
        "AND j.updated_at < now() - make_interval(secs => :old)",
    }[which]
    ids = [
        r[0]
        for r in session.execute(
            text(f"SELECT j.id FROM job j WHERE {cond} ORDER BY j.updated_at LIMIT :n {_SKIP}"),
            {"old": float(older_than_s), "pre": list(PRE_UNIT_STAGES), "n": int(limit)},
        ).all()
    ]
    if ids and which != "done":
        session.execute(text("UPDATE job SET updated_at = now() WHERE id = ANY(:ids)"), {"ids": ids})
    return ids


def unit_task_ids(session: Session, *, job_id: uuid.UUID | str) -> list[tuple[str, str]]:
    """(task id, unit status) of the job's units that were queued (for revoking them)."""
    return [
        (str(t), str(s))
        for t, s in session.execute(
            text("SELECT task_id, status FROM job_unit WHERE job_id = :j AND task_id IS NOT NULL"),
            {"j": _uuid(job_id)},
        ).all()
    ]


def count_delivery(session: Session, *, job_id: uuid.UUID | str) -> int:
    """Count one more delivery of the job's prepare or finish task; returns the count."""
    return int(
        session.execute(
            text("UPDATE job SET attempts = attempts + 1 WHERE id = :j RETURNING attempts"),
            {"j": _uuid(job_id)},
        ).scalar_one()
    )


def note_results_failed(session: Session, *, job_id: uuid.UUID | str, error: str) -> None:
    """A final job whose results folder could not be written: the error is recorded (the
    sweeper then leaves the job alone; its rows in PostGIS stay)."""
    session.execute(
        text("UPDATE job SET error = :e, stage = 'finish', updated_at = now() WHERE id = :j"),
        {"j": _uuid(job_id), "e": error},
    )

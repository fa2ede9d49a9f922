"""Job records in the database: jobs and their building units (OGC API Processes states),
and registered sequences with their frames.

In: a `Session` (the caller's unit of work commits; these helpers never commit). Out: rows of
`job`, `job_unit`, `sequence`, `frame`. PostGIS is the record of job state; a queue only carries
ids. States: accepted -> running -> successful | failed, and dismissed from any unfinished state.
A unit's success is written by `db.store.store_building_result` in the same transaction as its
result; `finish_job_if_done` then decides the job's outcome from the units (never from the queue).
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from sqlalchemy import text
from sqlalchemy.orm import Session

from db.errors import CityDBError, NotFoundError
from db.geomcodec import encode_linestring_z, encode_point_z
from workers.pipeline.geometry.manifest import SequenceManifest
from workers.pipeline.geometry.pose import Pose

__all__ = [
    "FINAL_STATES",
    "StateError",
    "add_units",
    "create_job",
    "dismiss_job",
    "finish_job_if_done",
    "job_counts",
    "register_sequence",
    "set_job_status",
    "set_unit_status",
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
    """Dismiss a job and its pending units (stored results stay)."""
    jid = _uuid(job_id)
    set_job_status(session, job_id=jid, status="dismissed")
    session.execute(
        text(
            "UPDATE job_unit SET status = 'dismissed', finished_at = now() "
            "WHERE job_id = :j AND status IN ('accepted', 'running')"
        ),
        {"j": jid},
    )


def register_sequence(
    session: Session,
    *,
    name: str,
    manifest: SequenceManifest,
    manifest_json: Mapping[str, Any],
    storage_location: str,
    srid: int,
    priors: Sequence[Pose] | None = None,
) -> int:
    """Insert a sequence (its `sequence.json` as jsonb, where it is stored), one row per frame
    (with the prior pose when `priors[i]` is given) and the trajectory of the frame positions
    (`LINESTRING Z` in `srid`, the EPSG code of the manifest CRS). Returns the sequence id."""
    pos = np.array([f.position for f in manifest.frames], dtype=np.float64).reshape(-1, 3)
    traj = encode_linestring_z(pos, srid) if len(pos) >= 2 else None
    sid = session.execute(
        text(
            "INSERT INTO sequence (name, manifest, storage_location, frame_count, srs_name, srid, "
            "trajectory) "
            "VALUES (:n, CAST(:m AS jsonb), :loc, :fc, :srs, :srid, CAST(:t AS geometry)) RETURNING id"
        ),
        {
            "n": name,
            "m": json.dumps(manifest_json),
            "loc": storage_location,
            "fc": len(manifest.frames),
            "srs": manifest.crs,
            "srid": srid,
            "t": traj,
        },
    ).scalar_one()
    rows = []
    for i, f in enumerate(manifest.frames):
        prior = priors[i] if priors is not None else None
        rows.append(
            {
                "s": sid,
                "i": f.index,
                "f": f.file,
                "t": f.time,
                "c": encode_point_z(prior.center, srid) if prior is not None else None,
                "r": prior.R_world_from_cam.ravel().tolist() if prior is not None else None,
                "rec": json.dumps({"position": f.position.tolist(), "attitude_deg": f.attitude_deg.tolist()}),
            }
        )
    if rows:
        session.execute(
            text(
                "INSERT INTO frame (sequence_id, index, file, time_s, prior_center, prior_rotation, record) "
                "VALUES (:s, :i, :f, :t, CAST(:c AS geometry), :r, CAST(:rec AS jsonb))"
            ),
            rows,
        )
    return int(sid)

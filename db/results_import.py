"""Put a results folder into the city model database: `citytherm results import` and
`citytherm run --database`.

In: a database (Engine, sessionmaker or URL), a results folder (`docs/results-format.md`, read by
`db.results_folder.read.read_results_folder`) and the city model (name or id) whose buildings it
textured. Out: one job of that model with a unit per building of the folder, and per building, in
one transaction each (`db.store.store_building_result`, as the service stores a unit's result):
the appearance of the job's theme with its texture coordinates, the 16-bit tiles with their
radiometry, the per-surface statistics (kelvin), the frame poses (with the manifest-only priors of
`orientation.json`) and the anomalies; units that failed in the run are recorded as failed.

Refused before anything is written: a folder that does not read back, a model that is missing
or not completely imported, buildings of the folder that are not in the model, polygons the
results refer to that are not in their building there (`InputDataError`, naming them).

Idempotent: the job's id is derived from the model and the folder's absolute path
(`results_job_id`), so importing the same folder again, or running `citytherm run --database`
again into the same folder, replaces that job's rows instead of adding a copy; the job then
holds exactly the folder's buildings (buildings of an earlier import that the folder no longer
has are removed from the job).
"""

from __future__ import annotations

import json
import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any

from sqlalchemy import Connection, Engine, text
from sqlalchemy.orm import Session

from db.city_models import find_model
from db.errors import InputDataError, NotFoundError
from db.importer import ImportSummary, import_citygml
from db.jobs import add_units, create_job, finish_job_if_done, set_job_status, set_unit_status
from db.results_folder.read import ResultsFolder, read_results_folder
from db.session import as_engine
from db.store import store_building_result

__all__ = [
    "RESULTS_JOB_NAMESPACE",
    "ResultsImportSummary",
    "check_folder_against_model",
    "ensure_model",
    "import_results",
    "results_job_id",
]

#: namespace of the job ids of imported results folders (uuid5 of model id and folder path)
RESULTS_JOB_NAMESPACE = uuid.UUID("5b0d2c1e-4a0f-5e8c-9a57-2f7c1d3e9b40")
_LIST = 10  # ids named in a refusal


@dataclass(frozen=True)
class ResultsImportSummary:
    """What `import_results` wrote.

    Attributes:
        job_id: the job holding the folder's results; created: True when it was new.
        buildings: buildings stored (one transaction each); failed: units recorded as failed;
        removed: buildings of an earlier import of the same job that the folder no longer has.
        images, surfaces, poses, anomalies: rows written over all buildings (`tex_image`,
            `surface_thermal`, `frame_pose`, `thermal_anomaly`).
        status: the job's status afterwards; seconds: wall time (reading the folder included).
    """

    job_id: uuid.UUID
    model_id: int
    model: str
    created: bool
    buildings: int
    failed: int
    removed: int
    images: int
    surfaces: int
    poses: int
    anomalies: int
    status: str
    seconds: float


def results_job_id(model_id: int, folder: str | PathLike[str]) -> uuid.UUID:
    """The job id of a results folder in a model: uuid5 of the model id and the folder's
    absolute path (the same folder gives the same job, so a re-import replaces it)."""
    return uuid.uuid5(RESULTS_JOB_NAMESPACE, f"{int(model_id)}:{Path(folder).resolve()}")


def _named(ids: list[str]) -> str:
    more = f" and {len(ids) - _LIST} more" if len(ids) > _LIST else ""
    return ", ".join(repr(i) for i in ids[:_LIST]) + more


def check_folder_against_model(conn: Connection, model: Mapping[str, Any], rf: ResultsFolder) -> None:
    """Refuse (`InputDataError`) a folder whose buildings are not top-level buildings of the model,
    or whose results refer to polygons that are not in their building there; and a model that is
    not completely imported."""
    if model["state"] != "complete":
        raise InputDataError(f"city model {model['name']!r} is {model['state']}, not complete")
    ids = list(dict.fromkeys([*rf.building_ids, *(b for b, _ in rf.failed)]))
    surfaces: dict[str, set[str]] = {}
    for bid, sid in conn.execute(
        text(
            "SELECT b.gml_id, s.gml_id FROM building b JOIN building p ON p.root_id = b.id "
            "LEFT JOIN surface s ON s.building_id = p.id "
            "WHERE b.city_model_id = :m AND NOT b.is_part AND b.gml_id = ANY(:ids)"
        ),
        {"m": model["id"], "ids": ids},
    ).all():
        surfaces.setdefault(bid, set())
        if sid is not None:
            surfaces[bid].add(sid)
    missing = [b for b in ids if b not in surfaces]
    if missing:
        raise InputDataError(
            f"{rf.path}: {len(missing)} of its {len(ids)} buildings are not in city model "
            f"{model['name']!r}: {_named(missing)}; nothing written"
        )
    for bid in rf.building_ids:
        extra = sorted(rf.polygon_ids(bid) - surfaces[bid])
        if extra:
            raise InputDataError(
                f"{rf.path}: building {bid!r} refers to polygons that its namesake in city model "
                f"{model['name']!r} does not have: {_named(extra)}; nothing written"
            )


def _open_job(session: Session, *, job_id: uuid.UUID, model: Mapping[str, Any], rf: ResultsFolder) -> bool:
    """Create the job (or take up the existing one of this folder) with a unit per building, and
    set it running; returns True when it was created."""
    conn = session.connection()
    # a model being deleted waits for this transaction (and this one for it)
    conn.execute(text("SELECT 1 FROM city_model WHERE id = :m FOR KEY SHARE"), {"m": model["id"]})
    row = conn.execute(
        text("SELECT city_model_id, status FROM job WHERE id = :j FOR UPDATE"), {"j": job_id}
    ).first()
    created = row is None
    if created:
        create_job(
            session,
            model_id=model["id"],
            theme=rf.theme,
            options=rf.report.get("options") or {},
            job_id=job_id,
        )
    elif row[0] != model["id"]:
        raise InputDataError(f"job {job_id} belongs to city model {row[0]}, not to {model['name']!r}")
    elif row[1] not in ("accepted", "running"):
        # a new import of the same folder is a new attempt of the job: it runs again
        conn.execute(
            text(
                "UPDATE job SET status = 'running', progress = 0, error = NULL, message = NULL, "
                "finished_at = NULL, started_at = now(), updated_at = now() WHERE id = :j"
            ),
            {"j": job_id},
        )
    conn.execute(
        text(
            "UPDATE job SET theme = :theme, options = CAST(:opt AS jsonb), mounting = CAST(:mnt AS jsonb), "
            "timings_s = CAST(:t AS jsonb), results_location = :loc, updated_at = now() WHERE id = :j"
        ),
        {
            "j": job_id,
            "theme": rf.theme,
            "opt": json.dumps(rf.report.get("options") or {}),
            "mnt": json.dumps(rf.mounting) if rf.mounting else None,
            "t": json.dumps(rf.report.get("timings_s") or {}),
            "loc": str(rf.path.resolve()),
        },
    )
    ids = list(dict.fromkeys([*rf.building_ids, *(b for b, _ in rf.failed)]))
    add_units(session, job_id=job_id, building_gml_ids=ids)
    # every unit of the folder is pending again until its result is stored
    conn.execute(
        text(
            "UPDATE job_unit u SET status = 'accepted', progress = 0, error = NULL, finished_at = NULL "
            "FROM building b WHERE u.building_id = b.id AND u.job_id = :j AND b.gml_id = ANY(:g)"
        ),
        {"j": job_id, "g": ids},
    )
    if created or row[1] == "accepted":
        set_job_status(session, job_id=job_id, status="running")
    return created


def _delete_building_rows(conn: Connection, job_id: uuid.UUID, building_rows: list[int]) -> None:
    p = {"j": job_id, "b": building_rows}
    for table in ("thermal_anomaly", "frame_pose", "appearance"):
        conn.execute(text(f"DELETE FROM {table} WHERE job_id = :j AND building_id = ANY(:b)"), p)


def _close_job(session: Session, *, job_id: uuid.UUID, rf: ResultsFolder) -> tuple[int, str]:
    """Record the failed units, drop buildings the folder no longer has, finish the job.
    Returns (buildings removed, the job's status)."""
    conn = session.connection()
    keep = list(dict.fromkeys([*rf.building_ids, *(b for b, _ in rf.failed)]))
    stale = [
        int(r[0])
        for r in conn.execute(
            text(
                "SELECT u.building_id FROM job_unit u JOIN building b ON b.id = u.building_id "
                "WHERE u.job_id = :j AND NOT (b.gml_id = ANY(:g)) "
                "UNION SELECT a.building_id FROM appearance a JOIN building b ON b.id = a.building_id "
                "WHERE a.job_id = :j AND NOT (b.gml_id = ANY(:g))"
            ),
            {"j": job_id, "g": keep},
        ).all()
    ]
    if stale:
        _delete_building_rows(conn, job_id, stale)
        conn.execute(
            text("DELETE FROM job_unit WHERE job_id = :j AND building_id = ANY(:b)"),
            {"j": job_id, "b": stale},
        )
    failed_ids = [b for b, _ in rf.failed]
    if failed_ids:  # a failure of this run replaces a success of an earlier one
        rows = [
            int(r[0])
            for r in conn.execute(
                text(
                    "SELECT id FROM building WHERE city_model_id = (SELECT city_model_id FROM job "
                    "WHERE id = :j) AND NOT is_part AND gml_id = ANY(:g)"
                ),
                {"j": job_id, "g": failed_ids},
            ).all()
        ]
        _delete_building_rows(conn, job_id, rows)
    for bid, error in rf.failed:
        set_unit_status(session, job_id=job_id, building_gml_id=bid, status="failed", error=error or "failed")
    status = finish_job_if_done(session, job_id=job_id)
    return len(stale), status


def import_results(
    db: Engine | Any,
    folder: str | PathLike[str],
    *,
    model: str | int,
    job_id: uuid.UUID | str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ResultsImportSummary:
    """Store the results folder `folder` in city model `model` (name or id); see the module
    docstring. `job_id` overrides the derived job id (`results_job_id`); `progress(done, total)`
    is called per building.

    Raises `ResultsReadError` (a `ValueError`) for a folder that does not read back,
    `NotFoundError` for a missing model, `InputDataError` for a folder that does not fit the model
    (nothing written in these cases). An error while storing leaves the buildings stored so far
    (each complete) and the job `failed`, with the error; importing again completes it.
    """
    t0 = time.perf_counter()
    engine = as_engine(db)
    rf = read_results_folder(folder)
    with engine.connect() as conn:
        m = find_model(conn, model)
        check_folder_against_model(conn, m, rf)
    jid = results_job_id(m["id"], rf.path) if job_id is None else uuid.UUID(str(job_id))
    with Session(engine) as session:
        created = _open_job(session, job_id=jid, model=m, rf=rf)
        session.commit()
        totals = dict.fromkeys(("images", "surfaces", "poses", "anomalies"), 0)
        step = progress or (lambda done, total: None)
        n = len(rf.building_ids)
        step(0, n)
        try:
            for k, result in enumerate(rf.iter_building_results()):
                stored = store_building_result(
                    session, job_id=jid, model_id=m["id"], result=result, priors=rf.priors
                )
                for key in totals:
                    totals[key] += getattr(stored, key)
                step(k + 1, n)
            removed, status = _close_job(session, job_id=jid, rf=rf)
            session.commit()
        except BaseException as exc:
            session.rollback()
            _fail_job(session, jid, exc)
            raise
    return ResultsImportSummary(
        job_id=jid,
        model_id=m["id"],
        model=m["name"],
        created=created,
        buildings=n,
        failed=len(rf.failed),
        removed=removed,
        images=totals["images"],
        surfaces=totals["surfaces"],
        poses=totals["poses"],
        anomalies=totals["anomalies"],
        status=status,
        seconds=time.perf_counter() - t0,
    )


def _fail_job(session: Session, job_id: uuid.UUID, exc: BaseException) -> None:
    """Mark the job failed after an error while storing (best effort: the error that got us here
    is the one to report)."""
    try:
        set_job_status(session, job_id=job_id, status="failed", error=f"{type(exc).__name__}: {exc}"[:2000])
        session.commit()
    except Exception:
        session.rollback()


def ensure_model(
    db: Engine | Any, city_gml: str | PathLike[str], name: str | None = None
) -> tuple[Mapping[str, Any], ImportSummary | None]:
    """The city model `name` (default: the file's stem, as `citytherm import` names it), imported
    from `city_gml` first when the database lacks it. Returns its row and the import summary
    (None when it was there already)."""
    engine = as_engine(db)
    name = name or Path(city_gml).stem
    with engine.connect() as conn:
        try:
            return find_model(conn, name, by_id=False), None
        except NotFoundError:
            pass
    summary = import_citygml(engine, city_gml, name=name)
    with engine.connect() as conn:
        return find_model(conn, summary.model_id), summary

"""Jobs over HTTP (OGC API - Processes 1.0 Core): the `texture` process, its execution, job
status, lists, dismissal and results.

In: a session, the settings, validated inputs. Out: JSON-ready dicts (OGC statusInfo, job list,
results document). The job's state is read from PostGIS (`job`, `job_unit`); the workers write
it. A job is submitted through `workers.submit.submit_job` (creates the `accepted` row, commits,
queues it) after the inputs were checked here: the model ready, the sequence committed, both in
one CRS, the options valid. Results are files the workers write to the storage:
`jobs/<id>/results.zip` and the folder `jobs/<id>/results/`.
"""

from __future__ import annotations

import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path, PurePosixPath
from typing import Any
from urllib.parse import urlencode

from sqlalchemy import text
from sqlalchemy.orm import Session

from db.errors import CityDBError, NotFoundError
from db.service_records import UploadStateError, get_model_import, get_sequence_upload
from db.settings import Settings
from services.api.problems import OGC_EXCEPTIONS
from services.api.schemas import TextureInputs

PROCESS_ID = "texture"

#: outputs of a successful job: id -> (file below jobs/<id>/, media type, title)
OUTPUTS: dict[str, tuple[str, str, str]] = {
    "results": ("results.zip", "application/zip", "The results folder, zipped (docs/results-format.md)"),
    "orientation": ("results/orientation.json", "application/json", "Estimated mounting (orientation.json)"),
    "report": ("results/report.json", "application/json", "Calibration, orientation and texel report"),
    "anomalies": (
        "results/anomalies.geojson",
        "application/geo+json",
        "Windows, heat-leak candidates and thermal bridges with 3D outlines (anomalies.geojson)",
    ),
}


class NoSuchJobError(NotFoundError):
    """A job id that is not in the database."""

    problem_type = OGC_EXCEPTIONS + "no-such-job"


class NoSuchProcessError(NotFoundError):
    """A process id other than `texture`."""

    problem_type = OGC_EXCEPTIONS + "no-such-process"


class ResultNotReadyError(CityDBError):
    """Results asked for before the job succeeded (or before they were written)."""

    status_code = 409
    problem_type = OGC_EXCEPTIONS + "result-not-ready"


class InputError(CityDBError):
    """An input that the process cannot take (names the input)."""

    status_code = 422


def job_dir(settings: Settings, job_id: uuid.UUID) -> Path:
    """`jobs/<job id>/` in the storage."""
    return Path(settings.storage_dir) / "jobs" / str(job_id)


def check_process(process_id: str) -> None:
    """Raise `NoSuchProcessError` unless `process_id` is `texture`."""
    if process_id != PROCESS_ID:
        raise NoSuchProcessError(f"no process {process_id!r}; the only process is {PROCESS_ID!r}")


def process_summary(base: str) -> dict[str, Any]:
    """The `texture` process as listed in `GET /processes`."""
    return {
        "id": PROCESS_ID,
        "title": "Texture a city model with a TIR sequence",
        "description": "Refine the frames' poses against the city model, extract and fuse thermal "
        "textures for every building the sequence sees, and write CityGML appearances (the job "
        "`citytherm run` runs). Jobs run asynchronously: execution answers 201 with the job's "
        "status; poll /jobs/{jobId}.",
        "version": "1.0.0",
        "jobControlOptions": ["async-execute", "dismiss"],
        "outputTransmission": ["reference"],
        "links": [
            {
                "href": f"{base}/processes/{PROCESS_ID}",
                "rel": "self",
                "type": "application/json",
                "title": "process description",
            },
            {
                "href": f"{base}/processes/{PROCESS_ID}/execution",
                "rel": "http://www.opengis.net/def/rel/ogc/1.0/execute",
                "type": "application/json",
                "title": "execute",
            },
        ],
    }


def process_description(base: str) -> dict[str, Any]:
    """`GET /processes/texture`: inputs (JSON schemas from `TextureInputs`) and outputs."""
    schema = TextureInputs.model_json_schema()
    required = set(schema.get("required", []))
    inputs = {}
    for name, prop in schema["properties"].items():
        prop = dict(prop)
        title = prop.pop("title", name)
        description = prop.pop("description", "")
        inputs[name] = {
            "title": title,
            "description": description,
            "schema": prop,
            "minOccurs": 1 if name in required else 0,
            "maxOccurs": 1,
        }
    outputs = {
        k: {"title": title, "schema": {"type": "string", "contentEncoding": "binary", "contentMediaType": mt}}
        for k, (_, mt, title) in OUTPUTS.items()
    }
    return {**process_summary(base), "inputs": inputs, "outputs": outputs}


def _ids_of(session: Session, rows: Sequence[Mapping[str, Any]]) -> tuple[dict[int, int], dict[int, str]]:
    """API ids of the jobs' models and sequences: city_model id -> import id, sequence id -> uuid."""
    models = sorted({int(r["city_model_id"]) for r in rows if r["city_model_id"] is not None})
    seqs = sorted({int(r["sequence_id"]) for r in rows if r["sequence_id"] is not None})
    mids = dict(
        session.execute(
            text("SELECT city_model_id, max(id) FROM model_import WHERE city_model_id = ANY(:m) GROUP BY 1"),
            {"m": models},
        ).all()
    )
    sids = {
        int(s): str(u)
        for s, u in session.execute(
            text("SELECT sequence_id, id FROM sequence_upload WHERE sequence_id = ANY(:s)"), {"s": seqs}
        ).all()
    }
    return {int(k): int(v) for k, v in mids.items()}, sids


def _counts(session: Session, job_ids: list[uuid.UUID]) -> dict[uuid.UUID, dict[str, int]]:
    out = {j: dict.fromkeys(("accepted", "running", "successful", "failed", "dismissed"), 0) for j in job_ids}
    for j, status, n in session.execute(
        text("SELECT job_id, status, count(*) FROM job_unit WHERE job_id = ANY(:j) GROUP BY 1, 2"),
        {"j": job_ids},
    ).all():
        out[j][status] = int(n)
    return out


_JOB_COLS = (
    "SELECT id, status, message, error, created_at, started_at, finished_at, updated_at, progress, stage, "
    "theme, city_model_id, sequence_id FROM job"
)


def _status_infos(session: Session, rows: Sequence[Mapping[str, Any]], base: str) -> list[dict[str, Any]]:
    counts = _counts(session, [r["id"] for r in rows])
    models, seqs = _ids_of(session, rows)
    out = []
    for r in rows:
        href = f"{base}/jobs/{r['id']}"
        links = [{"href": href, "rel": "self", "type": "application/json", "title": "job status"}]
        if r["status"] == "successful":
            links.append(
                {
                    "href": f"{href}/results",
                    "rel": "http://www.opengis.net/def/rel/ogc/1.0/results",
                    "type": "application/json",
                    "title": "job results",
                }
            )
        out.append(
            {
                "jobID": str(r["id"]),
                "processID": PROCESS_ID,
                "type": "process",
                "status": r["status"],
                "message": r["message"] or r["error"],
                "created": r["created_at"],
                "started": r["started_at"],
                "finished": r["finished_at"],
                "updated": r["updated_at"],
                "progress": max(0, min(100, round(100.0 * float(r["progress"] or 0.0)))),
                "stage": r["stage"] or "accepted",
                "units": counts[r["id"]],
                "inputs": {
                    "model": models.get(r["city_model_id"]),
                    "sequence": seqs.get(r["sequence_id"]) if r["sequence_id"] is not None else None,
                    "theme": r["theme"],
                },
                "links": links,
            }
        )
    return out


def status_info(session: Session, *, job_id: uuid.UUID, base: str) -> dict[str, Any]:
    """OGC statusInfo of one job (plus `stage`, `units`, `inputs`). Raises `NoSuchJobError`."""
    row = session.execute(text(_JOB_COLS + " WHERE id = :j"), {"j": job_id}).mappings().first()
    if row is None:
        raise NoSuchJobError(f"no job {job_id}")
    info = _status_infos(session, [row], base)[0]
    session.rollback()
    return info


def list_jobs(
    session: Session,
    *,
    status: Sequence[str] | None,
    process_id: Sequence[str] | None,
    limit: int,
    offset: int,
    base: str,
) -> dict[str, Any]:
    """`GET /jobs`: newest first, filtered by status and process id, paged (`next`/`prev` links)."""
    params: dict[str, Any] = {"lim": limit + 1, "off": offset}
    where = ""
    if status:
        where = " WHERE status = ANY(:st)"
        params["st"] = list(status)
    rows: Sequence[Mapping[str, Any]] = []
    if not process_id or PROCESS_ID in process_id:
        rows = (
            session.execute(
                text(_JOB_COLS + where + " ORDER BY created_at DESC, id LIMIT :lim OFFSET :off"), params
            )
            .mappings()
            .all()
        )
    more = len(rows) > limit
    jobs = _status_infos(session, rows[:limit], base)
    session.rollback()

    def page(off: int) -> str:
        q: list[tuple[str, Any]] = [("limit", limit), ("offset", off)]
        q += [("status", s) for s in status or ()]
        q += [("processID", p) for p in process_id or ()]
        return f"{base}/jobs?{urlencode(q)}"

    links = [{"href": page(offset), "rel": "self", "type": "application/json"}]
    if more:
        links.append({"href": page(offset + limit), "rel": "next", "type": "application/json"})
    if offset > 0:
        links.append({"href": page(max(0, offset - limit)), "rel": "prev", "type": "application/json"})
    return {"jobs": jobs, "links": links}


def _model_for_job(session: Session, model: int) -> Mapping[str, Any]:
    try:
        mi = get_model_import(session, import_id=model)
    except NotFoundError:
        raise NotFoundError(f"input model: no city model {model}") from None
    if mi.status != "ready" or mi.city_model_id is None:
        state = mi.status if mi.status != "ready" else "deleted"
        raise UploadStateError(f"input model: city model {model} is not ready (status {state})")
    return (
        session.execute(
            text("SELECT id, srid, srs_name FROM city_model WHERE id = :m"), {"m": mi.city_model_id}
        )
        .mappings()
        .one()
    )


def _sequence_for_job(session: Session, sequence: uuid.UUID) -> Mapping[str, Any]:
    try:
        up = get_sequence_upload(session, upload_id=sequence)
    except NotFoundError:
        raise NotFoundError(f"input sequence: no sequence {sequence}") from None
    if up.status != "committed" or up.sequence_id is None:
        raise UploadStateError(f"input sequence: sequence {sequence} is not committed (status {up.status})")
    return (
        session.execute(text("SELECT id, srid, srs_name FROM sequence WHERE id = :s"), {"s": up.sequence_id})
        .mappings()
        .one()
    )


def _check_buildings(session: Session, model_id: int, buildings: list[str]) -> None:
    found = set(
        session.execute(
            text("SELECT gml_id FROM building WHERE city_model_id = :m AND NOT is_part AND gml_id = ANY(:g)"),
            {"m": model_id, "g": buildings},
        ).scalars()
    )
    missing = [b for b in dict.fromkeys(buildings) if b not in found]
    if missing:
        shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
        raise InputError(f"inputs.buildings: not top-level buildings of the model: {shown}")


def execute(session: Session, *, inputs: TextureInputs, base: str) -> tuple[uuid.UUID, dict[str, Any]]:
    """Check the inputs and submit the job (`workers.submit.submit_job`); returns its id and
    statusInfo. 404 for an unknown model or sequence, 409 for one not ready, 422 for a sequence
    in another CRS than the model's or an option that does not fit."""
    model = _model_for_job(session, inputs.model)
    seq = _sequence_for_job(session, inputs.sequence)
    in_model_crs = (seq["srs_name"] or "").strip().lower() == "model"
    if not in_model_crs and int(seq["srid"]) != int(model["srid"]):
        raise InputError(
            f"inputs.sequence: the sequence's CRS {seq['srs_name']} (EPSG:{seq['srid']}) differs from "
            f"the model's CRS {model['srs_name']} (EPSG:{model['srid']}); a job runs in the model's CRS"
        )
    if inputs.buildings:
        _check_buildings(session, int(model["id"]), inputs.buildings)
    try:
        options = inputs.run_options()
    except (TypeError, ValueError) as exc:
        raise InputError(f"inputs: {exc}") from exc
    session.rollback()
    from workers.submit import submit_job

    job_id = submit_job(session, model_id=int(model["id"]), sequence_id=int(seq["id"]), options=options)
    return job_id, status_info(session, job_id=job_id, base=base)


def dismiss(session: Session, *, job_id: uuid.UUID, base: str) -> dict[str, Any]:
    """Dismiss a job (`workers.submit.dismiss`: pending units dismissed, its tasks revoked);
    returns its statusInfo. 404 for an unknown job, 409 for a finished one."""
    status_info(session, job_id=job_id, base=base)
    from workers.submit import dismiss as dismiss_job

    dismiss_job(session, job_id=job_id)
    session.commit()
    return status_info(session, job_id=job_id, base=base)


def _successful(session: Session, job_id: uuid.UUID) -> None:
    row = session.execute(text("SELECT status, message, error FROM job WHERE id = :j"), {"j": job_id}).first()
    session.rollback()
    if row is None:
        raise NoSuchJobError(f"no job {job_id}")
    if row[0] != "successful":
        why = f": {row[2] or row[1]}" if row[0] == "failed" and (row[2] or row[1]) else ""
        raise ResultNotReadyError(f"job {job_id} is {row[0]}{why}; results exist once it is successful")


def results(session: Session, settings: Settings, *, job_id: uuid.UUID, base: str) -> dict[str, Any]:
    """OGC results document: each output the workers wrote, by reference (`href`, `type`)."""
    _successful(session, job_id)
    folder = job_dir(settings, job_id)
    out = {}
    for key, (rel, mt, title) in OUTPUTS.items():
        if (folder / rel).is_file():
            name = PurePosixPath(rel).name
            out[key] = {"href": f"{base}/jobs/{job_id}/results/{name}", "type": mt, "title": title}
    if "results" not in out:
        raise ResultNotReadyError(
            f"job {job_id} is successful; its results are being written, try again shortly"
        )
    return out


def result_file(session: Session, settings: Settings, *, job_id: uuid.UUID, name: str) -> Path:
    """A file of a successful job's results: `results.zip`, or a path inside its results folder
    (e.g. `report.json`, `textured.gml`, `textures/...`). 404 when there is no such file."""
    _successful(session, job_id)
    folder = job_dir(settings, job_id)
    if name == "results.zip":
        path = folder / "results.zip"
    else:
        rel = PurePosixPath(name)
        if rel.is_absolute() or ".." in rel.parts or "\\" in name or not rel.parts:
            raise NotFoundError(f"job {job_id} has no result {name!r}")
        path = folder / "results" / Path(*rel.parts)
        if not path.resolve().is_relative_to((folder / "results").resolve()):
            raise NotFoundError(f"job {job_id} has no result {name!r}")
    if not path.is_file():
        raise NotFoundError(f"job {job_id} has no result {name!r}")
    return path

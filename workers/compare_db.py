"""`citytherm compare --db JOB_A JOB_B`: the two jobs' results read from the city model database.

In: a database (Engine or URL) and two job ids. Out: the same output folder as from results
folders (`workers.compare.compare_surveys`): each building both jobs stored an appearance for is
loaded with `db.result_load.load_building_result` (tiles, texture coordinates, statistics), the
buildings from the model (`db.model_load.iter_model_buildings`, in the model's own CRS).

The air temperature of a job comes from its sequence's manifest (`sequence.manifest`
`conditions`, service jobs) or, for a job imported from a results folder (`citytherm run
--database`, `citytherm results import`), from that folder's `report.json` (`conditions`) when it
is still there. Refused with `CompareError`: an id that is no UUID or no job, a job that did not
finish successfully, jobs of different city models.
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, RowMapping, text
from sqlalchemy.orm import Session

from db.model_load import iter_model_buildings
from db.result_load import load_building_result
from db.session import as_engine
from workers.compare import CompareError, Survey, check_output, compare_surveys, conditions_of
from workers.pipeline.change import ChangeOptions
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.manifest import Conditions
from workers.pipeline.results import BuildingResult

_JOB = (
    "SELECT j.id, j.city_model_id, j.theme, j.status, j.results_location, j.created_at, j.finished_at, "
    "cm.name AS model_name, cm.srs_name, sq.manifest -> 'conditions' AS conditions "
    "FROM job j JOIN city_model cm ON cm.id = j.city_model_id "
    "LEFT JOIN sequence sq ON sq.id = j.sequence_id WHERE j.id = :j"
)
_BUILDINGS = (
    "SELECT b.gml_id FROM appearance a JOIN building b ON b.id = a.building_id "
    "WHERE a.job_id = :j AND NOT b.is_part ORDER BY b.ordinal"
)


def _job_id(text_id: str, label: str) -> uuid.UUID:
    """The job id as a UUID; `CompareError` naming it otherwise."""
    try:
        return uuid.UUID(str(text_id))
    except ValueError:
        raise CompareError(f"job {label} {text_id!r}: not a job id (a UUID)") from None


def _conditions(row: RowMapping) -> Conditions | None:
    """The job's survey conditions: its sequence's manifest, else its results folder's report."""
    if row["conditions"] is not None:
        return conditions_of(row["conditions"], f"job {row['id']}: sequence manifest")
    loc = row["results_location"]
    report = Path(loc) / "report.json" if loc else None
    if report is None or not report.is_file():
        return None
    try:
        doc = json.loads(report.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None  # the folder moved on since the import: no conditions, no normalisation
    return conditions_of(
        doc.get("conditions") if isinstance(doc, dict) else None, f"{report}: field 'conditions'"
    )


def database_survey(session: Session, job_id: str, label: str, url: str) -> tuple[Survey, RowMapping]:
    """One job as a `Survey` (loading from `session`; `label` "A" or "B" for messages, `url` for
    `change.json`) and its job row."""
    jid = _job_id(job_id, label)
    conn = session.connection()
    row = conn.execute(text(_JOB), {"j": jid}).mappings().first()
    if row is None:
        raise CompareError(f"job {label} {jid}: no such job in the database")
    if row["status"] != "successful":
        raise CompareError(f"job {label} {jid}: status {row['status']!r}, not finished successfully")
    ids = tuple(str(r[0]) for r in conn.execute(text(_BUILDINGS), {"j": jid}).all())
    model_id = int(row["city_model_id"])

    def load(bid: str) -> BuildingResult:
        return load_building_result(session, job_id=jid, model_id=model_id, building_gml_id=bid)

    times = {k: row[k].isoformat() if row[k] is not None else None for k in ("created_at", "finished_at")}
    survey = Survey(
        source={"job": str(jid), "database": url},
        theme=row["theme"],
        city_model=row["model_name"],
        conditions=_conditions(row),
        building_ids=ids,
        load=load,
        extra=times,
    )
    return survey, row


def _model_buildings(session: Session, model_id: int, ids: set[str]) -> Iterator[Building]:
    """The model's top-level buildings whose ids are in `ids`, model CRS, file order."""
    for b in iter_model_buildings(session.connection(), model_id):
        if b.id in ids:
            yield b


def compare_database_jobs(
    db: Engine | str,
    job_a: str,
    job_b: str,
    out_dir: str | Path,
    options: ChangeOptions = ChangeOptions(),
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """`compare_surveys` of two jobs in the database (A the earlier survey); returns
    `change.json`. Raises `CompareError` (module docstring)."""
    check_output(Path(out_dir))
    engine = as_engine(db)
    url = engine.url.render_as_string(hide_password=True)
    with Session(engine) as session:
        a, row_a = database_survey(session, job_a, "A", url)
        b, row_b = database_survey(session, job_b, "B", url)
        if row_a["city_model_id"] != row_b["city_model_id"]:
            raise CompareError(
                f"jobs A {row_a['id']} and B {row_b['id']} textured different city models: "
                f"{row_a['model_name']!r} (id {row_a['city_model_id']}) and {row_b['model_name']!r} "
                f"(id {row_b['city_model_id']})"
            )
        both = set(a.building_ids) & set(b.building_ids)
        buildings = _model_buildings(session, int(row_a["city_model_id"]), both)
        return compare_surveys(a, b, buildings, row_a["srs_name"], out_dir, options, progress)

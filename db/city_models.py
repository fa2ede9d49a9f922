"""The city models of the database as a whole: find one by name or id, list them with their
appearance themes and jobs, delete one.

In: a database (Engine, sessionmaker or URL; `find_model` takes a `Connection`). Out: plain
dataclasses for the command line and the service. `delete_city_model` removes a model with its
buildings, surfaces, appearances, texture images, statistics, poses, anomalies and job records in
one transaction, and refuses while a job of the model is `accepted` or `running`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import Connection, Engine, text

from db.errors import CityDBError, NotFoundError
from db.ops import delete_model
from db.session import as_engine

__all__ = [
    "ACTIVE_JOB_STATES",
    "DeletedModel",
    "ModelInUseError",
    "ModelInfo",
    "delete_city_model",
    "find_model",
    "list_models",
]

#: job states that keep a model from being deleted
ACTIVE_JOB_STATES = ("accepted", "running")


class ModelInUseError(CityDBError):
    """A city model that a job is working on (`accepted` or `running`)."""

    status_code = 409


@dataclass(frozen=True)
class ModelInfo:
    """One city model: its row and what hangs off it.

    Attributes:
        themes: appearance theme -> number of appearances of it (imported with the file or
            written by jobs), sorted by theme.
        jobs: job status -> number of the model's jobs in it.
    """

    id: int
    name: str
    srs_name: str | None
    srid: int
    buildings: int
    parts: int
    surfaces: int
    state: str
    imported_at: Any
    themes: dict[str, int] = field(default_factory=dict)
    jobs: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class DeletedModel:
    """What `delete_city_model` removed."""

    id: int
    name: str
    buildings: int
    appearances: int
    images: int
    jobs: int
    seconds: float


def find_model(
    conn: Connection, model: str | int, *, lock: str | None = None, by_id: bool = True
) -> Mapping[str, Any]:
    """The `city_model` row (id, name, srs_name, srid, state) of a model given by name, or by id
    (an int, or with `by_id` a string of digits that is no model's name). `lock`: a row lock
    clause such as `FOR UPDATE`. Raises `NotFoundError`."""
    cols = "SELECT id, name, srs_name, srid, state FROM city_model"
    suffix = f" {lock}" if lock else ""
    row = None
    if not isinstance(model, int):
        row = conn.execute(text(f"{cols} WHERE name = :v{suffix}"), {"v": str(model)}).mappings().first()
    if row is None and (isinstance(model, int) or (by_id and str(model).isdigit())):
        row = conn.execute(text(f"{cols} WHERE id = :v{suffix}"), {"v": int(model)}).mappings().first()
    if row is None:
        raise NotFoundError(f"city model {str(model)!r} not found")
    return row


def list_models(db: Engine | Any) -> list[ModelInfo]:
    """Every city model, by name, with its appearance themes and jobs per status."""
    engine = as_engine(db)
    with engine.connect() as conn:
        rows = (
            conn.execute(
                text(
                    "SELECT id, name, srs_name, srid, building_count, part_count, surface_count, state, "
                    "imported_at FROM city_model ORDER BY name"
                )
            )
            .mappings()
            .all()
        )
        themes: dict[int, dict[str, int]] = {}
        for m, theme, n in conn.execute(
            text(
                "SELECT city_model_id, theme, count(*) FROM appearance GROUP BY city_model_id, theme "
                "ORDER BY city_model_id, theme"
            )
        ).all():
            themes.setdefault(m, {})[theme] = int(n)
        jobs: dict[int, dict[str, int]] = {}
        for m, status, n in conn.execute(
            text("SELECT city_model_id, status, count(*) FROM job GROUP BY 1, 2 ORDER BY 1, 2")
        ).all():
            jobs.setdefault(m, {})[status] = int(n)
    return [
        ModelInfo(
            id=r["id"],
            name=r["name"],
            srs_name=r["srs_name"],
            srid=r["srid"],
            buildings=r["building_count"],
            parts=r["part_count"],
            surfaces=r["surface_count"],
            state=r["state"],
            imported_at=r["imported_at"],
            themes=themes.get(r["id"], {}),
            jobs=jobs.get(r["id"], {}),
        )
        for r in rows
    ]


def delete_city_model(db: Engine | Any, model: str | int) -> DeletedModel:
    """Delete a city model (name or id) and everything of it: buildings, surfaces, appearances
    (imported and the jobs'), texture images, statistics, poses, anomalies, jobs and their units;
    one transaction. Registered sequences stay (they belong to no model).

    The model's row is locked first: a job being created for it waits, then fails (its model is
    gone); a job created before is seen. Raises `ModelInUseError` while a job of the model is
    `accepted` or `running` (nothing deleted), `NotFoundError` for an unknown model."""
    t0 = time.perf_counter()
    engine = as_engine(db)
    with engine.begin() as conn:
        m = find_model(conn, model, lock="FOR UPDATE")
        busy = conn.execute(
            text(
                "SELECT id, status FROM job WHERE city_model_id = :m AND status = ANY(:s) ORDER BY created_at"
            ),
            {"m": m["id"], "s": list(ACTIVE_JOB_STATES)},
        ).all()
        if busy:
            jobs = ", ".join(f"{j} ({s})" for j, s in busy[:5])
            jobs += f" and {len(busy) - 5} more" if len(busy) > 5 else ""
            raise ModelInUseError(
                f"city model {m['name']!r} has {len(busy)} job(s) in progress: {jobs}; "
                "delete it when they have finished (or were dismissed)"
            )
        counts = conn.execute(
            text(
                "SELECT (SELECT count(*) FROM building WHERE city_model_id = :m AND NOT is_part), "
                "(SELECT count(*) FROM appearance WHERE city_model_id = :m), "
                "(SELECT count(*) FROM tex_image ti JOIN appearance a ON a.id = ti.appearance_id "
                "WHERE a.city_model_id = :m), "
                "(SELECT count(*) FROM job WHERE city_model_id = :m)"
            ),
            {"m": m["id"]},
        ).one()
        delete_model(conn, m["id"])
    return DeletedModel(
        id=m["id"],
        name=m["name"],
        buildings=int(counts[0]),
        appearances=int(counts[1]),
        images=int(counts[2]),
        jobs=int(counts[3]),
        seconds=time.perf_counter() - t0,
    )

"""3D Tiles of a model in the database: its newest job's thermal theme, exported once and cached.

In: a database (Engine or URL), a city model id (or name), optionally a job and a theme. Out: a
tileset folder. The model and the job's appearance are written by the CityGML export
(`db.export.export_citygml`: `textured.gml` + 16-bit tiles, the code path of every other export)
into a temporary folder, with `tiles3d-source.json` beside it (theme, the job's radiometry, the
surfaces' figures from `surface_thermal`, kelvin); `export_3dtiles` makes the tileset from that.

Caching (`cached_model_tileset`, the API): the tileset of a model's newest job (the job with
appearances whose `finished_at`, else `updated_at`, is latest) is kept under
`<cache root>/model-<id>/<job id>-<job updated_at as µs>/` and served until the job changes
(a re-import of results bumps `updated_at`) or another job becomes the newest; older tilesets of
the model are then removed. A tileset is built in a temporary folder and renamed into place, so
a request never sees half of one; concurrent requests of one process wait for one build.
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
import threading
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import Connection, Engine, text

from db.errors import NotFoundError
from db.export import export_citygml
from db.session import as_engine
from db.tiles3d.content import SurfaceFigures
from db.tiles3d.export import TilesetSummary, TilesOptions, export_3dtiles
from db.tiles3d.images import ValueScale
from db.tiles3d.source import folder_source, write_source_file
from workers.pipeline.geometry.manifest import Radiometry

__all__ = ["JobTheme", "cached_model_tileset", "export_model_3dtiles", "newest_job"]

_LOCKS: defaultdict[int, threading.Lock] = defaultdict(threading.Lock)
_LOCKS_LOCK = threading.Lock()


class NoThermalJobError(NotFoundError):
    """The model has no job with textures to show."""


@dataclass(frozen=True)
class JobTheme:
    """A job whose appearances are exported: id, theme, model id and a stamp of its last change."""

    job_id: str
    theme: str
    model_id: int
    stamp: int


def _model_id(conn: Connection, model: str | int) -> int:
    col = "id" if isinstance(model, int) or str(model).isdigit() else "name"
    row = conn.execute(
        text(f"SELECT id FROM city_model WHERE {col} = :v"), {"v": int(model) if col == "id" else model}
    ).first()
    if row is None:
        raise NotFoundError(f"city model {model!r} not found")
    return int(row[0])


def newest_job(conn: Connection, model: str | int, job_id: str | None = None) -> JobTheme:
    """The model's newest job with appearances (or job `job_id`). Raises `NotFoundError`."""
    mid = _model_id(conn, model)
    sql = (
        "SELECT j.id, j.theme, (extract(epoch FROM j.updated_at) * 1e6)::bigint AS stamp FROM job j "
        "WHERE j.city_model_id = :m AND EXISTS (SELECT 1 FROM appearance a WHERE a.job_id = j.id)"
    )
    if job_id is not None:
        sql += " AND j.id = CAST(:j AS uuid)"
    sql += " ORDER BY coalesce(j.finished_at, j.updated_at) DESC, j.created_at DESC LIMIT 1"
    row = conn.execute(text(sql), {"m": mid, "j": job_id}).first()
    if row is None:
        what = f"job {job_id}" if job_id else "no job with thermal textures"
        raise NoThermalJobError(f"city model {model!r}: {what} found")
    return JobTheme(job_id=str(row[0]), theme=str(row[1]), model_id=mid, stamp=int(row[2]))


def _radiometry(conn: Connection, job: JobTheme) -> Radiometry:
    rad = conn.execute(
        text(
            "SELECT radiometry FROM appearance WHERE job_id = CAST(:j AS uuid) "
            "AND radiometry IS NOT NULL LIMIT 1"
        ),
        {"j": job.job_id},
    ).scalar()
    if not isinstance(rad, dict):
        return Radiometry()
    return Radiometry(unit=str(rad["unit"]), scale=float(rad["scale"]), offset=float(rad["offset"]))


def _num(v: Any) -> float:
    return math.nan if v is None else float(v)


def _figures(conn: Connection, job: JobTheme, values: ValueScale) -> dict[str, SurfaceFigures]:
    """polygon gml:id -> figures of the job's surfaces (kelvin; counts from the raw statistics)."""
    rows = conn.execute(
        text(
            "SELECT s.gml_id, st.mean_k, st.typical_k, st.p05_k, st.p95_k, st.observed_share, "
            "st.temperature FROM surface_thermal st JOIN appearance a ON a.id = st.appearance_id "
            "JOIN surface s ON s.id = st.surface_id WHERE a.job_id = CAST(:j AS uuid)"
        ),
        {"j": job.job_id},
    ).all()
    out = {}
    for gml_id, mean, typical, p05, p95, share, raw in rows:
        if values.unit != "K":
            raw = raw or {}
            mean, p05, p95 = raw.get("mean"), raw.get("p05"), raw.get("p95")
        out[str(gml_id)] = SurfaceFigures(_num(mean), _num(typical), _num(p05), _num(p95), _num(share))
    return out


def _export(
    engine: Engine, job: JobTheme, work: Path, out: Path, options: TilesOptions | None
) -> TilesetSummary:
    """CityGML export of the job's theme into `work/src`, then the tileset into `out`."""
    src = work / "src"
    export_citygml(engine, src, model=job.model_id, theme=job.theme, job_id=job.job_id)
    with engine.connect() as conn:
        rad = _radiometry(conn, job)
        figures = _figures(conn, job, ValueScale.of(rad))
    write_source_file(src, job.theme, rad, figures)
    return export_3dtiles(folder_source(src, job.theme), out, options)


def export_model_3dtiles(
    db: Engine | Any,
    out_dir: str | Path,
    *,
    model: str | int,
    job_id: str | None = None,
    options: TilesOptions | None = None,
) -> TilesetSummary:
    """Write the tileset of a model's newest job (or job `job_id`) into `out_dir` (replaced)."""
    engine = as_engine(db)
    with engine.connect() as conn:
        job = newest_job(conn, model, job_id)
    out = Path(out_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=".tiles3d-src-", dir=out.parent))
    try:
        return _export(engine, job, work, out, options)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def cached_model_tileset(
    db: Engine | Any, cache_root: str | Path, model_id: int, options: TilesOptions | None = None
) -> Path:
    """The folder of the cached tileset of a model's newest job (built when missing; see the
    module docstring). Raises `NotFoundError` for an unknown model or one without thermal jobs."""
    engine = as_engine(db)
    with engine.connect() as conn:
        job = newest_job(conn, model_id)
    base = Path(cache_root) / f"model-{job.model_id}"
    final = base / f"{job.job_id}-{job.stamp}"
    if (final / "tileset.json").is_file():
        return final
    with _LOCKS_LOCK:
        lock = _LOCKS[job.model_id]
    with lock:
        if (final / "tileset.json").is_file():
            return final
        base.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=".build-", dir=base))
        try:
            _export(engine, job, work, work / "tiles", options)
            (work / "tiles" / "job.json").write_text(
                json.dumps({"job": job.job_id, "theme": job.theme, "stamp": job.stamp}), encoding="utf-8"
            )
            try:
                (work / "tiles").rename(final)
            except OSError:
                if not (final / "tileset.json").is_file():  # another process won: keep its copy
                    raise
        finally:
            shutil.rmtree(work, ignore_errors=True)
        for old in base.iterdir():
            if old != final and not old.name.startswith("."):
                shutil.rmtree(old, ignore_errors=True)
    return final

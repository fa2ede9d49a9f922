"""City models over HTTP: CityGML uploads queued for import, their state, deletion and export.

In: requests' parameters, a session or engine, the settings. Out: JSON-ready dicts (the routes'
response models describe them). The API's model id is the `model_import` id; once the worker's
import is complete (`ready`), the import points at its `city_model`.

An upload is streamed to `uploads/models/.tmp-*.gml` (gzip decoded on the fly), its first bytes
checked as CityGML; only then is the `model_import` row created (status `importing`), the file
renamed to `uploads/models/<id>.gml` and the import queued (`workers.submit.queue_model_import`).
Nothing is left when the upload is refused.
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
import zipfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, text
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request

from db.city_models import delete_city_model
from db.errors import CityDBError, NotFoundError
from db.export import export_citygml
from db.service_records import (
    UploadStateError,
    adopt_models,
    check_model_name,
    create_model_import,
    delete_model_import,
    fail_model_import,
    get_model_import,
    model_upload_path,
    set_model_upload,
)
from db.settings import Settings
from services.api.citygml_head import check_citygml_head
from services.api.uploads import check_declared_size, receive_body, temp_name


class QueueUnavailableError(CityDBError):
    """The task queue (Redis) did not take the task."""

    status_code = 503


_MODEL_SQL = """
SELECT mi.id, mi.name, mi.status, mi.message, mi.bytes, mi.progress, mi.created_at, mi.updated_at,
       mi.city_model_id, m.srs_name, m.srid, m.building_count, m.part_count, m.surface_count,
       m.citygml_version, m.imported_at,
       ST_XMin(x.e) AS x0, ST_YMin(x.e) AS y0, ST_ZMin(x.e) AS z0,
       ST_XMax(x.e) AS x1, ST_YMax(x.e) AS y1, ST_ZMax(x.e) AS z1
FROM model_import mi
LEFT JOIN city_model m ON m.id = mi.city_model_id
LEFT JOIN LATERAL (
    SELECT CASE WHEN m.srid > 0 AND ST_SRID(m.envelope) > 0 AND ST_SRID(m.envelope) <> m.srid
                THEN ST_Transform(m.envelope, m.srid) ELSE m.envelope END AS e
) x ON TRUE
"""


def _themes(session: Session, model_ids: list[int]) -> dict[int, dict[str, int]]:
    out: dict[int, dict[str, int]] = {}
    if not model_ids:
        return out
    for m, theme, n in session.execute(
        text(
            "SELECT city_model_id, theme, count(*) FROM appearance WHERE city_model_id = ANY(:ids) "
            "GROUP BY 1, 2 ORDER BY 1, 2"
        ),
        {"ids": model_ids},
    ).all():
        out.setdefault(int(m), {})[str(theme)] = int(n)
    return out


def _view(r: Mapping[str, Any], themes: dict[str, int], base: str) -> dict[str, Any]:
    ready = r["status"] == "ready" and r["city_model_id"] is not None
    href = f"{base}/models/{r['id']}"
    out: dict[str, Any] = {
        "id": int(r["id"]),
        "name": r["name"],
        "status": r["status"] if ready or r["status"] != "ready" else "failed",
        "message": r["message"] if ready or r["status"] != "ready" else "the city model was deleted",
        "bytes": int(r["bytes"] or 0),
        "progress": float(r["progress"] or 0.0),
        "created": r["created_at"],
        "updated": r["updated_at"],
        "links": [{"href": href, "rel": "self", "type": "application/json", "title": r["name"]}],
    }
    if ready:
        out.update(
            crs=r["srs_name"],
            srid=int(r["srid"] or 0),
            citygml_version=r["citygml_version"],
            buildings=int(r["building_count"] or 0),
            parts=int(r["part_count"] or 0),
            surfaces=int(r["surface_count"] or 0),
            themes=themes,
            imported=r["imported_at"],
            extent=None if r["x0"] is None else [r[k] for k in ("x0", "y0", "z0", "x1", "y1", "z1")],
        )
        out["links"].append(
            {"href": f"{href}/citygml", "rel": "enclosure", "type": "application/zip", "title": "CityGML 2.0"}
        )
    return out


def model_view(session: Session, *, import_id: int, base: str) -> dict[str, Any]:
    """One model: status importing|ready|failed (message); when ready its CRS, counts, extent
    (minx, miny, minz, maxx, maxy, maxz in the model CRS) and appearance themes."""
    if adopt_models(session):
        session.commit()
    r = session.execute(text(_MODEL_SQL + " WHERE mi.id = :i"), {"i": import_id}).mappings().first()
    if r is None:
        raise NotFoundError(f"city model {import_id} not found")
    themes = _themes(session, [r["city_model_id"]] if r["city_model_id"] else [])
    return _view(r, themes.get(r["city_model_id"], {}), base)


def list_model_views(session: Session, *, base: str) -> dict[str, Any]:
    """Every model import with its city model, newest first (models imported from the command
    line adopted first)."""
    if adopt_models(session):
        session.commit()
    rows = session.execute(text(_MODEL_SQL + " ORDER BY mi.id DESC")).mappings().all()
    themes = _themes(session, [int(r["city_model_id"]) for r in rows if r["city_model_id"]])
    return {
        "models": [_view(r, themes.get(r["city_model_id"], {}), base) for r in rows],
        "links": [{"href": f"{base}/models", "rel": "self", "type": "application/json"}],
    }


def _register_upload(session: Session, settings: Settings, *, name: str, tmp: Path, size: int) -> int:
    """Create the import row, move the upload to its place, commit (the file removed on error)."""
    target: Path | None = None
    try:
        import_id = create_model_import(session, name=name, nbytes=size)
        target = model_upload_path(settings.storage_dir, import_id)
        tmp.replace(target)
        set_model_upload(session, import_id=import_id, upload_path=str(target.resolve()), nbytes=size)
        session.commit()
    except BaseException:
        session.rollback()
        tmp.unlink(missing_ok=True)
        if target is not None:
            target.unlink(missing_ok=True)
        raise
    return import_id


def _queue(session: Session, *, import_id: int, path: Path) -> None:
    """Queue the import; when the queue refuses, the import fails (message) and the file goes."""
    from workers.submit import queue_model_import

    try:
        queue_model_import(import_id)
    except Exception as exc:
        fail_model_import(session, import_id=import_id, message=f"could not queue the import: {exc}")
        session.commit()
        path.unlink(missing_ok=True)
        raise QueueUnavailableError(
            f"the import could not be queued ({type(exc).__name__}); try again"
        ) from exc


def _check_name(session: Session, name: str) -> None:
    try:
        check_model_name(session, name=name)
    finally:
        session.rollback()


async def accept_model_upload(
    request: Request, session: Session, settings: Settings, *, name: str, content_encoding: str | None
) -> dict[str, Any]:
    """Stream the CityGML body to storage, check its head, record and queue the import.
    Returns `{"id", "name", "status": "importing"}`."""
    folder = model_upload_path(settings.storage_dir, 0).parent
    check_declared_size(
        request, limit=settings.max_upload_bytes, min_free=settings.min_free_bytes, folder=folder
    )
    await run_in_threadpool(_check_name, session, name)
    received = await receive_body(
        request,
        temp_name(folder, ".gml"),
        limit=settings.max_upload_bytes,
        min_free=settings.min_free_bytes,
        content_encoding=content_encoding,
        head=check_citygml_head,
    )
    import_id = await run_in_threadpool(
        lambda: _register_upload(session, settings, name=name, tmp=received.path, size=received.size)
    )
    await run_in_threadpool(
        lambda: _queue(session, import_id=import_id, path=model_upload_path(settings.storage_dir, import_id))
    )
    return {"id": import_id, "name": name, "status": "importing", "bytes": received.size}


def delete_model(session: Session, engine: Engine, *, import_id: int) -> None:
    """Delete a model: its city model with everything of it (`db.city_models.delete_city_model`,
    refused with 409 while one of its jobs is accepted or running) and its import record.
    An import still running is refused (409)."""
    row = get_model_import(session, import_id=import_id)
    status, city_model_id, upload = row.status, row.city_model_id, row.upload_path
    session.rollback()
    if status == "importing":
        raise UploadStateError(
            f"city model {import_id} is being imported; delete it when the import has ended"
        )
    if city_model_id is not None:
        with contextlib.suppress(NotFoundError):  # deleted meanwhile (e.g. from the command line)
            delete_city_model(engine, int(city_model_id))
    delete_model_import(session, import_id=import_id)
    session.commit()
    if upload:
        Path(upload).unlink(missing_ok=True)


def _ready_model_id(session: Session, import_id: int) -> int:
    row = get_model_import(session, import_id=import_id)
    if row.status != "ready" or row.city_model_id is None:
        raise UploadStateError(f"city model {import_id} is not ready (status {row.status})")
    return int(row.city_model_id)


def parse_bbox(bbox: str | None) -> tuple[float, float, float, float] | None:
    """`"minx,miny,maxx,maxy"` -> a tuple (model CRS); None stays None.

    >>> parse_bbox("1,2,3,4")
    (1.0, 2.0, 3.0, 4.0)
    """
    if bbox is None or not bbox.strip():
        return None
    try:
        vals = tuple(float(v) for v in bbox.split(","))
    except ValueError:
        raise _BboxError(f"bbox: expected minx,miny,maxx,maxy as numbers, got {bbox!r}") from None
    if len(vals) != 4 or not all(abs(v) < 1e12 for v in vals) or vals[0] > vals[2] or vals[1] > vals[3]:
        raise _BboxError(f"bbox: expected minx,miny,maxx,maxy with min <= max, got {bbox!r}")
    return vals  # type: ignore[return-value]


class _BboxError(CityDBError):
    status_code = 422


def export_model_zip(
    session: Session,
    engine: Engine,
    settings: Settings,
    *,
    import_id: int,
    theme: str | None,
    bbox: str | None,
) -> tuple[Path, Path]:
    """Export the model (`db.export.export_citygml`: CityGML 2.0 + textures, optionally one theme
    and a bbox) into a temporary folder and zip it there. Returns (zip, folder to remove)."""
    box = parse_bbox(bbox)
    model_id = _ready_model_id(session, import_id)
    session.rollback()
    tmp_root = Path(settings.storage_dir) / "tmp"
    tmp_root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="export-", dir=tmp_root))
    try:
        out = tmp / "model"
        export_citygml(engine, out, model=model_id, theme=theme or None, bbox=box)
        zpath = tmp / f"model-{import_id}.zip"
        with zipfile.ZipFile(zpath, "w") as zf:
            for f in sorted(out.rglob("*")):
                if f.is_file():
                    packed = zipfile.ZIP_STORED if f.suffix.lower() == ".png" else zipfile.ZIP_DEFLATED
                    zf.write(f, f.relative_to(out).as_posix(), compress_type=packed)
        shutil.rmtree(out, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return zpath, tmp

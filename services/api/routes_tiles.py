"""3D Tiles of a city model over HTTP: `GET /models/{id}/3dtiles/tileset.json` and the files it
refers to (`/models/{id}/3dtiles/content/<level>/<x>_<y>.glb`). Thin: the tileset of the model's
newest job with thermal textures is made and cached by `db.tiles3d.database.cached_model_tileset`
under `<storage_dir>/3dtiles/` (built on the first request after the job changed, then served
from disk; docs/3dtiles.md)."""

from __future__ import annotations

from pathlib import Path as FsPath
from typing import Annotated

from fastapi import APIRouter, HTTPException, Path
from fastapi.responses import FileResponse
from sqlalchemy.orm import Session

from db.service_records import UploadStateError, get_model_import
from db.settings import Settings
from db.tiles3d.database import cached_model_tileset
from services.api.deps import EngineDep, ReadAccess, SessionDep, SettingsDep
from services.api.problems import problem_responses
from services.api.routes_processes import AUTH

router = APIRouter()

MEDIA_TYPES = {".json": "application/json", ".glb": "model/gltf-binary"}
ModelId = Annotated[int, Path(ge=1, le=2**62, description="API model id (`GET /models`).")]


def _tileset_folder(session: Session, engine: EngineDep, settings: Settings, import_id: int) -> FsPath:
    """The cached tileset folder of an API model (its import must be ready)."""
    row = get_model_import(session, import_id=import_id)
    if row.status != "ready" or row.city_model_id is None:
        raise UploadStateError(f"city model {import_id} is not ready (status {row.status})")
    model_id = int(row.city_model_id)
    session.rollback()  # no transaction stays open while the tileset is built
    return cached_model_tileset(engine, FsPath(settings.storage_dir) / "3dtiles", model_id)


@router.get(
    "/models/{modelId}/3dtiles/tileset.json",
    response_class=FileResponse,
    tags=["3D Tiles"],
    responses={
        200: {"content": {"application/json": {}}, "description": "3D Tiles 1.1 tileset."},
        **AUTH,
        **problem_responses(404, 409),
    },
)
def tileset(
    session: SessionDep, engine: EngineDep, settings: SettingsDep, _: ReadAccess, modelId: ModelId
) -> FileResponse:
    """The model's newest thermal job as 3D Tiles 1.1 (glTF content with the display texture, the
    per-texel temperature as an `EXT_structural_metadata` property texture and surfaces as
    `EXT_mesh_features` feature ids). 404 for a model without a job with textures."""
    folder = _tileset_folder(session, engine, settings, modelId)
    return FileResponse(folder / "tileset.json", media_type="application/json")


@router.get(
    "/models/{modelId}/3dtiles/{path:path}",
    response_class=FileResponse,
    tags=["3D Tiles"],
    responses={
        200: {"content": {"model/gltf-binary": {}}, "description": "A tile's glTF content."},
        **AUTH,
        **problem_responses(404, 409),
    },
)
def tile_file(
    session: SessionDep, engine: EngineDep, settings: SettingsDep, _: ReadAccess, modelId: ModelId, path: str
) -> FileResponse:
    """A file of the model's tileset (a tile's GLB), by the relative URI the tileset gives."""
    folder = _tileset_folder(session, engine, settings, modelId).resolve()
    try:
        target = (folder / path).resolve()
        found = folder in target.parents and target.suffix in MEDIA_TYPES and target.is_file()
    except (ValueError, OSError):  # a NUL byte, a name too long
        found = False
    if not found:
        raise HTTPException(404, f"no file {path[:200]!r} in the tileset of model {modelId}")
    return FileResponse(target, media_type=MEDIA_TYPES[target.suffix])

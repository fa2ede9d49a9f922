"""City model and sequence routes: uploads, state, deletion, export. Thin: each translates HTTP to
a call of `service_models` / `service_sequences` and back."""

from __future__ import annotations

import shutil
import uuid
from typing import Annotated

from fastapi import APIRouter, Header, HTTPException, Path, Query, Request, Response
from fastapi.responses import FileResponse
from starlette.background import BackgroundTask

from services.api import service_models, service_sequences
from services.api.deps import AdminAccess, EngineDep, ReadAccess, SessionDep, SettingsDep, SubmitAccess
from services.api.problems import problem_responses
from services.api.routes_processes import AUTH, base_url
from services.api.schemas import (
    ModelAccepted,
    ModelList,
    ModelView,
    PartReceived,
    RegisterRequest,
    SequenceCreated,
    SequenceView,
)

router = APIRouter()

CITYGML_TYPES = ("application/xml", "application/gml+xml", "text/xml")
_RAW_BODY = {
    "content": {
        "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
    },
    "required": True,
}
_GML_BODY = {
    "content": {t: {"schema": {"type": "string", "format": "binary"}} for t in CITYGML_TYPES[:2]},
    "required": True,
}


@router.post(
    "/models",
    status_code=202,
    response_model=ModelAccepted,
    tags=["Models"],
    openapi_extra={"requestBody": _GML_BODY},
    responses={**AUTH, **problem_responses(400, 409, 413, 415, 422, 503, 507)},
)
async def upload_model(
    request: Request,
    response: Response,
    session: SessionDep,
    settings: SettingsDep,
    _: SubmitAccess,
    name: Annotated[str, Query(min_length=1, max_length=200, pattern=r"^[^\x00-\x1f/\\]+$")],
    content_type: Annotated[str | None, Header()] = None,
    content_encoding: Annotated[str | None, Header()] = None,
) -> dict:
    """Upload a CityGML file (1.0/2.0/3.0) as the raw body (`application/xml` or
    `application/gml+xml`, optionally `Content-Encoding: gzip`); it is imported by a worker.
    202 with the model id; poll `GET /models/{id}` until `ready` (or `failed`, with a message).
    A body that is plainly not CityGML is refused at once (400)."""
    mime = (content_type or "").split(";")[0].strip().lower()
    if mime not in CITYGML_TYPES:
        raise HTTPException(
            415, f"Content-Type {mime or '(none)'!r}: expected application/xml or application/gml+xml"
        )
    out = await service_models.accept_model_upload(
        request, session, settings, name=name, content_encoding=content_encoding
    )
    response.headers["Location"] = f"/models/{out['id']}"
    return out


@router.get("/models", response_model=ModelList, tags=["Models"], responses=AUTH)
def models(request: Request, session: SessionDep, _: ReadAccess) -> dict:
    """The city models (imports and their models): id, name, status, CRS, counts, themes."""
    return service_models.list_model_views(session, base=base_url(request))


@router.get(
    "/models/{modelId}",
    response_model=ModelView,
    tags=["Models"],
    responses={**AUTH, **problem_responses(404)},
)
def model(
    request: Request, session: SessionDep, _: ReadAccess, modelId: Annotated[int, Path(ge=1, le=2**62)]
) -> dict:
    """A city model: status importing, ready (CRS, counts, extent, themes) or failed (message)."""
    return service_models.model_view(session, import_id=modelId, base=base_url(request))


@router.delete(
    "/models/{modelId}", status_code=204, tags=["Models"], responses={**AUTH, **problem_responses(404, 409)}
)
def delete_model(
    session: SessionDep,
    engine: EngineDep,
    _: AdminAccess,
    modelId: Annotated[int, Path(ge=1, le=2**62)],
) -> Response:
    """Delete a city model with its appearances, textures and jobs (admin). 409 while it is being
    imported or one of its jobs is accepted or running."""
    service_models.delete_model(session, engine, import_id=modelId)
    return Response(status_code=204)


@router.get(
    "/models/{modelId}/citygml",
    response_class=FileResponse,
    tags=["Models"],
    responses={
        200: {"content": {"application/zip": {}}, "description": "CityGML 2.0 with its textures, zipped."},
        **AUTH,
        **problem_responses(404, 409, 422),
    },
)
def export_model(
    session: SessionDep,
    engine: EngineDep,
    settings: SettingsDep,
    _: ReadAccess,
    modelId: Annotated[int, Path(ge=1, le=2**62)],
    theme: Annotated[str | None, Query(max_length=200, description="Only this appearance theme.")] = None,
    bbox: Annotated[str | None, Query(max_length=200, description="minx,miny,maxx,maxy (model CRS).")] = None,
) -> FileResponse:
    """The model as CityGML 2.0 with its textures (a zip: `textured.gml`, `textures/...`,
    `anomalies.geojson`), optionally one theme's appearances and the buildings in a bbox."""
    zpath, tmp = service_models.export_model_zip(
        session, engine, settings, import_id=modelId, theme=theme, bbox=bbox
    )
    return FileResponse(
        zpath,
        media_type="application/zip",
        filename=zpath.name,
        background=BackgroundTask(shutil.rmtree, tmp, ignore_errors=True),
    )


@router.post(
    "/sequences", status_code=201, response_model=SequenceCreated, tags=["Sequences"], responses=AUTH
)
def create_sequence(response: Response, session: SessionDep, _: SubmitAccess) -> dict:
    """Open a resumable sequence upload: send the archive (`.zip`, `.tar`, `.tar.gz`) in parts
    1..N with `PUT /sequences/{id}/parts/{n}`, then `POST /sequences/{id}/commit`."""
    out = service_sequences.new_upload(session)
    response.headers["Location"] = f"/sequences/{out['id']}"
    return out


@router.put(
    "/sequences/{sequenceId}/parts/{n}",
    response_model=PartReceived,
    tags=["Sequences"],
    openapi_extra={"requestBody": _RAW_BODY},
    responses={**AUTH, **problem_responses(400, 404, 409, 413, 507)},
)
async def put_part(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    _: SubmitAccess,
    sequenceId: uuid.UUID,
    n: Annotated[int, Path(ge=1, le=service_sequences.MAX_PARTS)],
    content_md5: Annotated[str | None, Header(description="Base64 MD5 of the part (RFC 1864).")] = None,
) -> dict:
    """Part `n` (1, 2, ...) of the archive, raw bytes. Sending a part again replaces it. With
    `Content-MD5` the part is checked (400 on mismatch). 409 once the upload is committed."""
    del content_md5  # read from the request by the service (declared here for the API document)
    return await service_sequences.accept_part(request, session, settings, upload_id=sequenceId, n=n)


@router.post(
    "/sequences/{sequenceId}/commit",
    response_model=SequenceView,
    tags=["Sequences"],
    responses={**AUTH, **problem_responses(400, 404, 409, 422, 507)},
)
def commit_sequence(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    _: SubmitAccess,
    sequenceId: uuid.UUID,
) -> dict:
    """Assemble parts 1..N (a gap: 400 naming the missing part), extract and validate the package
    (422 naming the field or file the reader refused), register it: the sequence with its
    frames, CRS and platform."""
    return service_sequences.commit_upload(session, settings, upload_id=sequenceId, base=base_url(request))


@router.post(
    "/sequences/register",
    status_code=201,
    response_model=SequenceView,
    tags=["Sequences"],
    responses={**AUTH, **problem_responses(404, 422, 507)},
)
def register_sequence(
    request: Request, session: SessionDep, settings: SettingsDep, _: AdminAccess, body: RegisterRequest
) -> dict:
    """Register a package already on the storage (admin): a folder, its sequence.json or an
    archive, inside the storage directory."""
    return service_sequences.register_path(session, settings, path=body.path, base=base_url(request))


@router.get(
    "/sequences/{sequenceId}",
    response_model=SequenceView,
    tags=["Sequences"],
    responses={**AUTH, **problem_responses(404)},
)
def sequence(request: Request, session: SessionDep, _: ReadAccess, sequenceId: uuid.UUID) -> dict:
    """A sequence: its upload (status, parts) and, once committed, frames, CRS and platform."""
    return service_sequences.sequence_view(session, upload_id=sequenceId, base=base_url(request))

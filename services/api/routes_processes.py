"""OGC API - Processes 1.0 Core routes: landing page, conformance, processes, execution, jobs,
results. Thin: each translates HTTP to a call of `service_jobs` and back."""

from __future__ import annotations

import uuid
from typing import Annotated

from fastapi import APIRouter, Header, Path, Query, Request, Response
from fastapi.responses import FileResponse

from services.api import service_jobs
from services.api.deps import ReadAccess, SessionDep, SettingsDep, SubmitAccess
from services.api.features import FEATURES_CONFORMANCE
from services.api.problems import problem_responses
from services.api.schemas import (
    Conformance,
    Execute,
    JobList,
    LandingPage,
    OutputRef,
    ProcessDescription,
    ProcessList,
    StatusInfo,
)

router = APIRouter()

CONFORMANCE = [
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/core",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/ogc-process-description",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/json",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/oas30",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/job-list",
    "http://www.opengis.net/spec/ogcapi-processes-1/1.0/conf/dismiss",
    *FEATURES_CONFORMANCE,
]
JOB_STATES = ("accepted", "running", "successful", "failed", "dismissed")
AUTH = problem_responses(401, 403)


def base_url(request: Request) -> str:
    """The API's base URL (no trailing slash), for links."""
    return str(request.base_url).rstrip("/")


@router.get("/", response_model=LandingPage, tags=["OGC API"])
def landing_page(request: Request) -> dict:
    """Landing page: links to the API definition, conformance, processes and jobs (open: clients
    discover the API, and health checks probe it, without a key)."""
    b = base_url(request)
    return {
        "title": "citytherm",
        "description": "Thermal-infrared image sequences textured onto CityGML building models "
        "(OGC API - Processes; OGC API - Features at /collections). Upload city models (/models) and "
        "sequences (/sequences), then execute the texture process.",
        "links": [
            {"href": f"{b}/", "rel": "self", "type": "application/json", "title": "this document"},
            {
                "href": f"{b}/openapi.json",
                "rel": "service-desc",
                "type": "application/vnd.oai.openapi+json;version=3.0",
                "title": "the API definition",
            },
            {
                "href": f"{b}/docs",
                "rel": "service-doc",
                "type": "text/html",
                "title": "the API documentation",
            },
            {
                "href": f"{b}/conformance",
                "rel": "http://www.opengis.net/def/rel/ogc/1.0/conformance",
                "type": "application/json",
                "title": "conformance classes",
            },
            {
                "href": f"{b}/processes",
                "rel": "http://www.opengis.net/def/rel/ogc/1.0/processes",
                "type": "application/json",
                "title": "processes",
            },
            {
                "href": f"{b}/jobs",
                "rel": "http://www.opengis.net/def/rel/ogc/1.0/job-list",
                "type": "application/json",
                "title": "jobs",
            },
            {
                "href": f"{b}/collections",
                "rel": "data",
                "type": "application/json",
                "title": "feature collections (OGC API - Features)",
            },
            {"href": f"{b}/models", "rel": "related", "type": "application/json", "title": "city models"},
        ],
    }


@router.get("/conformance", response_model=Conformance, tags=["OGC API"])
def conformance() -> dict:
    """The conformance classes the API implements (open, as the landing page)."""
    return {"conformsTo": CONFORMANCE}


@router.get("/processes", response_model=ProcessList, tags=["Processes"], responses=AUTH)
def processes(request: Request, _: ReadAccess) -> dict:
    """The processes: one, `texture`."""
    b = base_url(request)
    return {
        "processes": [service_jobs.process_summary(b)],
        "links": [{"href": f"{b}/processes", "rel": "self", "type": "application/json"}],
    }


@router.get(
    "/processes/{processID}",
    response_model=ProcessDescription,
    tags=["Processes"],
    responses={**AUTH, **problem_responses(404)},
)
def process(request: Request, _: ReadAccess, processID: Annotated[str, Path(max_length=200)]) -> dict:
    """The process description: inputs (the options of `citytherm run`) and outputs."""
    service_jobs.check_process(processID)
    return service_jobs.process_description(base_url(request))


@router.post(
    "/processes/{processID}/execution",
    status_code=201,
    response_model=StatusInfo,
    tags=["Processes"],
    responses={**AUTH, **problem_responses(404, 409, 422, 503)},
)
def execute(
    request: Request,
    response: Response,
    session: SessionDep,
    _: SubmitAccess,
    body: Execute,
    processID: Annotated[str, Path(max_length=200)],
    prefer: Annotated[str | None, Header()] = None,
) -> dict:
    """Execute the process: always asynchronously (201 Created, `Location: /jobs/{jobId}`, the
    job's statusInfo), with or without `Prefer: respond-async` (synchronous execution is not
    offered, as OGC API - Processes allows). Unknown model or sequence: 404; model not ready or
    sequence not committed: 409; a sequence in another CRS than the model's, or an option that
    does not fit: 422 naming the input."""
    service_jobs.check_process(processID)
    job_id, info = service_jobs.execute(session, inputs=body.inputs, base=base_url(request))
    response.headers["Location"] = f"/jobs/{job_id}"
    if prefer and "respond-async" in prefer:
        response.headers["Preference-Applied"] = "respond-async"
    return info


@router.get("/jobs", response_model=JobList, tags=["Jobs"], responses={**AUTH, **problem_responses(422)})
def jobs(
    request: Request,
    session: SessionDep,
    _: ReadAccess,
    status: Annotated[list[str] | None, Query(description=f"One of {', '.join(JOB_STATES)}.")] = None,
    processID: Annotated[list[str] | None, Query(max_length=200)] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 20,
    offset: Annotated[int, Query(ge=0, le=10**9)] = 0,
) -> dict:
    """The jobs, newest first; `status` and `processID` filter (repeatable), `limit`/`offset` page
    (a `next` link while there are more)."""
    bad = [s for s in status or () if s not in JOB_STATES]
    if bad:
        raise service_jobs.InputError(f"status: {bad[0]!r} is not one of {', '.join(JOB_STATES)}")
    return service_jobs.list_jobs(
        session, status=status, process_id=processID, limit=limit, offset=offset, base=base_url(request)
    )


@router.get(
    "/jobs/{jobId}", response_model=StatusInfo, tags=["Jobs"], responses={**AUTH, **problem_responses(404)}
)
def job(request: Request, session: SessionDep, _: ReadAccess, jobId: uuid.UUID) -> dict:
    """A job's status (OGC statusInfo, with its stage and unit counts by state)."""
    return service_jobs.status_info(session, job_id=jobId, base=base_url(request))


@router.delete(
    "/jobs/{jobId}",
    response_model=StatusInfo,
    tags=["Jobs"],
    responses={**AUTH, **problem_responses(404, 409)},
)
def dismiss(request: Request, session: SessionDep, _: SubmitAccess, jobId: uuid.UUID) -> dict:
    """Dismiss a job: pending units are dismissed and their tasks revoked (stored results stay).
    409 for a job that has finished."""
    return service_jobs.dismiss(session, job_id=jobId, base=base_url(request))


@router.get(
    "/jobs/{jobId}/results",
    response_model=dict[str, OutputRef],
    tags=["Jobs"],
    responses={**AUTH, **problem_responses(404, 409)},
)
def results(
    request: Request, session: SessionDep, settings: SettingsDep, _: ReadAccess, jobId: uuid.UUID
) -> dict:
    """The results of a successful job, by reference: `results` (the results folder zipped),
    `orientation` (orientation.json), `report` (report.json). 409 (result-not-ready) before."""
    return service_jobs.results(session, settings, job_id=jobId, base=base_url(request))


@router.get(
    "/jobs/{jobId}/results/{name:path}",
    response_class=FileResponse,
    tags=["Jobs"],
    responses={
        200: {"content": {"application/zip": {}, "application/json": {}}, "description": "The file."},
        **AUTH,
        **problem_responses(404, 409),
    },
)
def result_file(
    session: SessionDep,
    settings: SettingsDep,
    _: ReadAccess,
    jobId: uuid.UUID,
    name: Annotated[str, Path(max_length=1000)],
) -> FileResponse:
    """One file of a successful job's results: `results.zip`, `orientation.json`, `report.json`,
    or any path inside the results folder (`textured.gml`, `textures/...`)."""
    path = service_jobs.result_file(session, settings, job_id=jobId, name=name)
    return FileResponse(path, filename=path.name)

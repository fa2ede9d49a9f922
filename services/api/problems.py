"""RFC 7807 problem details (`application/problem+json`) for every error of the API.

In: exceptions raised by routes, dependencies and the layers below. Out: JSON responses with
`type`, `title`, `status`, `detail` (and `instance`, the request path). One handler per kind:
- `db.errors.CityDBError` and its subclasses carry their `status_code` (and optionally a
  `problem_type` URI, e.g. OGC's `no-such-job`);
- `PackageError` (a sequence package the reader refused: names the field or file) -> 422;
- `CityGMLError` (a CityGML document that cannot be read) -> 400;
- `OptionsError` / `RunError` (job options that do not fit) -> 422;
- request validation (FastAPI) -> 422 naming each offending parameter or input;
- `HTTPException` (unknown routes, wrong methods, auth) -> its status and headers;
- anything else -> 500 without internals (logged).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from db.citygml import CityGMLError
from db.errors import CityDBError
from db.sequence_manifest import PackageError
from workers.job import RunError
from workers.pipeline.options import OptionsError

log = logging.getLogger("citytherm.api")

PROBLEM_JSON = "application/problem+json"
OGC_EXCEPTIONS = "http://www.opengis.net/def/exceptions/ogcapi-processes-1/1.0/"


class Problem(BaseModel):
    """RFC 7807 problem details."""

    type: str = Field("about:blank", description="URI of the problem type.")
    title: str = Field(..., description="Short summary of the problem type.")
    status: int = Field(..., description="HTTP status code.")
    detail: str | None = Field(None, description="What went wrong with this request.")
    instance: str | None = Field(None, description="The request path.")


#: `responses=` entry for the OpenAPI document of routes that answer with problems.
def problem_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` for the given status codes, each a problem+json document."""
    return {
        code: {
            "model": Problem,
            "description": HTTPStatus(code).phrase,
            "content": {PROBLEM_JSON: {"schema": {"$ref": "#/components/schemas/Problem"}}},
        }
        for code in codes
    }


def problem(
    request: Request,
    status: int,
    detail: str | None,
    *,
    type_: str = "about:blank",
    headers: Mapping[str, str] | None = None,
) -> JSONResponse:
    """A problem+json response."""
    try:
        title = HTTPStatus(status).phrase
    except ValueError:
        title = "Error"
    body = Problem(type=type_, title=title, status=status, detail=detail, instance=request.url.path)
    return JSONResponse(
        body.model_dump(exclude_none=True), status_code=status, media_type=PROBLEM_JSON, headers=headers
    )


def _loc(loc: Sequence[Any]) -> str:
    parts = [str(p) for p in loc if p not in ("body",)]
    return ".".join(parts) or "body"


def validation_detail(errors: Sequence[Mapping[str, Any]]) -> str:
    """`where: message` for each validation error, joined with `; `."""
    return "; ".join(f"{_loc(e.get('loc', ()))}: {e.get('msg', 'invalid')}" for e in errors)


async def _domain(request: Request, exc: Exception) -> JSONResponse:
    status = int(getattr(exc, "status_code", 500))
    if status >= 500 and status != 507:
        log.error("domain error %s on %s: %s", type(exc).__name__, request.url.path, exc)
    return problem(request, status, str(exc), type_=getattr(exc, "problem_type", "about:blank"))


async def _package(request: Request, exc: Exception) -> JSONResponse:
    return problem(request, 422, f"sequence package refused: {exc}")


async def _citygml(request: Request, exc: Exception) -> JSONResponse:
    return problem(request, 400, f"not a readable CityGML document: {exc}")


async def _options(request: Request, exc: Exception) -> JSONResponse:
    return problem(request, 422, str(exc))


async def _validation(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    return problem(request, 422, validation_detail(exc.errors()))


async def _http(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
    if exc.status_code == 404 and detail == "Not Found":
        detail = f"no resource at {request.url.path}"
    return problem(request, exc.status_code, detail, headers=exc.headers)


async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unexpected error on %s %s", request.method, request.url.path, exc_info=exc)
    return problem(request, 500, "internal error; see the service log")


def install_problem_handlers(app: FastAPI) -> None:
    """Register the handlers above on `app`."""
    app.add_exception_handler(CityDBError, _domain)
    app.add_exception_handler(PackageError, _package)
    app.add_exception_handler(CityGMLError, _citygml)
    app.add_exception_handler(OptionsError, _options)
    app.add_exception_handler(RunError, _options)
    app.add_exception_handler(RequestValidationError, _validation)
    app.add_exception_handler(StarletteHTTPException, _http)
    app.add_exception_handler(Exception, _unexpected)

"""The FastAPI application of the citytherm service (`docs/service.md`).

`create_app(settings)` builds the app: the settings (created once, here or by the caller), one
database engine and session factory on `app.state`, the routes (OGC API - Processes for jobs;
models and sequences; OGC API - Features for buildings, facades, anomalies and jobs), and RFC 7807
problem responses for every error. OpenAPI at `/openapi.json`, interactive documentation at
`/docs`. Run it with `citytherm serve`.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI

from db.session import make_engine, make_session_factory
from db.settings import Settings
from services.api import routes_data, routes_features, routes_processes, routes_tiles, routes_viewer
from services.api.problems import Problem, install_problem_handlers
from workers.celery_app import configure as configure_celery

API_VERSION = "1.0.0"


def create_app(settings: Settings | None = None) -> FastAPI:
    """The API app for `settings` (default: read once from the environment, `CITYTHERM_*`)."""
    settings = settings or Settings()
    engine = make_engine(settings)
    configure_celery(settings)  # tasks are sent to this settings' broker

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        Path(settings.storage_dir).mkdir(parents=True, exist_ok=True)
        yield
        engine.dispose()

    app = FastAPI(
        title="citytherm",
        version=API_VERSION,
        description="Thermal-infrared image sequences textured onto CityGML building models: city "
        "models and sequence packages in, texturing jobs (OGC API - Processes 1.0) out. Access with "
        "`Authorization: Bearer KEY` (`citytherm apikey create`). Errors are RFC 7807 problem details.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.engine = engine
    app.state.session_factory = make_session_factory(engine)
    install_problem_handlers(app)
    app.include_router(routes_processes.router)
    app.include_router(routes_data.router)
    app.include_router(routes_tiles.router)
    app.include_router(routes_features.router)
    app.include_router(routes_viewer.router)  # the web page /viewer/ (static files)
    _add_problem_schema(app)
    return app


def _add_problem_schema(app: FastAPI) -> None:
    """Make sure `#/components/schemas/Problem` is in the OpenAPI document (the routes'
    problem responses refer to it)."""
    original = app.openapi

    def openapi() -> dict:
        """The OpenAPI document, with the Problem schema."""
        if app.openapi_schema is None:
            doc = original()
            doc.setdefault("components", {}).setdefault("schemas", {})["Problem"] = (
                Problem.model_json_schema()
            )
            app.openapi_schema = doc
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]

"""`citytherm serve --host H --port P`: the HTTP API (`services.api`) under uvicorn.

Settings come from the environment (`CITYTHERM_*`, `db/settings.py`), read once here and
passed to the app factory.
"""

from __future__ import annotations

import typer

from db.settings import get_settings


def serve(
    host: str = typer.Option("127.0.0.1", "--host", help="Address to listen on."),
    port: int = typer.Option(8000, "--port", min=1, max=65535, help="TCP port."),
    workers: int = typer.Option(1, "--workers", min=1, help="uvicorn worker processes."),
    log_level: str = typer.Option("info", "--log-level", help="uvicorn log level."),
) -> None:
    """Serve the HTTP API (OpenAPI at /openapi.json, documentation at /docs)."""
    import uvicorn

    if workers > 1:  # each worker process builds its app from the environment
        uvicorn.run(
            "services.api.app:create_app",
            factory=True,
            host=host,
            port=port,
            workers=workers,
            log_level=log_level,
        )
        return
    from services.api import create_app

    uvicorn.run(create_app(get_settings()), host=host, port=port, log_level=log_level)


def register(root: typer.Typer) -> None:
    """Add `serve` to the root app."""
    root.command("serve")(serve)

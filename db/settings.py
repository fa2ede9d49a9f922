"""Configuration: one typed settings object from environment variables (prefix `CITYTHERM_`).

It lives at the bottom of the service layers (`db/`), so that every entry point (CLI command,
API app factory, Celery app) reads it without importing upward. Created once by the entry point
and passed in; never read at import time. Defaults work on one machine with PostgreSQL on 5432
and Redis on 6379.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """citytherm settings (environment variables `CITYTHERM_<NAME>`)."""

    model_config = SettingsConfigDict(env_prefix="CITYTHERM_", extra="ignore")

    database_url: str = Field(
        "postgresql+psycopg://postgres@127.0.0.1:5432/citytherm",
        description="SQLAlchemy URL of the PostGIS city model database.",
    )
    database_pool_size: int = Field(
        20,
        ge=1,
        le=1000,
        description="Database connections a process keeps open (the API serves this many requests at "
        "once without opening new connections, each of which costs tens of ms to set up).",
    )
    database_max_overflow: int = Field(
        10, ge=0, le=1000, description="Extra database connections a process may open under load."
    )
    redis_url: str = Field("redis://127.0.0.1:6379/0", description="Celery broker and result backend.")
    storage_dir: Path = Field(Path("./citytherm-data"), description="Uploaded packages and job results.")
    max_package_bytes: int = Field(20 * 1024**3, description="Largest expanded size of a sequence archive.")
    max_package_members: int = Field(200_000, description="Most members in a sequence archive.")
    database_srid: int = Field(
        25832,
        description="EPSG code of every geometry column, set when the schema is created "
        "(`citytherm db upgrade`); models in another CRS are transformed on import.",
    )
    # the service (docs/service.md)
    api_read_open: bool = Field(False, description="GET requests need no API key.")
    api_key_cache_s: float = Field(
        5.0,
        ge=0,
        le=300,
        description="Seconds an API process keeps an authenticated key's scopes without asking the "
        "database again (0: ask every request); a revoked key is refused within this time.",
    )
    max_upload_bytes: int = Field(20 * 1024**3, description="Largest CityGML upload or sequence upload.")
    min_free_bytes: int = Field(
        1024**3, description="Uploads are refused (507) when the storage would keep less free space."
    )
    upload_ttl_s: float = Field(24 * 3600.0, description="Open uploads idle longer are removed.")
    unit_timeout_s: float = Field(
        3600.0, description="A unit running longer is re-queued by the sweeper (and its task time limit)."
    )
    sweep_interval_s: float = Field(30.0, description="How often the sweeper runs.")
    task_max_retries: int = Field(5, description="Retries of a task after a transient error.")
    worker_concurrency: int = Field(1, description="Processes per worker (`citytherm worker`).")
    worker_threads: int | None = Field(
        None, description="Library threads per worker process (None: cores // concurrency; 0: no cap)."
    )


def get_settings() -> Settings:
    """A fresh `Settings` read from the environment."""
    return Settings()

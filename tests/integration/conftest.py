"""Integration fixtures: a real PostgreSQL + PostGIS test database and a real Redis db number.

The test database is `citytherm_test` (override with `CITYTHERM_TEST_DATABASE`), created fresh
per session on the server at `CITYTHERM_TEST_PG` (default `postgresql://postgres@127.0.0.1:5432`);
Redis db 15 at `CITYTHERM_TEST_REDIS` (default `redis://127.0.0.1:6379/15`).
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import psycopg
import pytest

PG_SERVER = os.environ.get("CITYTHERM_TEST_PG", "postgresql://postgres@127.0.0.1:5432")
TEST_DB = os.environ.get("CITYTHERM_TEST_DATABASE", "citytherm_test")
REDIS_URL = os.environ.get("CITYTHERM_TEST_REDIS", "redis://127.0.0.1:6379/15")


def _admin_conn() -> psycopg.Connection:
    return psycopg.connect(f"{PG_SERVER}/postgres", autocommit=True)


@pytest.fixture(scope="session")
def pg_test_db() -> Iterator[str]:
    """Create an empty `citytherm_test` database with PostGIS; yield its psycopg URL; drop it after."""
    with _admin_conn() as conn:
        conn.execute(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s", (TEST_DB,)
        )
        conn.execute(f'DROP DATABASE IF EXISTS "{TEST_DB}"')
        conn.execute(f'CREATE DATABASE "{TEST_DB}"')
    url = f"{PG_SERVER}/{TEST_DB}"
    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute("CREATE EXTENSION IF NOT EXISTS postgis")
    yield url
    with _admin_conn() as conn:
        conn.execute(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s", (TEST_DB,)
        )
        conn.execute(f'DROP DATABASE IF EXISTS "{TEST_DB}"')


@pytest.fixture(scope="session")
def redis_url() -> str:
    """URL of the test Redis database (db 15), flushed before use."""
    import redis

    client = redis.Redis.from_url(REDIS_URL)
    client.flushdb()
    return REDIS_URL


@pytest.fixture(scope="session")
def migrated_db(pg_test_db: str) -> str:
    """`pg_test_db` upgraded to the newest schema revision (Alembic); yields the same URL."""
    from db.migrations import upgrade

    upgrade(pg_test_db)
    return pg_test_db


@pytest.fixture(scope="session")
def db_engine(migrated_db: str) -> Iterator[object]:
    """A SQLAlchemy engine (psycopg 3) on the migrated test database."""
    from db.session import make_engine

    engine = make_engine(migrated_db)
    yield engine
    engine.dispose()

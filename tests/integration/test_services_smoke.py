"""Smoke test: CI provisions a real PostgreSQL with PostGIS and a real Redis."""

from __future__ import annotations

import psycopg
import pytest
import redis

pytestmark = pytest.mark.integration


def test_postgis_is_available(pg_test_db: str) -> None:
    with psycopg.connect(pg_test_db) as conn:
        version = conn.execute("SELECT postgis_full_version()").fetchone()[0]
        assert "POSTGIS=" in version
        wkt = conn.execute(
            "SELECT ST_AsText(ST_Transform(ST_SetSRID(ST_MakePoint(691000, 5334000), 25832), 4326))"
        ).fetchone()[0]
        assert wkt.startswith("POINT(11.")


def test_redis_answers(redis_url: str) -> None:
    client = redis.Redis.from_url(redis_url)
    assert client.ping() is True
    client.set("citytherm:smoke", "1")
    assert client.get("citytherm:smoke") == b"1"

"""Low-level helpers of the database layer: id reservation, COPY through psycopg, deleting a
city model, dropping and rebuilding the spatial indexes around big loads.

In: a SQLAlchemy `Connection` inside a transaction (the caller's unit of work). Out: rows written.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from sqlalchemy import Connection, Engine, text

__all__ = [
    "SPATIAL_INDEXES",
    "copy_rows",
    "create_spatial_indexes",
    "delete_model",
    "drop_spatial_indexes",
    "reserve_ids",
]

#: spatial indexes dropped during a deferred-index load and rebuilt afterwards.
SPATIAL_INDEXES: tuple[tuple[str, str, str], ...] = (
    ("ix_building_footprint", "building", "footprint"),
    ("ix_building_envelope", "building", "envelope"),
    ("ix_surface_geometry", "surface", "geometry"),
)


def reserve_ids(conn: Connection, table: str, n: int) -> list[int]:
    """Reserve `n` ids of `table`'s id sequence."""
    if n == 0:
        return []
    rows = conn.exec_driver_sql(
        f"SELECT nextval(pg_get_serial_sequence('{table}', 'id')) FROM generate_series(1, %(n)s)",
        {"n": n},
    ).fetchall()
    return [r[0] for r in rows]


def copy_rows(conn: Connection, table: str, columns: Sequence[str], rows: Iterable[tuple]) -> None:
    """COPY rows into `table` through the connection's psycopg driver connection."""
    raw = conn.connection.driver_connection
    with raw.cursor() as cur, cur.copy(f"COPY {table} ({', '.join(columns)}) FROM STDIN") as cp:
        for r in rows:
            cp.write_row(r)


def drop_spatial_indexes(engine: Engine) -> None:
    with engine.begin() as conn:
        for name, _, _ in SPATIAL_INDEXES:
            conn.exec_driver_sql(f"DROP INDEX IF EXISTS {name}")


def create_spatial_indexes(engine: Engine) -> None:
    with engine.begin() as conn:
        for name, table, column in SPATIAL_INDEXES:
            conn.exec_driver_sql(f"CREATE INDEX IF NOT EXISTS {name} ON {table} USING gist ({column})")


def delete_model(conn: Connection, model_id: int) -> None:
    """Delete a city model and everything that hangs off it (children first, for speed)."""
    p = {"m": model_id}
    conn.execute(
        text(
            "DELETE FROM texture_param tp USING surface_data sd, appearance a "
            "WHERE tp.surface_data_id = sd.id AND sd.appearance_id = a.id AND a.city_model_id = :m"
        ),
        p,
    )
    conn.execute(
        text(
            "DELETE FROM texture_param tp USING surface s WHERE tp.surface_id = s.id AND s.city_model_id = :m"
        ),
        p,
    )
    conn.execute(text("DELETE FROM appearance WHERE city_model_id = :m"), p)
    conn.execute(text("DELETE FROM job WHERE city_model_id = :m"), p)
    conn.execute(text("DELETE FROM surface WHERE city_model_id = :m"), p)
    conn.execute(text("UPDATE building SET parent_id = NULL, root_id = NULL WHERE city_model_id = :m"), p)
    conn.execute(text("DELETE FROM building WHERE city_model_id = :m"), p)
    conn.execute(text("DELETE FROM city_model WHERE id = :m"), p)

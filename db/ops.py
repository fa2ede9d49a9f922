"""Low-level helpers of the database layer: id reservation, COPY through psycopg, deleting a
city model, dropping and rebuilding the spatial indexes around big loads.

In: a SQLAlchemy `Connection` inside a transaction (the caller's unit of work). Out: rows written.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from sqlalchemy import Connection, Engine, text

__all__ = [
    "SPATIAL_INDEXES",
    "copy_block",
    "copy_field",
    "copy_rows",
    "copy_text",
    "create_spatial_indexes",
    "delete_model",
    "drop_spatial_indexes",
    "pg_bool_array",
    "pg_float_array",
    "pg_text_array",
    "reserve_ids",
]

#: spatial indexes dropped during a deferred-index load and rebuilt afterwards.
SPATIAL_INDEXES: tuple[tuple[str, str, str], ...] = (
    ("ix_building_footprint", "building", "footprint"),
    ("ix_building_envelope", "building", "envelope"),
    ("ix_surface_geometry", "surface", "geometry"),
)


def reserve_ids(conn: Connection, table: str, n: int) -> list[int]:
    """Reserve `n` ids of `table`'s id sequence (one round trip; safe with concurrent inserts)."""
    if n == 0:
        return []
    ids = conn.exec_driver_sql(
        f"SELECT array_agg(nextval(pg_get_serial_sequence('{table}', 'id'))) FROM generate_series(1, %(n)s)",
        {"n": n},
    ).scalar_one()
    return list(ids)


def _esc(s: str) -> str:
    """Escape a string for COPY text format."""
    if "\\" in s:
        s = s.replace("\\", "\\\\")
    if "\t" in s or "\n" in s or "\r" in s:
        s = s.replace("\t", "\\t").replace("\n", "\\n").replace("\r", "\\r")
    return s


def copy_field(v: object) -> str:
    """One value -> COPY text field (None, bool, int, float, str; other types via str())."""
    if v is None:
        return "\\N"
    t = type(v)
    if t is str:
        return _esc(v)  # type: ignore[arg-type]
    if t is bool:
        return "t" if v else "f"
    if t is float:
        return repr(v) if v == v else "NaN"  # type: ignore[comparator-overlap]
    return _esc(str(v))


def pg_text_array(values: Sequence[str]) -> str:
    """A `text[]` literal with every element quoted (safe for any characters).

    >>> pg_text_array(['a', 'b"c'])
    '{"a","b\\\\"c"}'
    """
    joined = '","'.join(values)
    if "\\" not in joined and '"' not in "".join(values):
        return '{"' + joined + '"}' if values else "{}"
    return "{" + ",".join('"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"' for v in values) + "}"


_BOOL_ARRAYS = {(True,): "{t}", (False,): "{f}"}


def pg_bool_array(values: Sequence[bool]) -> str:
    """A `boolean[]` literal."""
    if len(values) == 1:
        return _BOOL_ARRAYS[(bool(values[0]),)]
    return "{" + ",".join("t" if v else "f" for v in values) + "}"


def pg_float_array(values: Sequence[float]) -> str:
    """A `float8[]` literal (shortest round-trip decimals; NaN as NaN)."""
    return "{" + ",".join(repr(float(v)) if v == v else "NaN" for v in values) + "}"


def copy_text(
    conn: Connection,
    table: str,
    columns: Sequence[str],
    rows: Iterable[Sequence[object]],
    chunk: int = 1 << 20,
) -> None:
    """COPY rows of plain values (None, bool, int, float, str; arrays and JSON pre-formatted as
    strings, geometry as hex EWKB) into `table`, formatted here in bulk: faster than per-row
    adaptation for big loads."""
    raw = conn.connection.driver_connection
    with raw.cursor() as cur, cur.copy(f"COPY {table} ({', '.join(columns)}) FROM STDIN") as cp:
        buf: list[str] = []
        size = 0
        for r in rows:
            line = "\t".join([copy_field(v) for v in r]) + "\n"
            buf.append(line)
            size += len(line)
            if size >= chunk:
                cp.write("".join(buf))
                buf.clear()
                size = 0
        if buf:
            cp.write("".join(buf))


def copy_rows(conn: Connection, table: str, columns: Sequence[str], rows: Iterable[tuple]) -> None:
    """COPY rows into `table` through the connection's psycopg driver connection."""
    raw = conn.connection.driver_connection
    with raw.cursor() as cur, cur.copy(f"COPY {table} ({', '.join(columns)}) FROM STDIN") as cp:
        for r in rows:
            cp.write_row(r)


def copy_block(conn: Connection, table: str, columns: Sequence[str], lines: Sequence[str]) -> None:
    """COPY ready-made text lines (tab-separated fields, each line ending in a newline)."""
    raw = conn.connection.driver_connection
    with raw.cursor() as cur, cur.copy(f"COPY {table} ({', '.join(columns)}) FROM STDIN") as cp:
        step = 2000
        for i in range(0, len(lines), step):
            cp.write("".join(lines[i : i + step]))


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

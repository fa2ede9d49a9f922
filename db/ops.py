"""Low-level helpers of the database layer: id reservation, COPY through psycopg, deleting a
city model; the import's advisory locks, removing models left `importing` by dead imports, and
checking (repairing) the shared spatial indexes.

In: a SQLAlchemy `Connection` inside a transaction (the caller's unit of work), or an `Engine` for
the repairs. Out: rows written, or what a repair did.

SQLAlchemy is imported where it is used: the COPY text helpers also run in the importer's reader
process, which should start fast.

Import locks (`pg_advisory_*` with two keys): an import holds `(IMPORT_NAME_LOCK, hashtext(name))`
for its transaction, so two imports of one name never wait on each other (the second is refused),
and `(IMPORT_MODEL_LOCK, model id)` while it writes that model. A `city_model` row in state
`importing` whose model lock nobody holds belongs to an import that died: `remove_dead_imports`
deletes it.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sqlalchemy import Connection, Engine

__all__ = [
    "IMPORT_MODEL_LOCK",
    "IMPORT_NAME_LOCK",
    "SPATIAL_INDEXES",
    "DeadImport",
    "IndexRepair",
    "copy_block",
    "copy_field",
    "copy_rows",
    "copy_text",
    "delete_model",
    "ensure_spatial_indexes",
    "pg_bool_array",
    "pg_float_array",
    "pg_text_array",
    "remove_dead_imports",
    "reserve_ids",
    "running_imports",
    "spatial_index_problems",
]

#: the shared GiST indexes (name, table, column): never dropped by an import.
SPATIAL_INDEXES: tuple[tuple[str, str, str], ...] = (
    ("ix_building_footprint", "building", "footprint"),
    ("ix_building_envelope", "building", "envelope"),
    ("ix_surface_geometry", "surface", "geometry"),
)
#: first key of the advisory lock on a model name being imported (second key: hashtext(name)).
IMPORT_NAME_LOCK = 0x43540001
#: first key of the advisory lock on a model being written (second key: its id).
IMPORT_MODEL_LOCK = 0x43540002


def _text(sql: str):  # sqlalchemy's TextClause (imported lazily)
    from sqlalchemy import text

    return text(sql)


def reserve_ids(conn: Connection, table: str, n: int) -> list[int]:
    """Reserve `n` ids of `table`'s id sequence (one round trip; safe with concurrent inserts)."""
    if n == 0:
        return []
    # the sequence is looked up once (an InitPlan), not per id: pg_get_serial_sequence scans the
    # catalogs on every call
    ids = conn.exec_driver_sql(
        f"SELECT array_agg(nextval((SELECT pg_get_serial_sequence('{table}', 'id')::regclass))) "
        "FROM generate_series(1, %(n)s)",
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


def delete_model(conn: Connection, model_id: int) -> None:
    """Delete a city model and everything that hangs off it (children first, for speed)."""
    p = {"m": model_id}
    conn.execute(
        _text(
            "DELETE FROM texture_param tp USING surface_data sd, appearance a "
            "WHERE tp.surface_data_id = sd.id AND sd.appearance_id = a.id AND a.city_model_id = :m"
        ),
        p,
    )
    conn.execute(
        _text(
            "DELETE FROM texture_param tp USING surface s WHERE tp.surface_id = s.id AND s.city_model_id = :m"
        ),
        p,
    )
    conn.execute(_text("DELETE FROM appearance WHERE city_model_id = :m"), p)
    conn.execute(_text("DELETE FROM job WHERE city_model_id = :m"), p)
    conn.execute(_text("DELETE FROM surface WHERE city_model_id = :m"), p)
    conn.execute(_text("UPDATE building SET parent_id = NULL, root_id = NULL WHERE city_model_id = :m"), p)
    conn.execute(_text("DELETE FROM building WHERE city_model_id = :m"), p)
    conn.execute(_text("DELETE FROM city_model WHERE id = :m"), p)


@dataclass(frozen=True)
class DeadImport:
    """A `city_model` row found in state `importing` by `remove_dead_imports`.

    `status` is "removed", "dead" (found dead, left alone: dry run) or "in progress" (its import's
    session still holds the model lock: left alone)."""

    model_id: int
    name: str
    buildings: int
    parts: int
    surfaces: int
    status: str


def remove_dead_imports(engine: Engine, *, dry_run: bool = False) -> list[DeadImport]:
    """Delete every model in state `importing` whose import is dead (nobody holds its model lock),
    each in its own transaction; report all models found `importing`."""
    found: list[DeadImport] = []
    with engine.connect() as conn:
        rows = conn.execute(
            _text("SELECT id, name FROM city_model WHERE state = 'importing' ORDER BY id")
        ).all()
        conn.commit()
        for model_id, name in rows:
            key = {"ns": IMPORT_MODEL_LOCK, "m": model_id}
            if not conn.execute(_text("SELECT pg_try_advisory_lock(:ns, :m)"), key).scalar_one():
                conn.commit()
                found.append(DeadImport(model_id, name, 0, 0, 0, "in progress"))
                continue
            try:
                # still importing (not finished meanwhile)? lock the row for the delete
                still = conn.execute(
                    _text("SELECT 1 FROM city_model WHERE id = :m AND state = 'importing' FOR UPDATE"), key
                ).first()
                if still is None:
                    conn.rollback()
                    continue
                b, p = conn.execute(
                    _text(
                        "SELECT count(*) FILTER (WHERE NOT is_part), count(*) FILTER (WHERE is_part) "
                        "FROM building WHERE city_model_id = :m"
                    ),
                    key,
                ).one()
                s = conn.execute(
                    _text("SELECT count(*) FROM surface WHERE city_model_id = :m"), key
                ).scalar_one()
                if dry_run:
                    conn.rollback()
                else:
                    delete_model(conn, model_id)
                    conn.commit()
                found.append(DeadImport(model_id, name, b, p, s, "dead" if dry_run else "removed"))
            finally:
                if conn.in_transaction():
                    conn.rollback()
                conn.execute(_text("SELECT pg_advisory_unlock(:ns, :m)"), key)
                conn.commit()
    return found


def running_imports(engine: Engine) -> list[tuple[int, str, str, object]]:
    """(backend pid, model name, state, transaction start) of the imports running now (their
    sessions name themselves `citytherm import <name>`)."""
    with engine.connect() as conn:
        rows = conn.execute(
            _text(
                "SELECT pid, substr(application_name, 18), state, xact_start FROM pg_stat_activity "
                "WHERE datname = current_database() AND application_name LIKE 'citytherm import %' "
                "ORDER BY xact_start"
            )
        ).all()
    return [tuple(r) for r in rows]


@dataclass(frozen=True)
class IndexRepair:
    """A shared spatial index found `missing` or `invalid` (a failed concurrent build), and whether
    `ensure_spatial_indexes` rebuilt it."""

    name: str
    table: str
    column: str
    problem: str
    rebuilt: bool


def spatial_index_problems(conn: Connection) -> list[tuple[str, str, str, str]]:
    """(name, table, column, "missing" | "invalid") of every spatial index that is not usable."""
    out = []
    for name, table, column in SPATIAL_INDEXES:
        row = conn.execute(
            _text("SELECT indisvalid FROM pg_index WHERE indexrelid = to_regclass(:n)"), {"n": name}
        ).first()
        if row is None or not row[0]:
            out.append((name, table, column, "missing" if row is None else "invalid"))
    return out


def ensure_spatial_indexes(engine: Engine, *, dry_run: bool = False) -> list[IndexRepair]:
    """Rebuild missing or invalid spatial indexes with `CREATE INDEX CONCURRENTLY` (other sessions
    keep reading and writing the tables meanwhile); report what was found."""
    done: list[IndexRepair] = []
    with engine.connect() as conn:
        conn.execution_options(isolation_level="AUTOCOMMIT")
        for name, table, column, problem in spatial_index_problems(conn):
            if not dry_run:
                if problem == "invalid":
                    conn.exec_driver_sql(f"DROP INDEX CONCURRENTLY IF EXISTS {name}")
                conn.exec_driver_sql(
                    f"CREATE INDEX CONCURRENTLY IF NOT EXISTS {name} ON {table} USING gist ({column})"
                )
            done.append(IndexRepair(name, table, column, problem, rebuilt=not dry_run))
    return done

"""SQL of the OGC API - Features service (`features.py`): the SELECT of a page (features built as
JSON text by PostgreSQL, or read where the collection keeps them with its rows), the filter and
bbox conditions, numberMatched, the data's extent, and a small per-process cache (database SRID,
optional columns, extents, counts).

In: a `Collection`, a validated `ItemsQuery`, a `features_db.Db` (one request's connection).
Out: SQL text and bind parameters.
"""

from __future__ import annotations

import functools
import re
import threading
import time
from typing import Any

from sqlalchemy import Engine

from db.feature_json import feature_expression, feature_lateral, feature_spec
from db.srid import database_srid
from services.api.features_collections import COLLECTIONS, Collection
from services.api.features_db import Db, engine_key
from services.api.features_params import Crs, ItemsQuery

__all__ = [
    "COUNT_CAP",
    "COUNT_TTL_S",
    "count_matched",
    "data_extent",
    "database_srid_cached",
    "feature_lateral",
    "feature_select",
    "features_by_key_sql",
    "page_sql",
    "properties",
    "rows_from",
    "stored_spec",
    "stored_text_ready",
    "where_clause",
]

COUNT_CAP = 1_000_000
COUNT_TTL_S = 30.0
_TTL_S = 30.0


class _Cache:
    """A small per-process cache with expiry (database SRID, optional columns, extents, counts)."""

    def __init__(self) -> None:
        self._data: dict[tuple[Any, ...], tuple[float, Any]] = {}
        self._lock = threading.Lock()

    def get(self, key: tuple[Any, ...], ttl: float) -> Any | None:
        """The value of `key` if stored less than `ttl` seconds ago, else None."""
        with self._lock:
            hit = self._data.get(key)
        return hit[1] if hit is not None and time.monotonic() - hit[0] < ttl else None

    def put(self, key: tuple[Any, ...], value: Any) -> Any:
        """Store `value` under `key`; returns it."""
        with self._lock:
            if len(self._data) > 10_000:
                self._data.clear()
            self._data[key] = (time.monotonic(), value)
        return value


_cache = _Cache()


def database_srid_cached(engine: Engine) -> int:
    """The database SRID (`db.srid.database_srid`), cached an hour per database URL (a short
    connection the first time)."""
    key = ("srid", engine_key(engine))
    hit = _cache.get(key, 3600.0)
    if hit is not None:
        return hit
    with engine.connect() as conn:
        return _cache.put(key, database_srid(conn))


def properties(db: Db, c: Collection) -> tuple[tuple[str, str], ...]:
    """The collection's properties, with its optional ones whose column exists."""
    if not c.optional:
        return c.properties
    have = _columns(db, c)
    return c.properties + tuple((n, e) for n, e, t, col in c.optional if (t, col) in have)


def stored_text_ready(db: Db, c: Collection) -> bool:
    """Whether the schema has the columns of the collection's stored feature texts."""
    st = c.stored_text
    return st is not None and {(st.table, st.text), (st.table, st.spec)} <= _columns(db, c)


def _columns(db: Db, c: Collection) -> frozenset[tuple[str, str]]:
    """(table, column) of the tables of the collection's optional properties and stored texts
    that the schema has (kept `_TTL_S` seconds)."""
    key = ("columns", db.key, c.id)
    have = _cache.get(key, _TTL_S)
    if have is None:
        tables = {o[2] for o in c.optional} | ({c.stored_text.table} if c.stored_text else set())
        rows = db.rows(
            "SELECT table_name, column_name FROM information_schema.columns "
            "WHERE table_schema = current_schema() AND table_name = ANY(:t)",
            {"t": sorted(tables)},
        )
        have = _cache.put(key, frozenset((r[0], r[1]) for r in rows))
    return have


def data_extent(db: Db, srid: int) -> dict[str, list[float]] | None:
    """Extent of the complete city models: `storage` (x0, y0, z0, x1, y1, z1, database SRID) and
    `crs84` (lon0, lat0, lon1, lat1); None without a model."""
    key = ("extent", db.key)
    hit = _cache.get(key, _TTL_S)
    if hit is not None:
        return hit or None
    row = db.first(
        (
            "WITH x AS (SELECT ST_3DExtent(envelope) AS e FROM city_model WHERE state = 'complete'), "
            "g AS (SELECT e, ST_Transform(ST_Segmentize(ST_SetSRID(e::box2d::geometry, CAST(:s AS int)), "
            "GREATEST(ST_XMax(e) - ST_XMin(e), ST_YMax(e) - ST_YMin(e), 1) / 16), 4326) AS w "
            "FROM x WHERE e IS NOT NULL) "
            "SELECT ST_XMin(e), ST_YMin(e), ST_ZMin(e), ST_XMax(e), ST_YMax(e), ST_ZMax(e), "
            "ST_XMin(w), ST_YMin(w), ST_XMax(w), ST_YMax(w) FROM g"
        ),
        {"s": srid},
    )
    if row is None:
        _cache.put(key, {})
        return None
    vals = [float(v) for v in row]
    return _cache.put(key, {"storage": vals[:6], "crs84": vals[6:]})


def feature_select(c: Collection, props: tuple[tuple[str, str], ...], crs: Crs) -> str:
    """The SELECT list: the key (`k`) and the feature as JSON text (`f`, `db.feature_json`; the
    properties are the columns of the lateral subquery `feature_lateral`, to follow the FROM
    clause)."""
    return f"{c.key} AS k, {feature_expression(c.key, c.key_kind, c.geometry, crs.geographic)} AS f"


def stored_spec(c: Collection, props: tuple[tuple[str, str], ...]) -> int:
    """The spec a feature text kept with a row of `c` has when it was written by the same
    definition as `feature_select` in CRS84 with `props` (`db.feature_json.feature_spec`)."""
    return _stored_spec(c.id, props)


@functools.lru_cache(maxsize=64)
def _stored_spec(collection_id: str, props: tuple[tuple[str, str], ...]) -> int:
    c = COLLECTIONS[collection_id]
    return feature_spec(feature_expression(c.key, c.key_kind, c.geometry, True), props)


def rows_from(c: Collection, from_sql: str, where: str) -> str:
    """The FROM clause of a query of `c`'s rows meeting `where` that writes no feature (a count,
    a page of stored texts): the lean one when `c` has one (`Collection.lean`), else `from_sql`."""
    return c.lean.for_condition(where) if c.lean is not None else from_sql


def page_sql(
    c: Collection,
    props: tuple[tuple[str, str], ...],
    crs: Crs,
    from_sql: str,
    where: str,
    forward: bool,
    limit: int,
    stored: bool = False,
) -> str:
    """The SELECT of a page: (key, feature JSON text) of `limit + 1` features in key order
    (`forward`: ascending, else descending; the one more tells whether there are more). Made
    once per distinct page query (cached).

    `stored` (the collection keeps its features' texts, the schema has them, `crs` is CRS84 or
    CRS84h: the texts are CRS84, written by the same SQL): the page reads the texts over the lean
    FROM clause (`rows_from`); the text of a row whose spec is not the one of `props` (written by
    another definition, or none) comes back NULL, and `features_by_key_sql` writes those.

    (Aggregating the page into one row in PostgreSQL, `string_agg` over a window, was tried: it
    costs PostgreSQL more CPU than the rows cost psycopg to fetch, `docs/features.md`.)"""
    st = c.stored_text if stored and crs.geographic else None
    return _page_sql(c.id, props, crs, from_sql, where, forward, limit, st is not None)


@functools.lru_cache(maxsize=1024)
def _page_sql(
    collection_id: str,
    props: tuple[tuple[str, str], ...],
    crs: Crs,
    from_sql: str,
    where: str,
    forward: bool,
    limit: int,
    stored: bool,
) -> str:
    c = COLLECTIONS[collection_id]
    order = f"ORDER BY {c.key} {'ASC' if forward else 'DESC'} LIMIT {limit + 1}"
    if stored:
        assert c.stored_text is not None
        t, s = c.stored_text, stored_spec(c, props)
        feature = f"CASE WHEN {t.alias}.{t.spec} = {s} THEN {t.alias}.{t.text} END"
        select, from_sql = f"{c.key} AS k, {feature} AS f", rows_from(c, from_sql, where)
    else:
        select, from_sql = feature_select(c, props, crs), from_sql + feature_lateral(props)
    return f"SELECT {select} FROM {from_sql} WHERE {where} {order}"


def features_by_key_sql(c: Collection, props: tuple[tuple[str, str], ...], crs: Crs) -> str:
    """The SELECT of (key, feature JSON text) of the features whose keys are in `:keys` (an
    array), in `crs`, written by PostgreSQL (binds: `keys`, `srid`)."""
    return _features_by_key_sql(c.id, props, crs)


@functools.lru_cache(maxsize=64)
def _features_by_key_sql(collection_id: str, props: tuple[tuple[str, str], ...], crs: Crs) -> str:
    c = COLLECTIONS[collection_id]
    from_sql = c.from_sql.format(**{s: "" for s in c.slots})
    return (
        f"SELECT {feature_select(c, props, crs)} FROM {from_sql}{feature_lateral(props)} "
        f"WHERE ({c.where}) AND {c.key} = ANY(:keys)"
    )


def where_clause(c: Collection, q: ItemsQuery, db: Db, srid: int) -> tuple[str, str, dict[str, Any]]:
    """(FROM clause with its slots filled, WHERE condition, bind parameters) of the query's
    filters and bbox (not the cursor)."""
    params: dict[str, Any] = {"srid": srid}
    conds = [c.where]
    slots: dict[str, list[str]] = {s: [] for s in c.slots}
    for name, value in q.filters.items():
        f = c.filter(name)
        assert f is not None
        params[name] = value
        (slots[f.slot] if f.slot != "where" else conds).append(f.sql)
        if name in c.required:
            conds.append(c.required[name])
    if q.bbox is not None:
        conds.append(_bbox_condition(c, q, db, srid, params))
    from_sql = c.from_sql.format(**{s: "".join(v) for s, v in slots.items()})
    return from_sql, " AND ".join(f"({x})" for x in conds), params


def _bbox_condition(c: Collection, q: ItemsQuery, db: Db, srid: int, params: dict[str, Any]) -> str:
    """The bbox condition. In the database CRS: `ST_Intersects` with the box. In CRS84: the box,
    clipped to the data's extent (with a margin), transformed densified into the database SRID
    for the index (`&&`), then `ST_Intersects` of the geometry transformed to WGS 84 with the
    lon/lat box (both tests against a rectangle: exact also for vertical walls, whose 2D
    polygons have no area)."""
    assert q.bbox is not None
    x0, y0, x1, y1 = q.bbox
    box = "CAST(:bx0 AS float8), CAST(:by0 AS float8), CAST(:bx1 AS float8), CAST(:by1 AS float8)"
    if q.bbox_crs.geographic:
        extent = data_extent(db, srid)
        if not extent:
            return "FALSE"
        e0, f0, e1, f1 = extent["crs84"]
        m = 0.01
        x0, y0, x1, y1 = max(x0, e0 - m), max(y0, f0 - m), min(x1, e1 + m), min(y1, f1 + m)
        if x0 > x1 or y0 > y1:
            return "FALSE"
        params["bseg"] = max(x1 - x0, y1 - y0, 1e-9) / 32
        dense = f"ST_Segmentize(ST_MakeEnvelope({box}, 4326), CAST(:bseg AS float8))"
        env = f"ST_Transform({dense}, CAST(:srid AS int))"
        test = rf"(\1 && {env} AND ST_Intersects(ST_Transform(\1, 4326), ST_MakeEnvelope({box}, 4326)))"
    else:
        test = rf"ST_Intersects(\1, ST_MakeEnvelope({box}, CAST(:srid AS int)))"
    params.update(bx0=x0, by0=y0, bx1=x1, by1=y1)
    return re.sub(r"INTERSECTS\(([^()]+)\)", test, c.bbox_sql)


def count_matched(
    db: Db, c: Collection, q: ItemsQuery, from_sql: str, where: str, params: dict
) -> int | None:
    """numberMatched of the query (None above `COUNT_CAP`), kept `COUNT_TTL_S` seconds."""
    key = ("count", db.key, q.fingerprint)
    hit = _cache.get(key, COUNT_TTL_S)
    if hit is not None:
        return hit if hit >= 0 else None
    rows = rows_from(c, from_sql, where)
    sql = f"SELECT count(*) FROM (SELECT 1 FROM {rows} WHERE {where} LIMIT {COUNT_CAP}) x"
    row = db.first(sql, params)
    n = row[0] if row else 0
    _cache.put(key, -1 if n >= COUNT_CAP else int(n))
    return None if n >= COUNT_CAP else int(n)

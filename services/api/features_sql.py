"""SQL of the OGC API - Features service (`features.py`): the SELECT of a page (features built as
JSON text by PostgreSQL), the filter and bbox conditions, numberMatched, the data's extent, and a
small per-process cache (database SRID, optional columns, extents, counts).

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
    "page_sql",
    "properties",
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
    key = ("columns", db.key, c.id)
    have = _cache.get(key, _TTL_S)
    if have is None:
        rows = db.rows(
            "SELECT table_name, column_name FROM information_schema.columns "
            "WHERE table_schema = current_schema() AND table_name = ANY(:t)",
            {"t": sorted({o[2] for o in c.optional})},
        )
        have = _cache.put(key, frozenset((r[0], r[1]) for r in rows))
    return c.properties + tuple((n, e) for n, e, t, col in c.optional if (t, col) in have)


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
    """The SELECT list: the key (`k`) and the feature as JSON text (`f`). The properties are
    the columns of the lateral subquery `feature_lateral` (to follow the FROM clause), written
    by `row_to_json` (which looks up its column types once per query, where `json_build_object`
    does for every argument of every row: about a quarter of a page's CPU in PostgreSQL); the
    feature's frame is concatenated text."""
    g = (  # options 0: no `crs` member in each geometry (RFC 7946; the document says its CRS)
        f"ST_AsGeoJSON(ST_Transform({c.geometry}, 4979), 9, 0)"
        if crs.geographic
        else f"ST_AsGeoJSON({c.geometry}, 6, 0)"
    )
    key_json = f"{c.key}::text" if c.key_kind == "int" else f"to_json({c.key}::text)::text"
    head, geometry, properties = (
        _sql_text(t) for t in ('{"type":"Feature","id":', ',"geometry":', ',"properties":')
    )
    return (
        f"{c.key} AS k, {head} || {key_json} || {geometry} || COALESCE({g}, 'null') || {properties} || "
        f"row_to_json({_PROPS})::text || '}}' AS f"
    )


def _sql_text(s: str) -> str:
    """`s` as an SQL string literal."""
    return "'" + s.replace("'", "''") + "'"


_PROPS = "_feature_props"


def feature_lateral(props: tuple[tuple[str, str], ...]) -> str:
    """The lateral subquery of the feature's properties (column name = property name), to
    append to the FROM clause of a `feature_select` query."""
    cols = ", ".join(f'{expr} AS "{name}"' for name, expr in props)
    return f", LATERAL (SELECT {cols}) AS {_PROPS}"


def page_sql(
    c: Collection,
    props: tuple[tuple[str, str], ...],
    crs: Crs,
    from_sql: str,
    where: str,
    forward: bool,
    limit: int,
) -> str:
    """The SELECT of a page: (key, feature JSON text) of `limit + 1` features in key order
    (`forward`: ascending, else descending; the one more tells whether there are more). Made
    once per distinct page query (cached).

    (Aggregating the page into one row in PostgreSQL, `string_agg` over a window, was tried: it
    costs PostgreSQL more CPU than the rows cost psycopg to fetch, `docs/features.md`.)"""
    return _page_sql(c.id, props, crs, from_sql, where, forward, limit)


@functools.lru_cache(maxsize=1024)
def _page_sql(
    collection_id: str,
    props: tuple[tuple[str, str], ...],
    crs: Crs,
    from_sql: str,
    where: str,
    forward: bool,
    limit: int,
) -> str:
    c = COLLECTIONS[collection_id]
    return (
        f"SELECT {feature_select(c, props, crs)} FROM {from_sql}{feature_lateral(props)} "
        f"WHERE {where} ORDER BY {c.key} {'ASC' if forward else 'DESC'} LIMIT {limit + 1}"
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
    sql = f"SELECT count(*) FROM (SELECT 1 FROM {from_sql} WHERE {where} LIMIT {COUNT_CAP}) x"
    row = db.first(sql, params)
    n = row[0] if row else 0
    _cache.put(key, -1 if n >= COUNT_CAP else int(n))
    return None if n >= COUNT_CAP else int(n)

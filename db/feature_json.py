"""SQL that makes PostgreSQL write a GeoJSON Feature as text: the expression of one feature per
row (its id, geometry and properties), shared by the OGC API - Features service
(`services.api.features_sql`) and by the feature texts kept with the rows
(`db.facade_features`), so that both write the same bytes.

In: the feature's key expression and kind ("int" or "uuid"), its geometry expression (in the
database SRID), its properties as (name, SQL expression) pairs, whether the output CRS is CRS84
(`ST_Transform` to EPSG:4979: longitude, latitude in degrees, heights kept; 9 decimals) or the
database CRS (6 decimals). Out: SQL text (no bind parameters) to put in a SELECT list, with
`feature_lateral` appended to its FROM clause.
"""

from __future__ import annotations

import zlib

__all__ = ["PROPS_ALIAS", "feature_expression", "feature_lateral", "feature_spec", "sql_text"]

#: alias of the lateral subquery of the feature's properties
PROPS_ALIAS = "_feature_props"


def sql_text(s: str) -> str:
    """`s` as an SQL string literal.

    >>> sql_text("it's")
    "'it''s'"
    """
    return "'" + s.replace("'", "''") + "'"


def feature_expression(key: str, key_kind: str, geometry: str, geographic: bool) -> str:
    """The feature as JSON text: `{"type":"Feature","id":…,"geometry":…,"properties":…}`. The
    properties are the columns of the lateral subquery `feature_lateral` (to follow the FROM
    clause), written by `row_to_json` (which looks up its column types once per query, where
    `json_build_object` does for every argument of every row: about a quarter of a page's CPU in
    PostgreSQL); the feature's frame is concatenated text. Geometries are RFC 7946 (no `crs`
    member of their own: the document says its CRS); `null` without one."""
    g = (
        f"ST_AsGeoJSON(ST_Transform({geometry}, 4979), 9, 0)"
        if geographic
        else f"ST_AsGeoJSON({geometry}, 6, 0)"
    )
    key_json = f"{key}::text" if key_kind == "int" else f"to_json({key}::text)::text"
    head, geom, props = (
        sql_text(t) for t in ('{"type":"Feature","id":', ',"geometry":', ',"properties":')
    )
    return (
        f"{head} || {key_json} || {geom} || COALESCE({g}, 'null') || {props} || "
        f"row_to_json({PROPS_ALIAS})::text || '}}'"
    )


def feature_lateral(props: tuple[tuple[str, str], ...]) -> str:
    """The lateral subquery of the feature's properties (column name = property name), to
    append to the FROM clause of a query with a `feature_expression`."""
    cols = ", ".join(f'{expr} AS "{name}"' for name, expr in props)
    return f", LATERAL (SELECT {cols}) AS {PROPS_ALIAS}"


def feature_spec(expression: str, props: tuple[tuple[str, str], ...]) -> int:
    """A 31-bit fingerprint of a feature definition (its expression and properties): kept next
    to a stored feature text, it tells whether the text was written by the same definition."""
    return zlib.crc32((expression + "\n" + feature_lateral(props)).encode()) & 0x7FFFFFFF

"""The facade features (one per `surface_thermal` row: a surface's thermal figures of one job
appearance) as SQL, and their GeoJSON text kept with the row (`surface_thermal.feature`,
migration 0012), so that a page of the OGC API - Features `facades` collection in CRS84 (the
default) is read, not written, by PostgreSQL (`docs/features.md`).

In: a SQLAlchemy `Connection` and a condition on `st` (the `surface_thermal` rows to write).
Out: `surface_thermal.feature` (the Feature as JSON text, as `db.feature_json` writes it in CRS84,
byte for byte what the service would write) and `surface_thermal.feature_spec` (the fingerprint
of the definition that wrote it, `db.feature_json.feature_spec`: the service uses a text only
when it matches its own definition, else writes the feature itself).

A text depends on its `surface_thermal` row and on rows written before it and not changed after
(the surface, its buildings, the appearance, the model's name, the texture parameters of the
surface in the appearance: `db.store` writes all of them before the statistics, in the same
transaction, and deletes the statistics with the appearance). Whoever writes or changes
`surface_thermal` rows writes their texts (`write_feature_texts`) in the same transaction.
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import Connection, text

from db.feature_json import feature_expression, feature_lateral, feature_spec

__all__ = [
    "FACADE_FIGURE_COLUMNS",
    "GEOMETRY",
    "JOINS",
    "KEY",
    "OPTIONAL",
    "PROPERTIES",
    "TABLE",
    "stored_expression",
    "stored_properties",
    "stored_spec",
    "write_feature_texts",
]

#: the main table and the feature id
TABLE = "surface_thermal st"
KEY = "st.id"
#: the joins of a facade's rows, (alias, JOIN clause), each after those it refers to; every one
#: finds exactly one row (not-null foreign keys), so leaving out one no condition needs keeps
#: the same rows
JOINS: tuple[tuple[str, str], ...] = (
    ("a", "JOIN appearance a ON a.id = st.appearance_id"),
    ("s", "JOIN surface s ON s.id = st.surface_id"),
    ("b", "JOIN building b ON b.id = s.building_id"),
    ("rb", "JOIN building rb ON rb.id = COALESCE(b.root_id, b.id)"),
    ("cm", "JOIN city_model cm ON cm.id = s.city_model_id"),
)
#: the polygon, in the database SRID
GEOMETRY = "s.geometry"
PROPERTIES: tuple[tuple[str, str], ...] = (
    ("building", "rb.gml_id"),
    ("owner", "b.gml_id"),
    ("surface_gml_id", "s.gml_id"),
    ("class", "s.surface_class"),
    ("lod", "s.lod"),
    ("model", "cm.name"),
    ("model_id", "cm.id"),
    ("theme", "a.theme"),
    ("job", "a.job_id::text"),
    (
        "textured",
        # a scalar subquery with LIMIT: an index lookup per feature of the page (an EXISTS may be
        # planned as a hashed scan of all of texture_param)
        "(SELECT TRUE FROM texture_param tp JOIN surface_data sd ON sd.id = tp.surface_data_id "
        "WHERE tp.surface_id = s.id AND sd.appearance_id = a.id LIMIT 1) IS NOT NULL",
    ),
    ("observed_share", "st.observed_share"),
    ("texels_observed", "st.texels_observed"),
    ("texels_total", "st.texels_total"),
    ("resolution_m", "st.resolution_m"),
    ("best_resolution_m", "st.best_resolution_m"),
    ("view_angle_deg", "st.view_angle_deg"),
    ("mean_k", "st.mean_k"),
    ("median_k", "st.median_k"),
    ("std_k", "st.std_k"),
    ("min_k", "st.min_k"),
    ("max_k", "st.max_k"),
    ("p05_k", "st.p05_k"),
    ("p95_k", "st.p95_k"),
    ("area_m2", "s.area_m2"),
)
#: the thermal analysis' figures of a surface (`surface_thermal`, migration 0010; written by
#: `db.store`)
FACADE_FIGURE_COLUMNS = (
    "typical_k",
    "spread_k",
    "hot_share",
    "window_share",
    "heat_loss_index",
    "windows",
    "leaks",
)
#: properties of columns a schema may lack (migration 0010): (name, SQL, table, column)
OPTIONAL: tuple[tuple[str, str, str, str], ...] = tuple(
    (name, f"st.{name}", "surface_thermal", name) for name in FACADE_FIGURE_COLUMNS
)


def stored_properties(present: frozenset[tuple[str, str]] | None = None) -> tuple[tuple[str, str], ...]:
    """The properties of a facade: `PROPERTIES` and those of `OPTIONAL` whose (table, column) is
    in `present` (None: all of them, the schema of `db.models`)."""
    return PROPERTIES + tuple(
        (name, expr) for name, expr, table, col in OPTIONAL if present is None or (table, col) in present
    )


def stored_expression() -> str:
    """The SQL of a facade's Feature text in CRS84 (needs `feature_lateral` in the FROM)."""
    return feature_expression(KEY, "int", GEOMETRY, geographic=True)


def stored_spec(props: tuple[tuple[str, str], ...]) -> int:
    """The fingerprint of the stored text's definition with properties `props`."""
    return feature_spec(stored_expression(), props)


def _present_columns(conn: Connection) -> frozenset[tuple[str, str]]:
    rows = conn.execute(
        text(
            "SELECT table_name, column_name FROM information_schema.columns "
            "WHERE table_schema = current_schema() AND table_name = ANY(:t)"
        ),
        {"t": sorted({o[2] for o in OPTIONAL})},
    ).all()
    return frozenset((r[0], r[1]) for r in rows)


def write_feature_texts(
    conn: Connection, where: str, params: dict[str, Any] | None = None, *, all_columns: bool = True
) -> int:
    """Write the Feature text and its spec of the `surface_thermal` rows (alias `st`) that meet
    the SQL condition `where` (binds from `params`); returns their number. `all_columns` False:
    the properties of the schema as it is (a migration's), else those of `db.models`."""
    props = stored_properties(None if all_columns else _present_columns(conn))
    joins = "\n".join(clause for _, clause in JOINS)
    sql = (
        f"UPDATE surface_thermal u SET feature = x.f, feature_spec = {stored_spec(props)} FROM ("
        f"SELECT {KEY} AS k, {stored_expression()} AS f FROM {TABLE}\n{joins}{feature_lateral(props)} "
        f"WHERE {where}) x WHERE u.id = x.k"
    )
    return int(conn.execute(text(sql), params or {}).rowcount)

"""`building_thermal` gets the building attributes a GIS filters on as typed columns, beside the
whole attribute document: `measured_height_m` (float8), `function` (text; the first of several),
`year_of_construction` (int, the year of a date), `roof_type` (text, the code list value),
`storeys_above_ground` (int), `attributes` (jsonb). Values that do not read as their type are
NULL (the JSONB keeps them as written). Appended after the existing columns.

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-25 15:40:00
"""

from __future__ import annotations

from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


#: a JSON attribute as text: the first element of an array (repeated attributes), else the value
def _text(key: str) -> str:
    return (
        f"(CASE jsonb_typeof(b.attributes->'{key}') WHEN 'array' THEN b.attributes->'{key}'->>0 "
        f"ELSE b.attributes->>'{key}' END)"
    )


def _number(key: str) -> str:
    t = _text(key)
    return f"(CASE WHEN {t} ~ '^\\s*[-+]?[0-9]+(\\.[0-9]*)?([eE][-+]?[0-9]+)?\\s*$' THEN ({t})::float8 END)"


def _integer(key: str) -> str:
    t = _text(key)
    return f"(CASE WHEN {t} ~ '^\\s*[-+]?[0-9]+\\s*$' THEN ({t})::int END)"


def _year(key: str) -> str:
    t = _text(key)
    return f"(substring({t} from '^\\s*([0-9]{{4}})'))::int"


_COLUMNS = f""",
       {_number('measuredHeight')}                AS measured_height_m,
       {_text('function')}                        AS function,
       {_year('yearOfConstruction')}              AS year_of_construction,
       {_text('roofType')}                        AS roof_type,
       {_integer('storeysAboveGround')}           AS storeys_above_ground,
       b.attributes                               AS attributes
FROM appearance a"""


#: the view as revision 0004 left it (a migration keeps its own copy)
_BUILDING_THERMAL_0004 = """
CREATE OR REPLACE VIEW building_thermal AS
SELECT a.id                                       AS id,
       cm.id                                      AS city_model_id,
       cm.name                                    AS model_name,
       b.gml_id                                   AS building_gml_id,
       a.theme                                    AS theme,
       a.job_id                                   AS job_id,
       count(*)                                   AS surfaces,
       count(*) FILTER (WHERE st.texels_observed > 0) AS observed_surfaces,
       CASE WHEN sum(st.texels_total) > 0
            THEN sum(st.texels_observed)::float8 / sum(st.texels_total) END AS observed_share,
       sum(st.mean_k * st.texels_observed) FILTER (WHERE st.mean_k IS NOT NULL)
         / NULLIF(sum(st.texels_observed) FILTER (WHERE st.mean_k IS NOT NULL), 0) AS mean_k,
       min(st.min_k)                              AS min_k,
       max(st.max_k)                              AS max_k,
       max(st.p95_k)                              AS max_p95_k,
       avg(st.resolution_m)                       AS mean_resolution_m,
       b.footprint::geometry(MultiPolygon)        AS footprint
FROM appearance a
JOIN building b        ON b.id = a.building_id
JOIN city_model cm     ON cm.id = a.city_model_id AND cm.state = 'complete'
JOIN surface_thermal st ON st.appearance_id = a.id
GROUP BY a.id, cm.id, cm.name, b.gml_id, a.theme, a.job_id, b.footprint
"""



def upgrade() -> None:
    sql = _BUILDING_THERMAL_0004.replace("\nFROM appearance a", _COLUMNS, 1).replace(
        "GROUP BY a.id, cm.id, cm.name, b.gml_id, a.theme, a.job_id, b.footprint",
        "GROUP BY a.id, cm.id, cm.name, b.gml_id, a.theme, a.job_id, b.footprint, b.attributes",
    )
    op.execute(sql)
    op.execute(
        "COMMENT ON VIEW building_thermal IS 'One row per building appearance with thermal statistics "
        "of complete city models: per-theme aggregates in kelvin on the 2D footprint (model SRID), "
        "with measured height, function, year of construction, roof type and storeys as typed columns "
        "and all attributes as jsonb.'"
    )


def downgrade() -> None:
    op.execute("DROP VIEW building_thermal")
    op.execute(_BUILDING_THERMAL_0004)
    op.execute(
        "COMMENT ON VIEW building_thermal IS 'One row per building appearance with thermal statistics "
        "of complete city models: per-theme aggregates in kelvin on the 2D footprint (model SRID).'"
    )

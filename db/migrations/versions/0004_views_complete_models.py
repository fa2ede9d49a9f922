"""GIS views show complete city models only: `facade_thermal` and `building_thermal` leave out
models whose `state` is not 'complete' (a model left 'importing' by an import that died, until
`citytherm db repair` or the next import removes it). Same columns as 0002.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-25 15:00:00
"""

from __future__ import annotations

from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None

_FACADE_THERMAL = """
CREATE OR REPLACE VIEW facade_thermal AS
SELECT st.id                          AS id,
       cm.id                          AS city_model_id,
       cm.name                        AS model_name,
       rb.gml_id                      AS building_gml_id,
       b.gml_id                       AS owner_gml_id,
       s.gml_id                       AS surface_gml_id,
       s.surface_class                AS surface_class,
       s.lod                          AS lod,
       a.theme                        AS theme,
       a.job_id                       AS job_id,
       a.id                           AS appearance_id,
       st.observed_share              AS observed_share,
       st.texels_observed             AS texels_observed,
       st.texels_total                AS texels_total,
       st.resolution_m                AS resolution_m,
       st.view_angle_deg              AS view_angle_deg,
       st.mean_k, st.median_k, st.std_k, st.min_k, st.max_k,
       st.p05_k, st.p25_k, st.p75_k, st.p95_k,
       s.area_m2                      AS area_m2,
       s.geometry::geometry(PolygonZ) AS geometry
FROM surface_thermal st
JOIN appearance a  ON a.id = st.appearance_id
JOIN surface s     ON s.id = st.surface_id
JOIN building b    ON b.id = s.building_id
JOIN building rb   ON rb.id = COALESCE(b.root_id, b.id)
JOIN city_model cm ON cm.id = s.city_model_id{state}
WHERE EXISTS (
    SELECT 1 FROM texture_param tp
    JOIN surface_data sd ON sd.id = tp.surface_data_id
    WHERE sd.appearance_id = a.id AND tp.surface_id = s.id
)
"""

_BUILDING_THERMAL = """
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
JOIN city_model cm     ON cm.id = a.city_model_id{state}
JOIN surface_thermal st ON st.appearance_id = a.id
GROUP BY a.id, cm.id, cm.name, b.gml_id, a.theme, a.job_id, b.footprint
"""

_COMPLETE = " AND cm.state = 'complete'"


def upgrade() -> None:
    op.execute(_FACADE_THERMAL.format(state=_COMPLETE))
    op.execute(_BUILDING_THERMAL.format(state=_COMPLETE))
    op.execute(
        "COMMENT ON VIEW facade_thermal IS 'One row per textured surface and appearance (theme) of "
        "complete city models: thermal statistics in kelvin and the surface polygon (POLYGON Z, model "
        "SRID).'"
    )
    op.execute(
        "COMMENT ON VIEW building_thermal IS 'One row per building appearance with thermal statistics "
        "of complete city models: per-theme aggregates in kelvin on the 2D footprint (model SRID).'"
    )


def downgrade() -> None:
    op.execute(_FACADE_THERMAL.format(state=""))
    op.execute(_BUILDING_THERMAL.format(state=""))
    op.execute(
        "COMMENT ON VIEW facade_thermal IS 'One row per textured surface and appearance (theme): "
        "thermal statistics in kelvin and the surface polygon (POLYGON Z, model SRID).'"
    )
    op.execute(
        "COMMENT ON VIEW building_thermal IS 'One row per building appearance with thermal "
        "statistics: per-theme aggregates in kelvin on the 2D footprint (model SRID).'"
    )

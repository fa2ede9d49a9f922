"""Change between surveys (issue 16, item 6): the GIS view `surface_thermal_change`, one row per
surface observed by two successful jobs on the same complete city model and theme, A the earlier
survey and B the later one: both typical temperatures (kelvin; `typical_k` of 0010, the median
for results stored before it), `delta_typical_k` = B − A, the air temperatures where the jobs'
sequence manifests give them (`conditions.air_temperature_c`) and the change normalised by them,
`(T_B − T_air,B) − (T_A − T_air,A)`, and the surface polygon (POLYGON Z typed with the database
SRID).

A survey's time is its manifest's `conditions.recorded_at`, else the job's creation time; pairs
are ordered by it (then by job id). The ΔT textures and the share of the surface observed in both
come from `citytherm compare` (they need the tiles, not a view).

Revision ID: 0011
Revises: 0010
Create Date: 2026-11-26 01:40:00
"""

from __future__ import annotations

from alembic import op
from sqlalchemy import text

revision = "0011"
down_revision = "0010"
branch_labels = None
depends_on = None

#: one job's observation of one surface (written out twice in the view, not as a CTE: PostgreSQL
#: materialises a CTE used twice, and a query for one pair of jobs would scan every job's rows)
_OBS = """(
    SELECT st.surface_id,
           a.job_id,
           a.theme,
           a.city_model_id,
           COALESCE(st.typical_k, st.median_k) AS typical_k,
           st.observed_share,
           COALESCE((sq.manifest -> 'conditions' ->> 'recorded_at')::timestamptz, j.created_at)
                                                AS survey_time,
           (sq.manifest -> 'conditions' ->> 'air_temperature_c')::float8 + 273.15 AS air_temperature_k
    FROM surface_thermal st
    JOIN appearance a     ON a.id = st.appearance_id
    JOIN job j            ON j.id = a.job_id AND j.status = 'successful'
    LEFT JOIN sequence sq ON sq.id = j.sequence_id
    WHERE st.texels_observed > 0 AND COALESCE(st.typical_k, st.median_k) IS NOT NULL
)"""

#: `id`: a stable 60-bit key of (job A, job B, surface) for GIS clients (not a window function:
#: a query for one pair of jobs then reads that pair's rows only)
_VIEW = """
CREATE VIEW surface_thermal_change AS
SELECT ('x' || left(md5(oa.job_id::text || '/' || ob.job_id::text || '/' || oa.surface_id::text), 15))
           ::bit(60)::bigint          AS id,
       cm.id                          AS city_model_id,
       cm.name                        AS model_name,
       oa.theme                       AS theme,
       rb.gml_id                      AS building_gml_id,
       b.gml_id                       AS owner_gml_id,
       s.gml_id                       AS surface_gml_id,
       s.surface_class                AS surface_class,
       oa.job_id                      AS job_a,
       ob.job_id                      AS job_b,
       oa.survey_time                 AS time_a,
       ob.survey_time                 AS time_b,
       oa.typical_k                   AS typical_a_k,
       ob.typical_k                   AS typical_b_k,
       ob.typical_k - oa.typical_k    AS delta_typical_k,
       oa.air_temperature_k           AS air_temperature_a_k,
       ob.air_temperature_k           AS air_temperature_b_k,
       (ob.typical_k - ob.air_temperature_k) - (oa.typical_k - oa.air_temperature_k)
                                      AS normalised_delta_k,
       oa.observed_share              AS observed_share_a,
       ob.observed_share              AS observed_share_b,
       s.area_m2                      AS area_m2,
       s.geometry::geometry(PolygonZ, {srid}) AS geometry
FROM {obs} oa
JOIN {obs} ob      ON ob.surface_id = oa.surface_id AND ob.theme = oa.theme
                  AND ob.city_model_id = oa.city_model_id
                  AND (oa.survey_time, oa.job_id) < (ob.survey_time, ob.job_id)
JOIN surface s     ON s.id = oa.surface_id
JOIN building b    ON b.id = s.building_id
JOIN building rb   ON rb.id = COALESCE(b.root_id, b.id)
JOIN city_model cm ON cm.id = oa.city_model_id AND cm.state = 'complete'
"""

_COMMENT = (
    "One row per surface observed by two successful jobs on the same complete city model and theme "
    "(A the earlier survey): typical temperatures in kelvin, their change B - A, the change normalised "
    "by the outside air temperatures where the sequence manifests give them, and the surface polygon "
    "(POLYGON Z, database SRID)."
)


def upgrade() -> None:
    srid = op.get_bind().execute(text("SELECT Find_SRID('public', 'surface', 'geometry')")).scalar_one()
    op.execute(_VIEW.format(srid=int(srid), obs=_OBS))
    op.execute(f"COMMENT ON VIEW surface_thermal_change IS '{_COMMENT}'")


def downgrade() -> None:
    op.execute("DROP VIEW surface_thermal_change")

"""Heat-leak detection in the database (issue 16): the facade figures per surface and theme
(typical temperature, spread, share of area above typical, window share, heat-loss index, numbers
of windows and leak candidates), the detector's figures per anomaly (stable id, frames, best
resolution, confidence), and the GIS views that show them: `facade_thermal` gains the texture
quality of 0009 and the facade figures (appended: the columns a GIS already reads keep their
order), `building_thermal` gains the numbers of leaks and windows, and the new view
`thermal_anomalies` gives every anomaly (kind `leak`, `window`, `bridge`) as a POLYGON Z typed
with the database SRID.

Revision ID: 0010
Revises: 0009
Create Date: 2026-11-26 01:20:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op
from sqlalchemy import text

revision = "0010"
down_revision = "0009"
branch_labels = None
depends_on = None

THERMAL = (
    ("typical_k", sa.Double()),
    ("spread_k", sa.Double()),
    ("hot_share", sa.Double()),
    ("window_share", sa.Double()),
    ("heat_loss_index", sa.Double()),
    ("windows", sa.Integer()),
    ("leaks", sa.Integer()),
)
ANOMALY = (
    ("anomaly_id", sa.Text()),
    ("frames", sa.Integer()),
    ("best_resolution_m", sa.Double()),
    ("confidence", sa.Double()),
)

#: facade_thermal as 0004 made it (0007 typed its geometry); `{srid}` and `{extra}` filled in
_FACADE = """
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
       s.geometry::geometry(PolygonZ, {srid}) AS geometry{extra}
FROM surface_thermal st
JOIN appearance a  ON a.id = st.appearance_id
JOIN surface s     ON s.id = st.surface_id
JOIN building b    ON b.id = s.building_id
JOIN building rb   ON rb.id = COALESCE(b.root_id, b.id)
JOIN city_model cm ON cm.id = s.city_model_id AND cm.state = 'complete'
WHERE EXISTS (
    SELECT 1 FROM texture_param tp
    JOIN surface_data sd ON sd.id = tp.surface_data_id
    WHERE sd.appearance_id = a.id AND tp.surface_id = s.id
)
"""

_FACADE_EXTRA = """,
       st.resolution_px_per_m, st.best_resolution_m, st.mean_observations, st.reason,
       st.typical_k, st.spread_k, st.hot_share, st.window_share, st.heat_loss_index,
       st.windows, st.leaks"""

_ANOMALIES = """
CREATE VIEW thermal_anomalies AS
SELECT ta.id                          AS id,
       cm.id                          AS city_model_id,
       cm.name                        AS model_name,
       rb.gml_id                      AS building_gml_id,
       s.gml_id                       AS surface_gml_id,
       s.surface_class                AS surface_class,
       a.theme                        AS theme,
       ta.job_id                      AS job_id,
       ta.anomaly_id                  AS anomaly_id,
       ta.kind                        AS kind,
       ta.area_m2                     AS area_m2,
       ta.peak_delta_k                AS peak_delta_k,
       ta.mean_delta_k                AS mean_delta_k,
       ta.frames                      AS frames,
       ta.best_resolution_m           AS best_resolution_m,
       ta.confidence                  AS confidence,
       ta.centre                      AS centre,
       ta.outline::geometry(PolygonZ, {srid}) AS geometry
FROM thermal_anomaly ta
JOIN building b    ON b.id = ta.building_id
JOIN building rb   ON rb.id = COALESCE(b.root_id, b.id)
JOIN city_model cm ON cm.id = b.city_model_id AND cm.state = 'complete'
LEFT JOIN surface s    ON s.id = ta.surface_id
LEFT JOIN appearance a ON a.id = ta.appearance_id
WHERE ta.outline IS NOT NULL
"""

_VIEWDEF = "SELECT pg_get_viewdef('building_thermal'::regclass, true)"
_BT_COMMENT = "SELECT obj_description('building_thermal'::regclass, 'pg_class')"

_FACADE_COMMENT = (
    "One row per textured surface and appearance (theme) of complete city models: thermal "
    "statistics in kelvin, texture quality, facade figures (typical temperature, spread, hot and "
    "window shares, heat-loss index, windows and leak candidates; docs/anomalies.md) and the "
    "surface polygon (POLYGON Z, database SRID)."
)
_FACADE_COMMENT_0007 = (
    "One row per textured surface and appearance (theme) of complete city models: thermal "
    "statistics in kelvin and the surface polygon (POLYGON Z, database SRID)."
)
_ANOMALIES_COMMENT = (
    "One row per thermal anomaly found by a job on a complete city model: kind leak (heat-leak "
    "candidate), window or bridge (linear thermal bridge); contrast against the surface typical "
    "temperature in kelvin; its 3D outline on the surface (POLYGON Z, database SRID)."
)


def _srid() -> int:
    srid = op.get_bind().execute(text("SELECT Find_SRID('public', 'surface', 'geometry')")).scalar_one()
    return int(srid)


def _building_thermal() -> str:
    """building_thermal's definition now, with the numbers of leaks and windows appended."""
    body = op.get_bind().execute(text(_VIEWDEF)).scalar_one()
    head, sep, tail = body.partition("\n   FROM appearance a")
    if not sep:
        raise RuntimeError("building_thermal: unexpected definition (no FROM appearance a)")
    extra = ",\n    sum(st.leaks) AS leaks,\n    sum(st.windows) AS windows"
    return f"CREATE OR REPLACE VIEW building_thermal AS {head}{extra}{sep}{tail}"


def upgrade() -> None:
    for name, type_ in THERMAL:
        op.add_column("surface_thermal", sa.Column(name, type_, nullable=True))
    for name, type_ in ANOMALY:
        op.add_column("thermal_anomaly", sa.Column(name, type_, nullable=True))
    srid = _srid()
    op.execute(_FACADE.format(srid=srid, extra=_FACADE_EXTRA))
    op.execute(f"COMMENT ON VIEW facade_thermal IS '{_FACADE_COMMENT}'")
    op.execute(_building_thermal().rstrip().rstrip(";"))
    op.execute(_ANOMALIES.format(srid=srid))
    op.execute(f"COMMENT ON VIEW thermal_anomalies IS '{_ANOMALIES_COMMENT}'")


def downgrade() -> None:
    op.execute("DROP VIEW thermal_anomalies")
    bind = op.get_bind()
    bt = bind.execute(text(_VIEWDEF)).scalar_one()
    bt_comment = bind.execute(text(_BT_COMMENT)).scalar()
    fc_comment = _FACADE_COMMENT_0007
    bt = bt.replace(",\n    sum(st.leaks) AS leaks,\n    sum(st.windows) AS windows", "")
    srid = _srid()
    op.execute("DROP VIEW facade_thermal")
    op.execute("DROP VIEW building_thermal")
    op.execute(_FACADE.format(srid=srid, extra="").replace("CREATE OR REPLACE", "CREATE"))
    op.execute(f"CREATE VIEW building_thermal AS {bt.rstrip().rstrip(';')}")
    for view, comment in (("facade_thermal", fc_comment), ("building_thermal", bt_comment)):
        if comment:
            quoted = comment.replace("'", "''")
            op.execute(f"COMMENT ON VIEW {view} IS '{quoted}'")
    for name, _ in reversed(ANOMALY):
        op.drop_column("thermal_anomaly", name)
    for name, _ in reversed(THERMAL):
        op.drop_column("surface_thermal", name)

"""The feature collections of the OGC API - Features (`docs/features.md`): what each one reads
from the city model database, as SQL fragments.

In: nothing (declarations). Out: `COLLECTIONS`, id -> `Collection`. A collection is a FROM clause
over the tables of `db/models.py` (only complete city models), a keyset column (the feature id:
unique, indexed, ordered), a geometry expression in the database SRID, its properties as
(name, SQL expression) pairs and the property filters (query parameters) it accepts.

- `buildings`: one feature per top-level building; the geometry is every surface of the
  building and its parts at the building's highest LoD (MULTIPOLYGON Z); the thermal figures are
  those of its most recent job appearance (of the `theme` / `job` asked for).
- `facades`: one feature per surface and job appearance (`surface_thermal`: every surface a job
  analysed, `textured` when it got a texture, as in the `facade_thermal` view), POLYGON Z; the
  facade figures of the anomaly detector (`typical_k`, `hot_share`, ...) when the schema has them.
- `anomalies`: `thermal_anomaly` rows, the outline POLYGON Z; the detector's `anomaly_id`,
  `frames`, `best_resolution_m`, `confidence` when the schema has them (migration 0010).
- `jobs`: one feature per job; its footprint is the 2D bounding box of the footprints of the
  buildings it textured, or of the city model while it has textured none (`footprint` says which).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from db.store import FACADE_FIGURE_COLUMNS

__all__ = ["COLLECTIONS", "Collection", "Filter"]


@dataclass(frozen=True)
class Filter:
    """A property filter: query parameter `name`, the SQL condition (with `:name` bound to the
    parsed value), which slot of the query it goes in ("where", or a named slot of the FROM
    clause), and the value type ("text", "float", "uuid")."""

    name: str
    sql: str
    kind: str = "text"
    slot: str = "where"
    description: str = ""


@dataclass(frozen=True)
class Collection:
    """One feature collection: SQL fragments and its description.

    `from_sql` may hold `{slot}` placeholders that filters of that slot fill (with `AND ...`);
    `key` is the feature id column (`key_kind` "int" or "uuid"); `geometry` an SQL expression in
    the database SRID; `bbox_sql` the condition of the `bbox` parameter, `INTERSECTS(column)`
    standing for "column intersects the bbox" (an indexed geometry column where there is one).
    """

    id: str
    title: str
    description: str
    from_sql: str
    key: str
    geometry: str
    geometry_type: str
    bbox_sql: str
    properties: tuple[tuple[str, str], ...]
    filters: tuple[Filter, ...]
    key_kind: str = "int"
    #: (property name, SQL expression, table, column): included when the column exists
    optional: tuple[tuple[str, str, str, str], ...] = ()
    slots: tuple[str, ...] = ()
    #: a condition every feature meets
    where: str = "TRUE"
    #: filters whose feature must have the thing they select (a LEFT JOIN that found a row)
    required: dict[str, str] = field(default_factory=dict)

    def filter(self, name: str) -> Filter | None:
        """The filter of query parameter `name`, or None."""
        return next((f for f in self.filters if f.name == name), None)


def _attr_text(key: str) -> str:
    """A building attribute as text: the first element of an array (repeated attributes)."""
    return (
        f"(CASE jsonb_typeof(b.attributes->'{key}') WHEN 'array' THEN b.attributes->'{key}'->>0 "
        f"ELSE b.attributes->>'{key}' END)"
    )


def _attr_number(key: str, pattern: str = r"^\s*[-+]?[0-9]+(\.[0-9]*)?([eE][-+]?[0-9]+)?\s*$") -> str:
    t = _attr_text(key)
    return f"(CASE WHEN {t} ~ '{pattern}' THEN ({t})::float8 END)"


_YEAR = f"(substring({_attr_text('yearOfConstruction')} from '^\\s*([0-9]{{4}})'))::int"
_COMPLETE = "cm.state = 'complete'"
_MODEL = Filter("model", "cm.name = :model", description="City model name.")

BUILDINGS = Collection(
    id="buildings",
    title="Buildings",
    description="Top-level buildings of the city models: the 3D surfaces of the building and its "
    "parts at its highest LoD (MULTIPOLYGON Z), its attributes and the thermal figures (kelvin) of "
    "its most recent job appearance (of the theme / job asked for with `theme` / `job`).",
    from_sql=f"""building b
JOIN city_model cm ON cm.id = b.city_model_id AND {_COMPLETE}
LEFT JOIN LATERAL (
    SELECT a.id, a.theme, a.job_id FROM appearance a
    WHERE a.building_id = b.id AND a.job_id IS NOT NULL{{thermal}}
    ORDER BY a.created_at DESC, a.id DESC LIMIT 1
) ta ON TRUE
LEFT JOIN LATERAL (
    SELECT count(*) AS surfaces, count(*) FILTER (WHERE st.texels_observed > 0) AS observed_surfaces,
           CASE WHEN sum(st.texels_total) > 0
                THEN sum(st.texels_observed)::float8 / sum(st.texels_total) END AS observed_share,
           sum(st.mean_k * st.texels_observed) FILTER (WHERE st.mean_k IS NOT NULL)
             / NULLIF(sum(st.texels_observed) FILTER (WHERE st.mean_k IS NOT NULL), 0) AS mean_k,
           min(st.min_k) AS min_k, max(st.max_k) AS max_k, max(st.p95_k) AS max_p95_k,
           sum(st.leaks) AS leaks, sum(st.windows) AS windows
    FROM surface_thermal st WHERE st.appearance_id = ta.id
) tt ON ta.id IS NOT NULL""",
    key="b.id",
    geometry="""(SELECT ST_Collect(s.geometry ORDER BY s.building_id, s.ordinal)
    FROM building p JOIN surface s ON s.building_id = p.id
    WHERE p.root_id = b.id AND s.geometry IS NOT NULL AND s.lod = (
        SELECT max(s2.lod) FROM building p2 JOIN surface s2 ON s2.building_id = p2.id
        WHERE p2.root_id = b.id AND s2.geometry IS NOT NULL))""",
    geometry_type="MultiPolygonZ",
    bbox_sql="(INTERSECTS(b.footprint) OR (b.footprint IS NULL AND INTERSECTS(b.envelope)))",
    properties=(
        ("gml_id", "b.gml_id"),
        ("name", "b.name"),
        ("model", "cm.name"),
        ("model_id", "cm.id"),
        ("parts", "(SELECT count(*) FROM building q WHERE q.parent_id = b.id)"),
        ("measured_height_m", _attr_number("measuredHeight")),
        ("function", _attr_text("function")),
        ("year_of_construction", _YEAR),
        ("roof_type", _attr_text("roofType")),
        ("storeys_above_ground", _attr_number("storeysAboveGround", r"^\s*[-+]?[0-9]+\s*$") + "::int"),
        ("theme", "ta.theme"),
        ("job", "ta.job_id::text"),
        ("surfaces", "tt.surfaces"),
        ("observed_surfaces", "tt.observed_surfaces"),
        ("observed_share", "tt.observed_share"),
        ("mean_k", "tt.mean_k"),
        ("min_k", "tt.min_k"),
        ("max_k", "tt.max_k"),
        ("max_p95_k", "tt.max_p95_k"),
        ("leaks", "tt.leaks"),
        ("windows", "tt.windows"),
    ),
    filters=(
        Filter("theme", " AND a.theme = :theme", slot="thermal", description="Appearance theme."),
        Filter("job", " AND a.job_id = :job", kind="uuid", slot="thermal", description="Job id."),
        Filter("building", "b.gml_id = :building", description="Building gml:id."),
        Filter("min_mean_k", "tt.mean_k >= :min_mean_k", kind="float", description="Mean kelvin at least."),
        _MODEL,
    ),
    slots=("thermal",),
    where="b.parent_id IS NULL",
    required={"theme": "ta.id IS NOT NULL", "job": "ta.id IS NOT NULL"},
)

FACADES = Collection(
    id="facades",
    title="Facades and roofs with thermal figures",
    description="One feature per surface and job appearance (theme): the surface polygon "
    "(POLYGON Z) with its thermal statistics in kelvin, observed share and resolution; `textured` "
    "when the surface got a texture (the rows of the `facade_thermal` view). Walls only: "
    "`class=WallSurface`.",
    from_sql=f"""surface_thermal st
JOIN appearance a ON a.id = st.appearance_id
JOIN surface s ON s.id = st.surface_id
JOIN building b ON b.id = s.building_id
JOIN building rb ON rb.id = COALESCE(b.root_id, b.id)
JOIN city_model cm ON cm.id = s.city_model_id AND {_COMPLETE}""",
    key="st.id",
    geometry="s.geometry",
    geometry_type="PolygonZ",
    bbox_sql="INTERSECTS(s.geometry)",
    properties=(
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
    ),
    optional=tuple((name, f"st.{name}", "surface_thermal", name) for name in FACADE_FIGURE_COLUMNS),
    filters=(
        Filter("theme", "a.theme = :theme", description="Appearance theme."),
        Filter("job", "a.job_id = :job", kind="uuid", description="Job id."),
        Filter("building", "rb.gml_id = :building", description="gml:id of the (top-level) building."),
        Filter("class", "s.surface_class = :class", description="Surface class, e.g. WallSurface."),
        Filter("min_mean_k", "st.mean_k >= :min_mean_k", kind="float", description="Mean kelvin at least."),
        _MODEL,
    ),
)

ANOMALIES = Collection(
    id="anomalies",
    title="Thermal anomalies",
    description="Heat-leak candidates (and what else the detector reports: `kind`) found by jobs: "
    "the outline on the surface (POLYGON Z) with its size and contrast in kelvin.",
    from_sql=f"""thermal_anomaly ta
JOIN job j ON j.id = ta.job_id
JOIN building b ON b.id = ta.building_id
JOIN building rb ON rb.id = COALESCE(b.root_id, b.id)
JOIN city_model cm ON cm.id = b.city_model_id AND {_COMPLETE}
LEFT JOIN surface s ON s.id = ta.surface_id
LEFT JOIN appearance a ON a.id = ta.appearance_id""",
    key="ta.id",
    geometry="ta.outline",
    geometry_type="PolygonZ",
    bbox_sql="INTERSECTS(ta.outline)",
    properties=(
        ("kind", "ta.kind"),
        ("building", "rb.gml_id"),
        ("owner", "b.gml_id"),
        ("surface_gml_id", "s.gml_id"),
        ("class", "s.surface_class"),
        ("model", "cm.name"),
        ("model_id", "cm.id"),
        ("theme", "COALESCE(a.theme, j.theme)"),
        ("job", "ta.job_id::text"),
        ("area_m2", "ta.area_m2"),
        ("peak_delta_k", "ta.peak_delta_k"),
        ("mean_delta_k", "ta.mean_delta_k"),
    ),
    optional=(
        ("anomaly_id", "ta.anomaly_id", "thermal_anomaly", "anomaly_id"),
        ("frames", "ta.frames", "thermal_anomaly", "frames"),
        ("best_resolution_m", "ta.best_resolution_m", "thermal_anomaly", "best_resolution_m"),
        ("confidence", "ta.confidence", "thermal_anomaly", "confidence"),
    ),
    filters=(
        Filter("theme", "COALESCE(a.theme, j.theme) = :theme", description="Appearance theme."),
        Filter("job", "ta.job_id = :job", kind="uuid", description="Job id."),
        Filter("building", "rb.gml_id = :building", description="gml:id of the (top-level) building."),
        Filter("kind", "ta.kind = :kind", description="leak, window, bridge, ..."),
        Filter("class", "s.surface_class = :class", description="Class of the anomaly's surface."),
        _MODEL,
    ),
)

JOBS = Collection(
    id="jobs",
    title="Texturing jobs",
    description="One feature per texturing job: its footprint is the 2D bounding box of the "
    "footprints of the buildings it textured (`footprint`: textured), or of its city model while it "
    "has textured none (`footprint`: model); status, theme, progress and counts.",
    from_sql=f"""job j
JOIN city_model cm ON cm.id = j.city_model_id AND {_COMPLETE}
LEFT JOIN LATERAL (
    SELECT count(*) AS n, ST_Extent(bb.footprint) AS e FROM appearance ja
    JOIN building bb ON bb.id = ja.building_id WHERE ja.job_id = j.id
) fx ON TRUE
LEFT JOIN LATERAL (
    SELECT CASE WHEN fx.n > 0 AND fx.e IS NOT NULL THEN ST_SetSRID(fx.e::geometry, CAST(:srid AS int))
                ELSE ST_Envelope(ST_Force2D(cm.envelope)) END AS g
) jg ON TRUE""",
    key="j.id",
    key_kind="uuid",
    geometry="jg.g",
    geometry_type="Polygon",
    bbox_sql="INTERSECTS(jg.g)",
    properties=(
        ("status", "j.status"),
        ("stage", "j.stage"),
        ("theme", "j.theme"),
        ("progress", "j.progress"),
        ("model", "cm.name"),
        ("model_id", "cm.id"),
        ("created", "j.created_at"),
        ("finished", "j.finished_at"),
        ("units", "(SELECT count(*) FROM job_unit u WHERE u.job_id = j.id)"),
        ("textured_buildings", "fx.n"),
        ("footprint", "CASE WHEN fx.n > 0 THEN 'textured' ELSE 'model' END"),
    ),
    filters=(
        Filter("theme", "j.theme = :theme", description="Appearance theme."),
        Filter("job", "j.id = :job", kind="uuid", description="Job id."),
        Filter("status", "j.status = :status", description="accepted, running, successful, failed, ..."),
        _MODEL,
    ),
)

COLLECTIONS: dict[str, Collection] = {c.id: c for c in (BUILDINGS, FACADES, ANOMALIES, JOBS)}

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
  Its SQL is `db.facade_features`', which also keeps each feature's text in CRS84 with its row
  (`stored_text`); a page without filters on the appearance or buildings joins only the surface
  and the model (`lean`).
- `anomalies`: `thermal_anomaly` rows, the outline POLYGON Z; the detector's `anomaly_id`,
  `frames`, `best_resolution_m`, `confidence` when the schema has them (migration 0010).
- `jobs`: one feature per job; its footprint is the 2D bounding box of the footprints of the
  buildings it textured, or of the city model while it has textured none (`footprint` says which).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from db import facade_features

__all__ = ["COLLECTIONS", "Collection", "Filter", "LeanFrom", "StoredText"]


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
class StoredText:
    """Where a collection keeps each feature's GeoJSON text in CRS84 (as `feature_select`
    writes it with the properties of the schema) and the fingerprint of the definition that
    wrote it (`db.feature_json.feature_spec`): columns `text` and `spec` of `table`, which the
    collection's query names `alias`."""

    table: str
    alias: str
    text: str = "feature"
    spec: str = "feature_spec"


@dataclass(frozen=True)
class LeanFrom:
    """The FROM clause of a query that selects a collection's rows without writing their
    features (a count; a page of stored feature texts): `base`, what every such query needs, and
    the joins it may leave out, (alias, JOIN clause) in order, each finding exactly one row
    (not-null foreign keys), so that leaving out one no condition names keeps the same rows."""

    base: str
    joins: tuple[tuple[str, str], ...]

    def for_condition(self, condition: str) -> str:
        """`base` with the joins `condition` names (by alias, `a.`) and those they need."""
        needed = {a for a, _ in self.joins if _names(condition, a)}
        kept: list[str] = []
        for alias, clause in reversed(self.joins):
            if alias in needed:
                kept.append(clause)
                needed |= {a for a, _ in self.joins if _names(clause, a)}
        return "\n".join([self.base, *reversed(kept)])


def _names(sql: str, alias: str) -> bool:
    """Whether `sql` names a column of `alias` (`alias.` not preceded by a name character or dot).

    >>> _names("rb.gml_id = :b", "b"), _names("b.gml_id = :b", "b")
    (False, True)
    """
    return re.search(rf"(?<![\w.]){re.escape(alias)}\.", sql) is not None


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
    #: the FROM clause of queries that need the rows but not `properties` (None: `from_sql`)
    lean: LeanFrom | None = None
    #: the feature's GeoJSON text in CRS84 kept with its row, where the schema has its columns
    stored_text: StoredText | None = None

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

_FACADE_JOINS = dict(facade_features.JOINS)

FACADES = Collection(
    id="facades",
    title="Facades and roofs with thermal figures",
    description="One feature per surface and job appearance (theme): the surface polygon "
    "(POLYGON Z) with its thermal statistics in kelvin, observed share and resolution; `textured` "
    "when the surface got a texture (the rows of the `facade_thermal` view). Walls only: "
    "`class=WallSurface`.",
    from_sql="\n".join(
        [facade_features.TABLE]
        + [f"{j} AND {_COMPLETE}" if a == "cm" else j for a, j in facade_features.JOINS]
    ),
    key=facade_features.KEY,
    geometry=facade_features.GEOMETRY,
    geometry_type="PolygonZ",
    bbox_sql="INTERSECTS(s.geometry)",
    properties=facade_features.PROPERTIES,
    optional=facade_features.OPTIONAL,
    filters=(
        Filter("theme", "a.theme = :theme", description="Appearance theme."),
        Filter("job", "a.job_id = :job", kind="uuid", description="Job id."),
        Filter("building", "rb.gml_id = :building", description="gml:id of the (top-level) building."),
        Filter("class", "s.surface_class = :class", description="Surface class, e.g. WallSurface."),
        Filter("min_mean_k", "st.mean_k >= :min_mean_k", kind="float", description="Mean kelvin at least."),
        _MODEL,
    ),
    lean=LeanFrom(
        base="\n".join(
            [facade_features.TABLE, _FACADE_JOINS["s"], f"{_FACADE_JOINS['cm']} AND {_COMPLETE}"]
        ),
        joins=tuple((a, _FACADE_JOINS[a]) for a in ("a", "b", "rb")),
    ),
    stored_text=StoredText("surface_thermal", "st"),
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

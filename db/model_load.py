"""Load a city model's top-level buildings from the database as the pipeline's `Building`s.

In: a `Connection`, a city model id and optionally a 2D box in the model's CRS. Out: top-level
`workers.pipeline.geometry.citymodel.Building`s in file order (`building.ordinal`), parts nested,
polygons in file order with their ring ids and flags, coordinates bit-exact (float64 WKB), no
appearances: the same buildings `db.citygml.reader.iter_buildings` gives from the imported file
(but `Polygon.solid_reversed`, which the database does not keep). The export (`db.export`) shares
the row -> `Polygon` and rows -> `Building` assembly (`polygon_from_row`, `assemble_buildings`).

Coordinates: geometry columns hold the database's SRID (`db.srid.database_srid`). When it differs
from the model's (`city_model.srid`), the buildings are transformed from the database SRID back
into the model's CRS (`db.srid.from_database`: horizontal, heights kept, as the export does), so
a job always runs in the model's own CRS. A box given in the model's CRS is transformed the other
way for the spatial query (GiST index on `building.envelope`).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np
from sqlalchemy import Connection, text

from db.city_models import find_model
from db.geomcodec import polygon_rings_from_wkb
from db.srid import database_srid, from_database
from workers.pipeline.geometry.citymodel import Appearance, Building, Polygon, Ring
from workers.pipeline.geometry.transform import transform_building

__all__ = [
    "ModelBuildingIds",
    "assemble_buildings",
    "building_rows",
    "iter_model_buildings",
    "near_box",
    "polygon_from_row",
    "surface_polygons",
]

#: the `surface` columns `polygon_from_row` reads (geometry as WKB under `wkb`)
SURFACE_ROW_SQL = (
    "building_id, gml_id, generated_id, ring_ids, ring_generated, ring_closed, surface_class, "
    "surface_gml_id, lod, in_solid, collection_id, raw_rings, ST_AsBinary(geometry) AS wkb"
)


def polygon_from_row(row: Mapping[str, Any]) -> Polygon:
    """A `surface` row (the columns of `SURFACE_ROW_SQL`) -> `Polygon`: rings from the WKB (or
    from `raw_rings` where PostGIS could not hold them), an input ring that was not closed
    unclosed again, ids and flags as imported."""
    if row["wkb"] is not None:
        coords = polygon_rings_from_wkb(row["wkb"])
    else:
        coords = [np.asarray(r, dtype=np.float64).reshape(-1, 3) for r in row["raw_rings"]]
    rings = []
    for c, rid, gen, closed in zip(
        coords, row["ring_ids"], row["ring_generated"], row["ring_closed"], strict=True
    ):
        if not closed and row["wkb"] is not None:
            c = c[:-1]
        rings.append(Ring(id=rid, coords=c, generated_id=gen))
    return Polygon(
        id=row["gml_id"],
        exterior=rings[0],
        interiors=tuple(rings[1:]),
        surface_class=row["surface_class"],
        lod=row["lod"],
        surface_id=row["surface_gml_id"],
        in_solid=row["in_solid"],
        generated_id=row["generated_id"],
        collection_id=row["collection_id"],
    )


def assemble_buildings(
    roots: Sequence[int],
    building_rows: Sequence[Mapping[str, Any]],
    polygons: Mapping[int, Sequence[Polygon]],
    appearances: Callable[[int], tuple[Appearance, ...]] | None = None,
) -> list[Building]:
    """Top-level `Building`s `roots` (row ids, in that order) from their `building` rows (parts
    included, file order: id, gml_id, parent_id, is_part, name, srs_name, generated_id,
    attributes), their polygons by building row and, optionally, their appearances by building
    row. Roots without a row are left out."""
    children: dict[int, list[int]] = defaultdict(list)
    for b in building_rows:
        if b["parent_id"] is not None:
            children[b["parent_id"]].append(b["id"])
    by_id = {b["id"]: b for b in building_rows}

    def build(bid: int, parent_gml: str | None) -> Building:
        r = by_id[bid]
        return Building(
            id=r["gml_id"],
            polygons=tuple(polygons.get(bid, ())),
            parts=tuple(build(c, r["gml_id"]) for c in children.get(bid, ())),
            attributes=dict(r["attributes"] or {}),
            is_part=r["is_part"],
            parent_id=parent_gml,
            srs_name=r["srs_name"],
            appearances=appearances(bid) if appearances is not None else (),
            name=r["name"],
            generated_id=r["generated_id"],
        )

    return [build(rid, None) for rid in roots if rid in by_id]


def building_rows(conn: Connection, roots: Sequence[int]) -> list[Mapping[str, Any]]:
    """The `building` rows of the top-level buildings `roots` and of their parts, file order (the
    columns `assemble_buildings` reads)."""
    sql = (
        "SELECT id, gml_id, parent_id, is_part, name, srs_name, generated_id, attributes "
        "FROM building WHERE root_id = ANY(:r) ORDER BY ordinal"
    )
    return list(conn.execute(text(sql), {"r": list(roots)}).mappings().all())


def surface_polygons(conn: Connection, building_ids: Sequence[int]) -> dict[int, list[Polygon]]:
    """The polygons of the buildings (row ids) by building row, file order."""
    polys: dict[int, list[Polygon]] = defaultdict(list)
    sql = f"SELECT {SURFACE_ROW_SQL} FROM surface WHERE building_id = ANY(:b) ORDER BY building_id, ordinal"
    for s in conn.execute(text(sql), {"b": list(building_ids)}).mappings():
        polys[s["building_id"]].append(polygon_from_row(s))
    return polys


def iter_model_buildings(
    conn: Connection,
    model_id: int,
    *,
    bbox: tuple[float, float, float, float] | None = None,
    batch_size: int = 200,
) -> Iterator[Building]:
    """The model's top-level buildings in file order (see the module docstring), in the model's
    CRS; with `bbox` = (minx, miny, maxx, maxy) in the model's CRS only those whose envelope meets
    it. Streamed: `batch_size` buildings per query round. Raises `NotFoundError`."""
    m = find_model(conn, int(model_id))
    db_srid = database_srid(conn)
    back = from_database(m["srs_name"] or f"EPSG:{db_srid}", db_srid)
    sql = "SELECT id FROM building WHERE city_model_id = :m AND NOT is_part"
    params: dict[str, Any] = {"m": m["id"], "srid": m["srid"] or db_srid, "db_srid": db_srid}
    if bbox is not None:  # the box is in the model's CRS, the envelopes in the database SRID
        sql += " AND envelope && ST_Transform(ST_MakeEnvelope(:x0, :y0, :x1, :y1, :srid), :db_srid)"
        params.update(dict(zip(("x0", "y0", "x1", "y1"), map(float, bbox), strict=True)))
    roots = [int(r[0]) for r in conn.execute(text(sql + " ORDER BY ordinal"), params).all()]
    for i in range(0, len(roots), batch_size):
        batch = roots[i : i + batch_size]
        rows = building_rows(conn, batch)
        for b in assemble_buildings(batch, rows, surface_polygons(conn, [r["id"] for r in rows])):
            yield transform_building(b, back, set_srs=False)


def near_box(
    conn: Connection, model_id: int, points: np.ndarray, reach_m: float
) -> tuple[float, float, float, float]:
    """A 2D box (model CRS) holding every top-level building whose bounding-box centre lies
    within `reach_m` plus its half diagonal of one of `points` (`(N, 3)`, model CRS, metres),
    the rule of `workers.pipeline.plan.near_buildings`: the points' box grown by `reach_m` and
    the model's largest half diagonal (1 % and 1 m more, for a transformation between CRSs)."""
    half = conn.execute(
        text(
            "SELECT max(sqrt((ST_XMax(envelope) - ST_XMin(envelope)) ^ 2 + (ST_YMax(envelope) - "
            "ST_YMin(envelope)) ^ 2 + (ST_ZMax(envelope) - ST_ZMin(envelope)) ^ 2)) / 2 FROM building "
            "WHERE city_model_id = :m AND NOT is_part"
        ),
        {"m": int(model_id)},
    ).scalar()
    grow = (float(reach_m) + float(half or 0.0)) * 1.01 + 1.0
    xy = np.asarray(points, dtype=np.float64).reshape(-1, 3)[:, :2]
    lo, hi = xy.min(axis=0) - grow, xy.max(axis=0) + grow
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


class ModelBuildingIds:
    """The gml ids of a model's top-level buildings as a `Collection[str]` answered by queries
    (`in`, `len`, iteration), so a large model's ids need not be held in memory."""

    def __init__(self, conn: Connection, model_id: int) -> None:
        self.conn = conn
        self.model_id = int(model_id)

    def __contains__(self, gml_id: object) -> bool:
        return (
            self.conn.execute(
                text("SELECT 1 FROM building WHERE city_model_id = :m AND gml_id = :g AND NOT is_part"),
                {"m": self.model_id, "g": str(gml_id)},
            ).first()
            is not None
        )

    def __len__(self) -> int:
        return int(
            self.conn.execute(
                text("SELECT count(*) FROM building WHERE city_model_id = :m AND NOT is_part"),
                {"m": self.model_id},
            ).scalar_one()
        )

    def __iter__(self) -> Iterator[str]:
        rows = self.conn.execute(
            text("SELECT gml_id FROM building WHERE city_model_id = :m AND NOT is_part ORDER BY ordinal"),
            {"m": self.model_id},
        )
        return (str(r[0]) for r in rows.all())

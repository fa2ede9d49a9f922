"""Import a CityGML file into the city model database, streamed, in batches.

In: a CityGML file (1.0/2.0/3.0; read by `db.citygml.reader`, never whole in memory) and a
database (Engine, sessionmaker or URL) migrated to head. Out: one `city_model` row with its
`building` (parts point to parent and root), `surface` (POLYGON Z in the model SRID, ring ids,
plane, geometry checks) and the file's appearances (`appearance` → `surface_data` →
`texture_param`); an `ImportSummary`.

Buildings are written with `COPY` in batches of `ImportOptions.batch_size` top-level buildings,
one transaction per batch; geometries are built in Python as hex EWKB (`db.geomcodec`). Row ids are
reserved from the sequences first so parents, surfaces and texture targets are linked without a
round trip. For big files the GiST indexes can be dropped during the load and rebuilt once at the
end (`ImportOptions.defer_spatial_indexes`). A model name that exists is refused
(`ModelExistsError`) unless `replace=True`, which deletes the old model first. A failed import
deletes what it wrote.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
from psycopg.types.json import Jsonb
from sqlalchemy import Connection, Engine, text

from db.appearance_rows import AppearanceRows, collect_appearance_rows
from db.citygml import reader as citygml_reader
from db.crs import UnknownCRSError, horizontal_epsg, vertical_epsg
from db.errors import ModelExistsError
from db.geomcodec import encode_envelope, encode_footprints, encode_polygons
from db.ops import copy_rows, create_spatial_indexes, delete_model, drop_spatial_indexes, reserve_ids
from db.session import as_engine
from db.surface_checks import full_checks, jsonable, surface_checks
from workers.pipeline.citymodel import Appearance, Building, ModelHeader, Polygon

__all__ = ["ImportOptions", "ImportSummary", "import_citygml", "model_srid"]

log = logging.getLogger(__name__)

BUILDING_COLUMNS = (
    "id",
    "city_model_id",
    "gml_id",
    "parent_id",
    "root_id",
    "is_part",
    "ordinal",
    "name",
    "srs_name",
    "generated_id",
    "attributes",
    "footprint",
    "envelope",
)
SURFACE_COLUMNS = (
    "id",
    "city_model_id",
    "building_id",
    "ordinal",
    "gml_id",
    "generated_id",
    "ring_ids",
    "ring_generated",
    "ring_closed",
    "surface_class",
    "surface_gml_id",
    "lod",
    "in_solid",
    "collection_id",
    "geometry",
    "raw_rings",
    "plane_normal",
    "plane_offset",
    "area_m2",
    "checks",
)


@dataclass(frozen=True)
class ImportOptions:
    """Options of `import_citygml`.

    Attributes:
        batch_size: top-level buildings per transaction.
        defer_spatial_indexes: drop the GiST indexes during the load and rebuild them at the end;
            None = automatically for files larger than `defer_above_bytes`.
        defer_above_bytes: file size above which indexes are deferred automatically.
        checks: geometry checks stored per surface: "fast" (vectorised over the batch: vertex
            count, planarity, area, unclosed rings), "full" (`db.citygml.checks.check_building`,
            adding self-intersection and outward wall normals; about 20 ms per building) or "none".
        huge_tree: passed to the reader (lift libxml2 limits for unusual files).
    """

    batch_size: int = 250
    defer_spatial_indexes: bool | None = None
    defer_above_bytes: int = 100 * 1024**2
    checks: str = "fast"
    huge_tree: bool = False


@dataclass(frozen=True)
class ImportSummary:
    """What an import wrote."""

    model_id: int
    name: str
    srs_name: str | None
    srid: int
    buildings: int
    parts: int
    surfaces: int
    appearances: int
    seconds: float
    replaced: bool


def model_srid(srs_name: str | None) -> int:
    """SRID for a model's geometries: EPSG code of its horizontal CRS, 0 when it has none or the
    name is unknown."""
    if not srs_name:
        return 0
    try:
        return horizontal_epsg(srs_name) or 0
    except UnknownCRSError:
        log.warning("CRS %r not resolvable: geometries get SRID 0", srs_name)
        return 0


def _vertical(srs_name: str | None) -> int | None:
    try:
        return vertical_epsg(srs_name) if srs_name else None
    except UnknownCRSError:
        return None


class _Batch:
    """Rows of one batch of top-level buildings, ready for COPY."""

    def __init__(self, model_id: int, srid: int, ordinal0: int) -> None:
        self.model_id = model_id
        self.srid = srid
        self.ordinal = ordinal0
        self.buildings: list[tuple] = []
        self.surfaces: list[tuple] = []
        self.appearances = AppearanceRows()
        self.n_buildings = 0
        self.n_parts = 0


def _batch_rows(
    conn: Connection, tops: Sequence[Building], model_id: int, srid: int, ordinal0: int, checks: str
) -> _Batch:
    """Turn a batch of top-level buildings (parts nested) into COPY rows with reserved ids."""
    flat: list[tuple[Building, Building, Building | None]] = []  # (building, root, parent)

    def walk(b: Building, root: Building, parent: Building | None) -> None:
        flat.append((b, root, parent))
        for p in b.parts:
            walk(p, root, b)

    for t in tops:
        walk(t, t, None)
    polys: list[Polygon] = [p for b, _, _ in flat for p in b.polygons]
    bids = reserve_ids(conn, "building", len(flat))
    sids = reserve_ids(conn, "surface", len(polys))
    row_of = {id(b): bid for (b, _, _), bid in zip(flat, bids, strict=True)}
    enc = encode_polygons(polys, srid)
    full = full_checks(tops) if checks == "full" else {}
    normals = {p.id: enc.normal[k] for k, p in enumerate(polys)}
    footprints = encode_footprints([b for b, _, _ in flat], normals, srid)
    batch = _Batch(model_id, srid, ordinal0)
    surface_row: dict[str, int] = {}
    k = 0
    for (b, root, parent), bid, fp in zip(flat, bids, footprints, strict=True):
        lo, hi = b.bounds() if any(True for _ in b.iter_polygons()) else (None, None)
        batch.buildings.append(
            (
                bid,
                model_id,
                b.id,
                row_of[id(parent)] if parent is not None else None,
                row_of[id(root)],
                b.is_part,
                batch.ordinal,
                b.name,
                b.srs_name,
                b.generated_id,
                Jsonb(jsonable(dict(b.attributes))),
                fp,
                encode_envelope(lo, hi, srid) if lo is not None else None,
            )
        )
        batch.ordinal += 1
        batch.n_parts += int(b.is_part)
        batch.n_buildings += int(not b.is_part)
        for j, p in enumerate(b.polygons):
            sid = sids[k]
            surface_row.setdefault(p.id, sid)
            ewkb = enc.ewkb[k]
            raw = None if ewkb is not None else Jsonb([r.coords.tolist() for r in p.rings])
            n = enc.normal[k]
            batch.surfaces.append(
                (
                    sid,
                    model_id,
                    bid,
                    j,
                    p.id,
                    p.generated_id,
                    [r.id for r in p.rings],
                    [r.generated_id for r in p.rings],
                    enc.ring_closed[k],
                    p.surface_class,
                    p.surface_id,
                    p.lod,
                    p.in_solid,
                    p.collection_id,
                    ewkb,
                    raw,
                    n.tolist() if np.all(np.isfinite(n)) else None,
                    float(enc.offset[k]) if np.isfinite(enc.offset[k]) else None,
                    float(enc.area[k]) if np.isfinite(enc.area[k]) else None,
                    surface_checks(checks, full, enc, k, p, b.id),
                )
            )
            k += 1
    for b, _, _ in flat:
        if b.appearances:
            collect_appearance_rows(
                batch.appearances,
                b.appearances,
                model_id=model_id,
                building_row=row_of[id(b)],
                surface_row=surface_row,
            )
    return batch


def _write_batch(conn: Connection, batch: _Batch) -> None:
    copy_rows(conn, "building", BUILDING_COLUMNS, batch.buildings)
    copy_rows(conn, "surface", SURFACE_COLUMNS, batch.surfaces)
    batch.appearances.write(conn, copy_rows, reserve_ids)


def _events(path: Path, huge_tree: bool) -> Iterator[tuple[str, Any]]:
    """("building", Building) in document order, then ("appearance", Appearance) for
    CityModel-level appearances that follow the buildings (when the reader reports them)."""
    stream = getattr(citygml_reader, "_Stream", None)
    if stream is None:  # pragma: no cover - reader without its event stream
        for b in citygml_reader.iter_buildings(path, huge_tree=huge_tree):
            yield "building", b
        return
    for kind, obj in stream(path, huge_tree).events():
        if kind in ("building", "appearance"):
            yield kind, obj


def _start_model(
    engine: Engine, header: ModelHeader, path: Path, name: str, srid: int, replace: bool
) -> tuple[int, bool]:
    """Create the `city_model` row (deleting an old one of that name with `replace`)."""
    with engine.begin() as conn:
        old = conn.execute(text("SELECT id FROM city_model WHERE name = :n FOR UPDATE"), {"n": name}).first()
        replaced = False
        if old is not None:
            if not replace:
                raise ModelExistsError(
                    f"city model {name!r} exists already (import with replace to overwrite)"
                )
            delete_model(conn, old[0])
            replaced = True
        model_id = conn.execute(
            text(
                "INSERT INTO city_model (name, srs_name, srid, vertical_epsg, citygml_version, gml_name, "
                "source_file, building_count, part_count, surface_count, state) "
                "VALUES (:name, :srs, :srid, :vert, :ver, :gname, :src, 0, 0, 0, 'importing') RETURNING id"
            ),
            {
                "name": name,
                "srs": header.srs_name,
                "srid": srid,
                "vert": _vertical(header.srs_name),
                "ver": header.version,
                "gname": header.name,
                "src": str(path.resolve()),
            },
        ).scalar_one()
        if header.appearances:
            rows = AppearanceRows()
            collect_appearance_rows(
                rows, header.appearances, model_id=model_id, building_row=None, surface_row={}
            )
            rows.write(conn, copy_rows, reserve_ids)
    return model_id, replaced


def _finish_model(conn: Connection, model_id: int, counts: dict[str, int], late: list[Appearance]) -> None:
    if late:
        rows = AppearanceRows()
        collect_appearance_rows(rows, late, model_id=model_id, building_row=None, surface_row={})
        rows.write(conn, copy_rows, reserve_ids)
    # texture targets not resolved within their batch (CityModel-level appearances, cross-building)
    conn.execute(
        text(
            "UPDATE texture_param tp SET surface_id = s.id FROM surface_data sd, appearance a, surface s "
            "WHERE tp.surface_data_id = sd.id AND sd.appearance_id = a.id AND a.city_model_id = :m "
            "AND tp.surface_id IS NULL AND s.city_model_id = :m AND s.gml_id = tp.target_gml_id"
        ),
        {"m": model_id},
    )
    box = conn.execute(
        text(
            "SELECT ST_XMin(e), ST_YMin(e), ST_ZMin(e), ST_XMax(e), ST_YMax(e), ST_ZMax(e), "
            "(SELECT srid FROM city_model WHERE id = :m) FROM (SELECT ST_3DExtent(envelope) AS e "
            "FROM building WHERE city_model_id = :m AND NOT is_part) x"
        ),
        {"m": model_id},
    ).one()
    envelope = None if box[0] is None else encode_envelope(np.array(box[:3]), np.array(box[3:6]), box[6])
    conn.execute(
        text(
            "UPDATE city_model SET building_count = :b, part_count = :p, surface_count = :s, "
            "state = 'complete', envelope = CAST(:env AS geometry) WHERE id = :m"
        ),
        {
            "m": model_id,
            "b": counts["buildings"],
            "p": counts["parts"],
            "s": counts["surfaces"],
            "env": envelope,
        },
    )


def import_citygml(
    db: Engine | Any,
    path: str | PathLike[str],
    *,
    name: str | None = None,
    replace: bool = False,
    options: ImportOptions | None = None,
) -> ImportSummary:
    """Import the CityGML file `path` as city model `name` (default: the file's stem).

    `db` is an Engine, a sessionmaker bound to one, or a URL. Raises `ModelExistsError` when the
    name exists and `replace` is false, `CityGMLError` (from the reader) for a bad file.
    """
    opts = options or ImportOptions()
    path = Path(path)
    name = name or path.stem
    engine = as_engine(db)
    t0 = time.perf_counter()
    header = citygml_reader.read_header(path, huge_tree=opts.huge_tree)
    srid = model_srid(header.srs_name)
    if opts.checks not in ("fast", "full", "none"):
        raise ValueError(f"ImportOptions.checks must be 'fast', 'full' or 'none', not {opts.checks!r}")
    defer = opts.defer_spatial_indexes
    if defer is None:
        defer = path.stat().st_size > opts.defer_above_bytes
    model_id, replaced = _start_model(engine, header, path, name, srid, replace)
    counts = {"buildings": 0, "parts": 0, "surfaces": 0, "appearances": len(header.appearances)}
    late: list[Appearance] = []
    ordinal = 0
    try:
        if defer:
            drop_spatial_indexes(engine)
        pending: list[Building] = []

        def flush() -> None:
            nonlocal ordinal
            with engine.begin() as conn:
                batch = _batch_rows(conn, pending, model_id, srid, ordinal, opts.checks)
                _write_batch(conn, batch)
            ordinal = batch.ordinal
            counts["buildings"] += batch.n_buildings
            counts["parts"] += batch.n_parts
            counts["surfaces"] += len(batch.surfaces)
            counts["appearances"] += batch.appearances.count
            pending.clear()

        for kind, obj in _events(path, opts.huge_tree):
            if kind == "appearance":
                late.append(obj)
                continue
            pending.append(obj)
            if len(pending) >= opts.batch_size:
                flush()
        if pending:
            flush()
        counts["appearances"] += len(late)
        with engine.begin() as conn:
            _finish_model(conn, model_id, counts, late)
    except BaseException:
        with engine.begin() as conn:
            delete_model(conn, model_id)
        raise
    finally:
        if defer:
            create_spatial_indexes(engine)
    with engine.begin() as conn:
        for table in ("building", "surface"):
            conn.exec_driver_sql(f"ANALYZE {table}")
    return ImportSummary(
        model_id=model_id,
        name=name,
        srs_name=header.srs_name,
        srid=srid,
        buildings=counts["buildings"],
        parts=counts["parts"],
        surfaces=counts["surfaces"],
        appearances=counts["appearances"],
        seconds=time.perf_counter() - t0,
        replaced=replaced,
    )

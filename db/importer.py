"""Import a CityGML file into the city model database, streamed, in batches.

In: a CityGML file (1.0/2.0/3.0; read by `db.citygml.reader`, never whole in memory) and a
database (Engine, sessionmaker or URL) migrated to head. Out: one `city_model` row with its
`building` (parts point to parent and root), `surface` (POLYGON Z in the model SRID, ring ids,
plane, geometry checks) and the file's appearances (`appearance` → `surface_data` →
`texture_param`); an `ImportSummary`.

Buildings are written with `COPY` in batches of `ImportOptions.batch_size` top-level buildings,
one transaction per batch. The COPY text of a batch (geometries as hex EWKB built in Python with
numpy, planes, footprints, envelopes, checks: `db.import_rows`) is made where the file is read; for
big files that is a separate reader process (`db.import_stream`), so parsing overlaps with the
database's work. Row ids are reserved from the sequences in one round trip per batch, so parents,
roots, surfaces and texture targets are linked without further queries. For big files the GiST
indexes are dropped during the load and rebuilt once at the end
(`ImportOptions.defer_spatial_indexes`). A model name that exists is refused (`ModelExistsError`)
unless `replace=True`: the new model is then loaded under a temporary name and replaces the old
one in the final transaction, so a failed import leaves the old model as it was. A failed import
deletes what it wrote.
"""

from __future__ import annotations

import logging
import time
import uuid
from dataclasses import dataclass, field
from functools import partial
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import psycopg
from sqlalchemy import Connection, Engine, text
from sqlalchemy.exc import IntegrityError

from db.appearance_images import store_appearance_images
from db.appearance_rows import AppearanceRows, collect_appearance_rows
from db.citygml import reader as citygml_reader
from db.errors import InputDataError, ModelExistsError
from db.geomcodec import encode_envelope
from db.import_rows import BUILDING_TAIL, SURFACE_TAIL, BatchLines, batch_lines
from db.import_stream import BatchStream
from db.ops import (
    copy_block,
    copy_rows,
    create_spatial_indexes,
    delete_model,
    drop_spatial_indexes,
    reserve_ids,
)
from db.session import as_engine
from workers.pipeline.geometry.citymodel import Appearance, ModelHeader
from workers.pipeline.geometry.crs import UnknownCRSError, horizontal_epsg, vertical_epsg

__all__ = ["ImportOptions", "ImportSummary", "import_citygml", "model_srid"]

log = logging.getLogger(__name__)

BUILDING_COLUMNS = ("id", "city_model_id", "parent_id", "root_id", "ordinal", *BUILDING_TAIL)
SURFACE_COLUMNS = ("id", "city_model_id", "building_id", *SURFACE_TAIL)


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
        parallel_read: parse the file in a separate reader process while this one writes (None:
            for files larger than `parallel_above_bytes`; always in-process inside daemonic
            workers, which may not have children).
        import_images: store the image files of the file's textures that lie in its folder.
    """

    batch_size: int = 250
    defer_spatial_indexes: bool | None = None
    defer_above_bytes: int = 100 * 1024**2
    checks: str = "fast"
    huge_tree: bool = False
    parallel_read: bool | None = None
    parallel_above_bytes: int = 16 * 1024**2
    import_images: bool = True


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
    #: peak RSS of the reader process (MB) when the file was read in parallel.
    reader_peak_rss_mb: float | None = None
    #: seconds: waiting for the reader, writing batches, finishing, rebuilding spatial indexes.
    timings_s: dict[str, float] = field(default_factory=dict)


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


def _write_lines(
    conn: Connection, lines: BatchLines, model_id: int, ordinal0: int, image_dir: Path | None = None
) -> None:
    """Reserve ids, link parents/roots/owners and COPY one batch; then its appearances."""
    bids = reserve_ids(conn, "building", len(lines.building_tails))
    sids = reserve_ids(conn, "surface", len(lines.surface_tails))
    m = str(model_id)
    null = "\\N"
    b_lines = [
        f"{bids[i]}\t{m}\t{bids[p] if p >= 0 else null}\t{bids[r]}\t{ordinal0 + i}\t{tail}\n"
        for i, (p, r, tail) in enumerate(zip(lines.parent, lines.root, lines.building_tails, strict=True))
    ]
    copy_block(conn, "building", BUILDING_COLUMNS, b_lines)
    s_lines = [
        f"{sids[k]}\t{m}\t{bids[o]}\t{tail}\n"
        for k, (o, tail) in enumerate(zip(lines.owner, lines.surface_tails, strict=True))
    ]
    copy_block(conn, "surface", SURFACE_COLUMNS, s_lines)
    if lines.appearances:
        surface_row: dict[str, int] = {}
        for k, pid in enumerate(lines.polygon_ids):
            surface_row.setdefault(pid, sids[k])
        rows = AppearanceRows()
        for i, apps in lines.appearances:
            collect_appearance_rows(
                rows, apps, model_id=model_id, building_row=bids[i], surface_row=surface_row
            )
        app_ids = rows.write(conn, copy_rows, reserve_ids)
        if image_dir is not None:
            store_appearance_images(conn, app_ids, image_dir)


def _start_model(
    engine: Engine,
    header: ModelHeader,
    path: Path,
    name: str,
    srid: int,
    replace: bool,
    image_dir: Path | None = None,
) -> tuple[int, bool]:
    """Create the `city_model` row. When a model of that name exists (and `replace` is set) the
    new one is loaded under a temporary name and takes over in `_finish_model`, so the old model
    stays intact until the new one is complete."""
    with engine.begin() as conn:
        old = conn.execute(text("SELECT id FROM city_model WHERE name = :n"), {"n": name}).first()
        replaced = old is not None
        if replaced and not replace:
            raise ModelExistsError(f"city model {name!r} exists already (import with replace to overwrite)")
        model_id = conn.execute(
            text(
                "INSERT INTO city_model (name, srs_name, srid, vertical_epsg, citygml_version, gml_name, "
                "source_file, building_count, part_count, surface_count, state) "
                "VALUES (:name, :srs, :srid, :vert, :ver, :gname, :src, 0, 0, 0, 'importing') RETURNING id"
            ),
            {
                "name": f"{name}#importing-{uuid.uuid4().hex}" if replaced else name,
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
            app_ids = rows.write(conn, copy_rows, reserve_ids)
            if image_dir is not None:
                store_appearance_images(conn, app_ids, image_dir)
    return model_id, replaced


def _finish_model(
    conn: Connection,
    model_id: int,
    name: str,
    counts: dict[str, int],
    late: list[Appearance],
    image_dir: Path | None = None,
) -> None:
    """Late appearances, cross-batch texture targets, counts, envelope; the model takes its name
    (replacing an older model of that name in the same transaction)."""
    old = conn.execute(
        text("SELECT id FROM city_model WHERE name = :n AND id <> :m FOR UPDATE"), {"n": name, "m": model_id}
    ).first()
    if old is not None:
        delete_model(conn, old[0])
    conn.execute(text("UPDATE city_model SET name = :n WHERE id = :m"), {"n": name, "m": model_id})
    if late:
        rows = AppearanceRows()
        collect_appearance_rows(rows, late, model_id=model_id, building_row=None, surface_row={})
        app_ids = rows.write(conn, copy_rows, reserve_ids)
        if image_dir is not None:
            store_appearance_images(conn, app_ids, image_dir)
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
    image_dir = path.resolve().parent if opts.import_images else None
    model_id, replaced = _start_model(engine, header, path, name, srid, replace, image_dir)
    counts = {"buildings": 0, "parts": 0, "surfaces": 0, "appearances": len(header.appearances)}
    late: list[Appearance] = []
    ordinal = 0
    timings = {"wait_for_reader": 0.0, "write": 0.0}
    try:
        if defer:
            drop_spatial_indexes(engine)
        stream = BatchStream(
            path,
            batch_size=opts.batch_size,
            transform=partial(batch_lines, srid=srid, checks=opts.checks),
            huge_tree=opts.huge_tree,
            parallel=(
                opts.parallel_read
                if opts.parallel_read is not None
                else path.stat().st_size > opts.parallel_above_bytes
            ),
        )
        t_wait = time.perf_counter()
        for kind, obj in stream:
            timings["wait_for_reader"] += time.perf_counter() - t_wait
            if kind == "appearance":
                late.append(obj)
                t_wait = time.perf_counter()
                continue
            t_write = time.perf_counter()
            with engine.begin() as conn:
                _write_lines(conn, obj, model_id, ordinal, image_dir=image_dir)
            timings["write"] += time.perf_counter() - t_write
            ordinal += len(obj.building_tails)
            n_parts = sum(obj.is_part)
            counts["buildings"] += len(obj.is_part) - n_parts
            counts["parts"] += n_parts
            counts["surfaces"] += len(obj.surface_tails)
            counts["appearances"] += sum(len(a) for _, a in obj.appearances)
            t_wait = time.perf_counter()
        counts["appearances"] += len(late)
        t_fin = time.perf_counter()
        with engine.begin() as conn:
            _finish_model(conn, model_id, name, counts, late, image_dir=image_dir)
        with engine.begin() as conn:
            # planner statistics for the key columns (geometry statistics are slow to gather)
            conn.exec_driver_sql("ANALYZE building (city_model_id, root_id, parent_id, is_part, ordinal)")
            conn.exec_driver_sql("ANALYZE surface (city_model_id, building_id)")
        timings["finish"] = time.perf_counter() - t_fin
    except BaseException as exc:
        with engine.begin() as conn:
            delete_model(conn, model_id)
        if isinstance(exc, IntegrityError | psycopg.errors.IntegrityError):
            orig = getattr(exc, "orig", None) or exc
            detail = " ".join(str(orig).split())
            raise InputDataError(f"{path}: cannot be stored as one model ({detail})") from exc
        raise
    finally:
        if defer:
            t_idx = time.perf_counter()
            create_spatial_indexes(engine)
            timings["spatial_indexes"] = time.perf_counter() - t_idx
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
        reader_peak_rss_mb=stream.peak_rss_mb,
        timings_s={k: round(v, 3) for k, v in timings.items()},
    )

"""Import a CityGML file into the city model database, streamed, all or nothing.

In: a CityGML file (1.0/2.0/3.0; read by `db.citygml.reader`, never whole in memory) and a
database (Engine, sessionmaker or URL) migrated to head. Out: one `city_model` row with its
`building` (parts point to parent and root), `surface` (POLYGON Z in the model SRID, ring ids,
plane, geometry checks) and the file's appearances (`appearance` → `surface_data` →
`texture_param`); an `ImportSummary`.

The whole model is written in ONE transaction on one connection: `COPY` in batches of
`ImportOptions.batch_size` top-level buildings, then the final step (late appearances,
cross-batch texture targets, counts, envelope, state `complete`; with `replace` the old model is
deleted and the new one takes its name) and the commit. Other sessions never see a partial model,
whatever stops the import: an error or SIGINT/SIGTERM/SIGHUP (turned into `ImportInterrupted`
while the import runs in the main thread: the running statement is cancelled, the transaction
rolled back, the reader process stopped) or SIGKILL (the server rolls back the transaction of a
connection that is gone; `client_connection_check_interval` makes it notice within a second even
in the middle of a statement). Nothing is dropped or locked that other users need: COPY of new
rows takes only the row-exclusive table locks every writer takes, the spatial (GiST) indexes stay
in place and usable throughout, and rows of other models are touched only by a replacement's
final step. Two imports of one name do not wait on each other: the second is refused
(`ModelExistsError`). The COPY text of a batch (geometries as hex EWKB built in Python with
numpy, planes, footprints, envelopes, checks: `db.import_rows`) is made where the file is read;
for big files that is a separate reader process, or two, one per part (`db.import_stream`), so
parsing overlaps with the database's work; the readers start before anything else (before the
database layer loads, when the command line starts them: `db.import_stream.prestart`), and the
second part's batches are written whenever the first reader has none ready, numbered after the
first part (`db.import_model.renumber` corrects them where its count, estimated from its bytes,
was wrong). The model row's steps (start, finish, statistics) are in `db.import_model`.
Where the role may, the foreign keys of the copied rows (all pointing to rows of this import)
are not checked row by row (`own_links_unchecked`).
Row ids are reserved from the sequences in one round trip per batch, so parents, roots, surfaces
and texture targets are linked without further queries.

A model name that exists is refused (`ModelExistsError`) unless `replace=True`. Before it starts,
an import removes models left in state `importing` by dead imports (`db.ops.remove_dead_imports`;
this importer never commits such a row, older versions did), as `citytherm db repair` does.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from os import PathLike
from pathlib import Path
from typing import Any

import psycopg
from sqlalchemy import Connection, Engine, text
from sqlalchemy.exc import IntegrityError

from db.appearance_images import store_appearance_images
from db.appearance_rows import AppearanceRows, collect_appearance_rows
from db.citygml import reader as citygml_reader
from db.errors import InputDataError
from db.import_model import analyze, finish_model, renumber, start_model
from db.import_options import ImportOptions
from db.import_rows import BUILDING_TAIL, SURFACE_TAIL, BatchLines, batch_lines
from db.import_signals import ImportInterrupted, Interrupts, abandon
from db.import_stream import BatchStream
from db.ops import (
    copy_block,
    copy_rows,
    remove_dead_imports,
    reserve_ids,
    spatial_index_problems,
)
from db.session import as_engine
from db.settings import Settings
from db.srid import database_srid, model_epsg, to_database
from workers.pipeline.geometry.citymodel import Appearance, ModelHeader

__all__ = ["ImportInterrupted", "ImportOptions", "ImportProgress", "ImportSummary", "import_citygml"]

log = logging.getLogger(__name__)

BUILDING_COLUMNS = ("id", "city_model_id", "parent_id", "root_id", "ordinal", *BUILDING_TAIL)
SURFACE_COLUMNS = ("id", "city_model_id", "building_id", *SURFACE_TAIL)


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
    #: peak RSS of the reader process (MB; the largest of them) when the file was read in parallel.
    reader_peak_rss_mb: float | None = None
    #: CPU seconds of each reader process (start-up included), in the order they read the file.
    reader_cpu_s: tuple[float, ...] = ()
    #: seconds: starting (dead imports removed, model row), waiting for the reader, writing
    #: batches, the final step, the commit, planner statistics afterwards.
    timings_s: dict[str, float] = field(default_factory=dict)
    #: models left `importing` by dead imports that this import removed first.
    removed_dead_imports: int = 0


@dataclass(frozen=True)
class ImportProgress:
    """Where an import is, for a progress display: `stage` is "writing" (after each batch),
    "finishing" (all batches written, final step running) or "committed"."""

    stage: str
    buildings: int
    parts: int
    surfaces: int
    seconds: float


def model_crs(path: Path, header: ModelHeader, crs: str | None, huge_tree: bool = False) -> tuple[str, int]:
    """The model's CRS name and its horizontal EPSG code: `crs` when given, else the file's
    `srsName` (the model's envelope, else its first building's). Raises `InputDataError` naming
    the file when there is none or it is unknown: a model is never stored without a CRS."""
    srs = crs or header.srs_name
    if not srs:
        first = next(iter(citygml_reader.iter_buildings(path, huge_tree=huge_tree)), None)
        srs = first.srs_name if first is not None else None
    return srs or "", model_epsg(srs, what=f"{path}")


def _write_lines(
    conn: Connection, lines: BatchLines, model_id: int, ordinal0: int, image_dir: Path | None = None
) -> list[int]:
    """Reserve ids, link parents/roots/owners and COPY one batch; then its appearances. Returns
    the building row ids."""
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
    return bids


def _may_skip_link_checks(conn: Connection) -> bool:
    """True when this session may set `session_replication_role` (superuser, or SET granted:
    PostgreSQL 15+) and the schema has no trigger of its own (replica mode would skip it too)."""
    su, version, user_triggers = conn.execute(
        text(
            "SELECT current_setting('is_superuser') = 'on', current_setting('server_version_num')::int, "
            "EXISTS (SELECT 1 FROM pg_trigger t JOIN pg_class c ON c.oid = t.tgrelid "
            "WHERE NOT t.tgisinternal AND c.relnamespace = CAST(current_schema() AS regnamespace))"
        )
    ).one()
    if user_triggers:
        return False
    if su:
        return True
    return version >= 150000 and bool(
        conn.execute(text("SELECT has_parameter_privilege('session_replication_role', 'SET')")).scalar_one()
    )


def import_citygml(
    db: Engine | Any,
    path: str | PathLike[str],
    *,
    name: str | None = None,
    replace: bool = False,
    options: ImportOptions | None = None,
    progress: Callable[[ImportProgress], None] | None = None,
    readers: BatchStream | None = None,
) -> ImportSummary:
    """Import the CityGML file `path` as city model `name` (default: the file's stem), all or
    nothing (module docstring).

    `db` is an Engine, a sessionmaker bound to one, or a URL. `progress` is called after every
    batch and at the final step. `readers`: the reader processes of this file started earlier
    with the same options (`db.import_stream.prestart`, by a command line before it loads the
    database layer); the import owns them from the call on (closes them whatever happens).
    Raises `ModelExistsError` when the name exists and `replace` is
    false (or another session is importing that name), `CityGMLError` (from the reader) for a bad
    file, `InputDataError` for a file that cannot be one model (e.g. duplicate building ids),
    `ImportInterrupted` when SIGINT, SIGTERM or SIGHUP stopped it.
    """
    opts = options or ImportOptions()
    path = Path(path)
    name = name or path.stem
    try:
        if opts.checks not in ("fast", "full", "none"):
            raise ValueError(f"ImportOptions.checks must be 'fast', 'full' or 'none', not {opts.checks!r}")
        if readers is not None and not _readers_fit(readers, path, opts):
            readers.close()
            readers = None
        stream = readers or BatchStream(
            path,
            batch_size=opts.batch_size,
            transform=None,
            split_above_bytes=opts.split_above_bytes,
            split_at=opts.split_at,
            huge_tree=opts.huge_tree,
            parallel=opts.reads_in_parallel(path) if path.is_file() else False,
        )
        # the readers load their modules and parse while the header is read and the database asked
        stream.spawn()
    except BaseException:
        if readers is not None:
            readers.close()
        raise
    engine = None
    try:
        engine = as_engine(db)
        return _import(engine, path, name, replace, opts, progress, stream)
    finally:
        stream.close()
        if engine is not None and isinstance(db, str | Settings):  # an engine of our own: close it
            engine.dispose()


def _readers_fit(readers: BatchStream, path: Path, opts: ImportOptions) -> bool:
    """True when `readers` (started earlier) read `path` as `opts` would have them."""
    return (
        readers.path.resolve() == path.resolve()
        and readers.batch_size == opts.batch_size
        and readers.huge_tree == opts.huge_tree
        and readers.split_above_bytes == opts.split_above_bytes
        and readers.split_at == opts.split_at
        and readers.transform is None
    )


def _import(
    engine: Engine,
    path: Path,
    name: str,
    replace: bool,
    opts: ImportOptions,
    progress: Callable[[ImportProgress], None] | None,
    stream: BatchStream,
) -> ImportSummary:
    t0 = time.perf_counter()
    header = citygml_reader.read_header(path, huge_tree=opts.huge_tree)
    srs_name, srid = model_crs(path, header, opts.crs, opts.huge_tree)
    header = dataclasses.replace(header, srs_name=srs_name)
    with engine.connect() as conn:
        db_srid = database_srid(conn)
    to_db = to_database(srs_name, db_srid)
    image_dir = path.resolve().parent if opts.import_images else None
    counts = {"buildings": 0, "parts": 0, "surfaces": 0, "appearances": len(header.appearances)}
    late: list[Appearance] = []
    ordinal = 0
    # a split file's second part: its buildings' ordinals follow the first part's, whose count is
    # estimated before its batches arrive (`BatchStream.first_part_estimate`) and checked at the end
    ordinal2 = 0
    second_ids: list[int] = []
    timings = {"wait_for_reader": 0.0, "write": 0.0}

    def report(stage: str) -> None:
        if progress is not None:
            progress(
                ImportProgress(
                    stage, counts["buildings"], counts["parts"], counts["surfaces"], time.perf_counter() - t0
                )
            )

    # an identity transform is left out: the reader process then never loads PROJ
    to_db_or_none = None if to_db.identity else to_db
    transform = partial(batch_lines, srid=db_srid, checks=opts.checks, to_db=to_db_or_none)
    with Interrupts() as interrupts, stream, engine.connect() as conn:
        try:
            stream.start(transform)  # the readers parse while the database is prepared
            interrupts.conn = conn.connection.driver_connection
            dead = [d for d in remove_dead_imports(engine) if d.status == "removed"]
            for d in dead:
                log.warning("removed model %r (id %d) left 'importing' by a dead import", d.name, d.model_id)
            for index, table, column, problem in spatial_index_problems(conn):
                log.warning(
                    "spatial index %s on %s(%s) is %s: run `citytherm db repair`",
                    index,
                    table,
                    column,
                    problem,
                )
            skip_checks = opts.own_links_unchecked and _may_skip_link_checks(conn)
            model_id, replaced = start_model(conn, header, path, name, srid, replace, image_dir, skip_checks)
            timings["start"] = time.perf_counter() - t0
            t_wait = time.perf_counter()
            for kind, obj in stream:
                timings["wait_for_reader"] += time.perf_counter() - t_wait
                if kind == "appearance":
                    late.append(obj)
                    t_wait = time.perf_counter()
                    continue
                t_write = time.perf_counter()
                if kind == "batch2":  # second part of a split file, numbered after the first
                    o0 = (stream.first_part_estimate or 0) + ordinal2
                    second_ids += _write_lines(conn, obj, model_id, o0, image_dir=image_dir)
                    ordinal2 += len(obj.building_tails)
                else:
                    _write_lines(conn, obj, model_id, ordinal, image_dir=image_dir)
                    ordinal += len(obj.building_tails)
                timings["write"] += time.perf_counter() - t_write
                n_parts = sum(obj.is_part)
                counts["buildings"] += len(obj.is_part) - n_parts
                counts["parts"] += n_parts
                counts["surfaces"] += len(obj.surface_tails)
                counts["appearances"] += sum(len(a) for _, a in obj.appearances)
                report("writing")
                t_wait = time.perf_counter()
            if second_ids and ordinal != stream.first_part_estimate:
                renumber(conn, second_ids, ordinal - (stream.first_part_estimate or 0))
            counts["appearances"] += len(late)
            report("finishing")
            t_fin = time.perf_counter()
            finish_model(conn, model_id, name, counts, late, image_dir=image_dir)
            t_commit = time.perf_counter()
            timings["finish"] = t_commit - t_fin
            # from the commit on a signal waits until the import is over: it must not report a
            # committed model as rolled back
            interrupts.depth += 1
            conn.commit()
            timings["commit"] = time.perf_counter() - t_commit
        except BaseException as exc:
            with interrupts.deferred():
                abandon(conn)
                stream.close()
            if isinstance(exc, IntegrityError | psycopg.errors.IntegrityError):
                orig = getattr(exc, "orig", None) or exc
                detail = " ".join(str(orig).split())
                raise InputDataError(f"{path}: cannot be stored as one model ({detail})") from exc
            raise
    report("committed")
    t_an = time.perf_counter()
    analyze(engine)
    timings["analyze"] = time.perf_counter() - t_an
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
        reader_cpu_s=tuple(round(c, 3) for c in stream.reader_cpu_s),
        timings_s={k: round(v, 3) for k, v in timings.items()},
        removed_dead_imports=len(dead),
    )

"""The steps of an import on its model row (`db.importer`): start (name lock, `city_model` row in
state `importing`, model-level appearances), finish (late appearances, cross-batch texture
targets, counts, envelope, the name taken over, state `complete`), the second part of a split
file renumbered, and the planner statistics gathered after the commit.

In: the import's connection (SQLAlchemy `Connection`, inside its one transaction) or engine.
Out: rows of `city_model` and of the appearance tables; ids.
"""

from __future__ import annotations

import uuid
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from sqlalchemy import Connection, Engine, text

from db.appearance_images import store_appearance_images
from db.appearance_rows import AppearanceRows, collect_appearance_rows
from db.errors import ModelExistsError
from db.geomcodec import encode_envelope
from db.ops import IMPORT_MODEL_LOCK, IMPORT_NAME_LOCK, copy_rows, delete_model, reserve_ids
from workers.pipeline.geometry.citymodel import Appearance, ModelHeader
from workers.pipeline.geometry.crs import UnknownCRSError, vertical_epsg

__all__ = ["analyze", "finish_model", "renumber", "start_model"]


def _vertical(srs_name: str | None) -> int | None:
    try:
        return vertical_epsg(srs_name) if srs_name else None
    except UnknownCRSError:
        return None


def renumber(conn: Connection, building_ids: list[int], delta: int) -> None:
    """Shift the ordinals of the buildings `building_ids` by `delta` (the second part of a split
    file when the first part's building count estimated from its bytes was wrong)."""
    conn.execute(
        text("UPDATE building SET ordinal = ordinal + :d WHERE id = ANY(:ids)"),
        {"d": delta, "ids": building_ids},
    )


#: planner statistics of the key columns of the tables an import fills (geometry statistics are
#: slow to gather)
_ANALYZE = (
    "ANALYZE surface (city_model_id, building_id)",
    "ANALYZE building (city_model_id, root_id, parent_id, is_part, ordinal)",
)


def analyze(engine: Engine) -> None:
    """`_ANALYZE`, the two statements at once on two connections (two server processes: the
    import's last step takes as long as the larger table's alone)."""

    def run(sql: str) -> None:
        with engine.begin() as conn:
            conn.exec_driver_sql(sql)

    with ThreadPoolExecutor(max_workers=len(_ANALYZE)) as pool:
        list(pool.map(run, _ANALYZE))


def start_model(
    conn: Connection,
    header: ModelHeader,
    path: Path,
    name: str,
    srid: int,
    replace: bool,
    image_dir: Path | None = None,
    skip_link_checks: bool = False,
) -> tuple[int, bool]:
    """Begin the import's transaction: take the name lock, create the `city_model` row. When a
    model of that name exists (and `replace` is set) the new one is written under a temporary name
    and takes over in `finish_model`, so the old model stays as it is until the commit."""
    free = conn.execute(
        text("SELECT pg_try_advisory_xact_lock(:ns, hashtext(:n))"), {"ns": IMPORT_NAME_LOCK, "n": name}
    ).scalar_one()
    if not free:
        raise ModelExistsError(f"city model {name!r} is being imported by another session")
    # who we are for pg_stat_activity; the server notices a vanished client within a second
    # (PostgreSQL 14+), even while a statement of ours runs or waits for a lock
    conn.execute(
        text(
            "SELECT set_config('application_name', :app, true), "
            "CASE WHEN current_setting('server_version_num')::int >= 140000 "
            "THEN set_config('client_connection_check_interval', '1000', true) END"
        ),
        {"app": f"citytherm import {name}"[:63]},
    )
    if skip_link_checks:  # until `finish_model`: the rows copied link only to rows of this import
        conn.execute(text("SET LOCAL session_replication_role = replica"))
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
    conn.execute(text("SELECT pg_advisory_xact_lock(:ns, :m)"), {"ns": IMPORT_MODEL_LOCK, "m": model_id})
    if header.appearances:
        rows = AppearanceRows()
        collect_appearance_rows(
            rows, header.appearances, model_id=model_id, building_row=None, surface_row={}
        )
        app_ids = rows.write(conn, copy_rows, reserve_ids)
        if image_dir is not None:
            store_appearance_images(conn, app_ids, image_dir)
    return model_id, replaced


def finish_model(
    conn: Connection,
    model_id: int,
    name: str,
    counts: dict[str, int],
    late: list[Appearance],
    image_dir: Path | None = None,
) -> None:
    """Late appearances, cross-batch texture targets, counts, envelope; the model takes its name
    (replacing an older model of that name in the same transaction); foreign keys act again."""
    if conn.execute(text("SELECT current_setting('session_replication_role') <> 'origin'")).scalar_one():
        conn.execute(text("SET LOCAL session_replication_role = origin"))
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
            "Find_SRID(current_schema()::text, 'building', 'envelope') "
            "FROM (SELECT ST_3DExtent(envelope) AS e FROM building "
            "WHERE city_model_id = :m AND NOT is_part) x"
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

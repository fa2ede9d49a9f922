"""Write one building unit's result into the database, in one transaction, idempotently.

In: a `Session`, the job id, the city model id and a `workers.pipeline.results.BuildingResult`
(appearance with `ParameterizedTexture`s whose `image_uri` is a tile name, uint16 tiles, per-surface
statistics in the radiometry unit, frame poses, anomalies). Out: rows in `appearance` (theme, job,
building), `tex_image` (16-bit PNG bytes, size, radiometry, sha256), `surface_data`,
`texture_param`, `surface_thermal` (kelvin, with each facade's GeoJSON feature text:
`db.facade_features`), `frame_pose`, `thermal_anomaly`; the job unit marked successful when it
exists.

Idempotent: the rows of (job, building) are deleted and written again inside one savepoint, under a
transaction-level advisory lock on (job, building), and a partial unique index allows one job
appearance per building; a failure half way rolls the savepoint back and leaves the previous state.
"""

from __future__ import annotations

import hashlib
import json
import uuid
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from psycopg.types.json import Jsonb
from sqlalchemy import Connection, text
from sqlalchemy.orm import Session

from db.appearance_rows import AppearanceRows, collect_appearance_rows
from db.errors import InputDataError, NotFoundError
from db.facade_features import FACADE_FIGURE_COLUMNS, write_feature_texts
from db.geomcodec import encode_point_z, encode_polygon_z
from db.jobs import create_job
from db.ops import copy_rows, reserve_ids
from db.srid import database_srid, to_database
from workers.pipeline.geometry.citymodel import Appearance, ParameterizedTexture
from workers.pipeline.geometry.manifest import Radiometry
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.transform import CrsTransform
from workers.pipeline.results import BuildingResult, TextureTile

__all__ = ["StoredResult", "create_job", "encode_tile_png", "store_building_result", "to_kelvin"]

_STAT_KEYS = ("mean", "median", "std", "min", "max", "p05", "p25", "p75", "p95")
TEX_IMAGE_COLUMNS = (
    "appearance_id",
    "uri",
    "mime_type",
    "image",
    "width",
    "height",
    "bit_depth",
    "radiometry_scale",
    "radiometry_offset",
    "radiometry_unit",
    "sha256",
)
THERMAL_COLUMNS = (
    "appearance_id",
    "surface_id",
    "texels_total",
    "texels_observed",
    "observed_share",
    "frames_used",
    "resolution_m",
    "view_angle_deg",
    "mean_k",
    "median_k",
    "std_k",
    "min_k",
    "max_k",
    "p05_k",
    "p25_k",
    "p75_k",
    "p95_k",
    "temperature",
    "unit",
    "resolution_px_per_m",
    "best_resolution_m",
    "mean_observations",
    "reason",
    *FACADE_FIGURE_COLUMNS,
)
POSE_COLUMNS = (
    "job_id",
    "building_id",
    "frame_index",
    "status",
    "prior_center",
    "prior_rotation",
    "refined_center",
    "refined_rotation",
    "center",
    "rms_px",
    "matches",
)
ANOMALY_COLUMNS = (
    "job_id",
    "appearance_id",
    "building_id",
    "surface_id",
    "kind",
    "outline",
    "centre",
    "area_m2",
    "peak_delta_k",
    "mean_delta_k",
    "anomaly_id",
    "frames",
    "best_resolution_m",
    "confidence",
)


@dataclass(frozen=True)
class StoredResult:
    """Row ids of what `store_building_result` wrote."""

    appearance_id: int
    building_id: int
    images: int
    textured_surfaces: int
    surfaces: int
    poses: int
    anomalies: int


def encode_tile_png(tile: TextureTile) -> bytes:
    """A tile's `(H, W)` uint16 DNs -> single-channel 16-bit PNG bytes (OpenCV's encoder)."""
    dn = np.asarray(tile.dn)
    if dn.ndim != 2 or dn.dtype != np.uint16:
        raise InputDataError(f"tile {tile.name!r}: expected a (H, W) uint16 array, got {dn.dtype} {dn.shape}")
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(dn))
    if not ok:  # pragma: no cover - OpenCV failure
        raise InputDataError(f"tile {tile.name!r}: PNG encoding failed")
    return buf.tobytes()


def to_kelvin(value: float | None, unit: str) -> float | None:
    """A temperature in `unit` -> kelvin; None for
    `counts` (no physical meaning) and for non-finite values.

    >>> to_kelvin(20.0, "degC")
    293.15
    """
    if value is None or not np.isfinite(value) or unit == "counts":
        return None
    if unit == "degC":
        return float(value) + 273.15
    return float(value)


def _f(v: float | None) -> float | None:
    return None if v is None or not np.isfinite(v) else float(v)


def _json(v: Any) -> str:
    return json.dumps(v)


def _building_row(conn: Connection, model_id: int, gml_id: str) -> int:
    row = conn.execute(
        text("SELECT id FROM building WHERE city_model_id = :m AND gml_id = :g AND NOT is_part"),
        {"m": model_id, "g": gml_id},
    ).first()
    if row is None:
        raise NotFoundError(f"building {gml_id!r} not found in city model {model_id}")
    return int(row[0])


def _check_result(result: BuildingResult, surface_row: Mapping[str, int]) -> None:
    """Refuse a result whose references do not resolve, before anything is written."""
    tiles = {t.name for t in result.tiles}
    app = result.appearance
    if app is not None:
        for sd in app.surface_data:
            if isinstance(sd, ParameterizedTexture):
                if sd.image_uri not in tiles:
                    raise InputDataError(f"texture {sd.id!r}: image {sd.image_uri!r} is not among the tiles")
                for t in sd.targets:
                    if t.polygon_id not in surface_row:
                        raise InputDataError(
                            f"texture {sd.id!r}: target polygon {t.polygon_id!r} is not in building "
                            f"{result.building_id!r}"
                        )
    for s in result.surfaces:
        if s.polygon_id not in surface_row:
            raise InputDataError(
                f"statistics for polygon {s.polygon_id!r}, not in building {result.building_id!r}"
            )


def _write(
    conn: Connection,
    *,
    job_id: uuid.UUID,
    model_id: int,
    result: BuildingResult,
    theme: str,
    srid: int,
    to_db: CrsTransform,
    priors: Mapping[int, Pose] | None,
) -> StoredResult:
    bid = _building_row(conn, model_id, result.building_id)
    conn.execute(
        text("SELECT pg_advisory_xact_lock(hashtext(:k))"), {"k": f"citytherm-result:{job_id}:{bid}"}
    )
    surface_row = {
        g: int(i)
        for i, g in conn.execute(
            text(
                "SELECT s.id, s.gml_id FROM surface s JOIN building b ON b.id = s.building_id "
                "WHERE b.root_id = :b ORDER BY b.ordinal DESC, s.ordinal DESC"
            ),
            {"b": bid},
        ).all()
    }
    _check_result(result, surface_row)
    p = {"j": job_id, "b": bid}
    conn.execute(text("DELETE FROM appearance WHERE job_id = :j AND building_id = :b"), p)
    conn.execute(text("DELETE FROM frame_pose WHERE job_id = :j AND building_id = :b"), p)
    conn.execute(text("DELETE FROM thermal_anomaly WHERE job_id = :j AND building_id = :b"), p)
    rad: Radiometry = result.radiometry
    app = result.appearance or Appearance(theme=theme, surface_data=())
    rows = AppearanceRows()
    collect_appearance_rows(
        rows,
        [app],
        model_id=model_id,
        building_row=bid,
        surface_row=surface_row,
        job_id=job_id,
        radiometry={"unit": rad.unit, "scale": rad.scale, "offset": rad.offset},
    )
    (aid,) = rows.write(conn, copy_rows, reserve_ids)
    used = {sd.image_uri for sd in app.surface_data if isinstance(sd, ParameterizedTexture)}
    img_rows = []
    for tile in result.tiles:
        if tile.name not in used:
            continue
        png = encode_tile_png(tile)
        h, w = tile.dn.shape
        img_rows.append(
            (
                aid,
                tile.name,
                "image/png",
                png,
                w,
                h,
                16,
                rad.scale,
                rad.offset,
                rad.unit,
                hashlib.sha256(png).hexdigest(),
            )
        )
    copy_rows(conn, "tex_image", TEX_IMAGE_COLUMNS, img_rows)
    conn.execute(
        text(
            "UPDATE surface_data sd SET tex_image_id = ti.id FROM tex_image ti "
            "WHERE sd.appearance_id = :a AND ti.appearance_id = :a AND ti.uri = sd.image_uri"
        ),
        {"a": aid},
    )
    th_rows = []
    for s in result.surfaces:
        t = dict(s.temperature)
        k = {key: to_kelvin(t.get(key), rad.unit) for key in _STAT_KEYS}
        k["std"] = None if rad.unit == "counts" else _f(t.get("std"))
        th_rows.append(
            (
                aid,
                surface_row[s.polygon_id],
                s.texels_total,
                s.texels_observed,
                s.observed_share,
                list(s.frames_used),
                _f(s.mean_resolution_m),
                _f(s.mean_view_angle_deg),
                *(k[key] for key in _STAT_KEYS),
                Jsonb({key: _f(v) for key, v in t.items()}),
                rad.unit,
                _f(s.resolution_px_per_m),
                _f(s.best_resolution_m),
                _f(s.mean_observations),
                s.reason or None,
                to_kelvin(s.typical, rad.unit),
                None if rad.unit == "counts" else _f(s.spread),
                _f(s.hot_share),
                _f(s.window_share),
                None if rad.unit == "counts" else _f(s.heat_loss_index),
                int(s.windows),
                int(s.leaks),
            )
        )
    copy_rows(conn, "surface_thermal", THERMAL_COLUMNS, th_rows)
    write_feature_texts(conn, "st.appearance_id = :a", {"a": aid})  # the facades' GeoJSON texts
    pose_rows = []
    for fp in result.poses:
        prior = (priors or {}).get(fp.frame)
        pose_rows.append(
            (
                job_id,
                bid,
                fp.frame,
                fp.status,
                prior.center.tolist() if prior is not None else None,
                prior.R_world_from_cam.ravel().tolist() if prior is not None else None,
                fp.pose.center.tolist(),
                fp.pose.R_world_from_cam.ravel().tolist(),
                encode_point_z(to_db.points(fp.pose.center[None])[0], srid),
                _f(fp.rms_px),
                int(fp.matches),
            )
        )
    copy_rows(conn, "frame_pose", POSE_COLUMNS, pose_rows)
    if pose_rows:  # link the job's registered frames, and their priors where none were given
        conn.execute(
            text(
                "UPDATE frame_pose fp SET frame_id = f.id, "
                "prior_center = COALESCE(fp.prior_center, CASE WHEN f.prior_center IS NULL THEN NULL "
                "ELSE (SELECT ARRAY[ST_X(c), ST_Y(c), ST_Z(c)] FROM ST_Transform(f.prior_center, m.srid) c) "
                "END), prior_rotation = COALESCE(fp.prior_rotation, f.prior_rotation) "
                "FROM job j JOIN frame f ON f.sequence_id = j.sequence_id "
                "JOIN city_model m ON m.id = j.city_model_id "
                "WHERE j.id = :j AND fp.job_id = :j AND fp.building_id = :b AND f.index = fp.frame_index"
            ),
            p,
        )
    an_rows = []
    for a in result.anomalies:
        ring = np.asarray(a.outline, dtype=np.float64)
        if len(ring) and not np.array_equal(ring[0], ring[-1]):
            ring = np.vstack([ring, ring[:1]])
        an_rows.append(
            (
                job_id,
                aid,
                bid,
                surface_row.get(a.polygon_id),
                a.kind,
                encode_polygon_z([to_db.points(ring)], srid) if len(ring) >= 4 else None,
                np.asarray(a.centre, dtype=np.float64).tolist(),
                float(a.area_m2),
                float(a.peak_delta_k),
                float(a.mean_delta_k),
                a.id or None,
                int(a.frames),
                _f(a.best_resolution_m),
                _f(a.confidence),
            )
        )
    copy_rows(conn, "thermal_anomaly", ANOMALY_COLUMNS, an_rows)
    conn.execute(
        text(
            "UPDATE job_unit SET status = 'successful', progress = 1, finished_at = now(), "
            "timings_s = CAST(:t AS jsonb), error = NULL WHERE job_id = :j AND building_id = :b"
        ),
        {**p, "t": _json({k: float(v) for k, v in result.timings_s.items()})},
    )
    n_tex = sum(len(sd.targets) for sd in app.surface_data if isinstance(sd, ParameterizedTexture))
    return StoredResult(aid, bid, len(img_rows), n_tex, len(th_rows), len(pose_rows), len(an_rows))


def store_building_result(
    session: Session,
    *,
    job_id: uuid.UUID | str,
    model_id: int,
    result: BuildingResult,
    priors: Mapping[int, Pose] | None = None,
    commit: bool = True,
) -> StoredResult:
    """Store one building unit's result for a job, replacing what an earlier run of the same
    (job, building) wrote.

    The work runs in a savepoint: on any error it is rolled back (nothing partial remains, an
    earlier copy stays) and the error propagates. With `commit` (default) the session's transaction
    is committed afterwards; pass `commit=False` to make it part of a larger unit of work.
    `priors` (frame index -> prior pose) fills the prior columns of `frame_pose`.
    Raises `NotFoundError` (unknown job or building) and `InputDataError` (dangling references).
    """
    jid = job_id if isinstance(job_id, uuid.UUID) else uuid.UUID(str(job_id))
    with session.begin_nested():
        conn = session.connection()
        job = conn.execute(
            text(
                "SELECT j.theme, m.srs_name FROM job j JOIN city_model m ON m.id = j.city_model_id "
                "WHERE j.id = :j AND j.city_model_id = :m"
            ),
            {"j": jid, "m": model_id},
        ).first()
        if job is None:
            raise NotFoundError(f"job {jid} of city model {model_id} not found")
        db_srid = database_srid(conn)
        stored = _write(
            conn,
            job_id=jid,
            model_id=model_id,
            result=result,
            theme=job[0],
            srid=db_srid,
            to_db=to_database(job[1], db_srid),
            priors=priors,
        )
    if commit:
        session.commit()
    return stored

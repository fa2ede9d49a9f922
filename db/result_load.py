"""Read a stored building unit result back from the database.

In: a `Session`, a job id, the city model id and a top-level building's gml id. Out: the
`workers.pipeline.results.BuildingResult` that `db.store.store_building_result` wrote (appearance
with its texture coordinates, tiles decoded from the stored 16-bit PNGs, radiometry, per-surface
statistics in the radiometry unit, frame poses, anomalies, the unit's timings when a job unit
exists), so the service can write `report.json` / `orientation.json` with the same code as the
in-process run. Raises `NotFoundError` when nothing was stored for that job and building.
"""

from __future__ import annotations

import uuid
from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np
from sqlalchemy import text
from sqlalchemy.orm import Session

from db.appearance_rows import load_texture_params, surface_data_from_rows
from db.errors import NotFoundError
from db.geomcodec import polygon_rings_from_wkb
from db.srid import database_srid, from_database
from workers.pipeline.geometry.citymodel import Appearance
from workers.pipeline.geometry.manifest import Radiometry
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.transform import CrsTransform
from workers.pipeline.results import Anomaly, BuildingResult, FramePose, SurfaceStats, TextureTile

__all__ = ["load_building_result"]


def _nan(v: float | None) -> float:
    return float("nan") if v is None else float(v)


def from_kelvin(v: float | None, unit: str | None) -> float:
    """A stored kelvin temperature back in the radiometry `unit` (NaN when not stored: `counts`;
    inverse of `store.to_kelvin`)."""
    if v is None:
        return float("nan")
    return float(v) - 273.15 if unit == "degC" else float(v)


def anomaly_from_row(r: Mapping[str, Any], building_id: str, back: CrsTransform) -> Anomaly:
    """An `Anomaly` from a `thermal_anomaly` row (`r`: its columns, plus `surface` = the surface's
    gml id and `outline_wkb` = `ST_AsBinary(outline)`); `back` maps the outline from the database
    SRID to the model CRS."""
    wkb = r["outline_wkb"]
    outline = back.points(polygon_rings_from_wkb(wkb)[0]) if wkb is not None else np.zeros((0, 3))
    return Anomaly(
        building_id=building_id,
        polygon_id=r["surface"],
        outline=outline,
        centre=np.array(r["centre"], dtype=np.float64),
        area_m2=r["area_m2"],
        peak_delta_k=r["peak_delta_k"],
        mean_delta_k=r["mean_delta_k"],
        kind=r["kind"],
        id=r["anomaly_id"] or "",
        frames=int(r["frames"] or 0),
        best_resolution_m=_nan(r["best_resolution_m"]),
        confidence=_nan(r["confidence"]),
    )


def load_building_result(
    session: Session, *, job_id: uuid.UUID | str, model_id: int, building_gml_id: str
) -> BuildingResult:
    """The stored result of (job, building); see the module docstring."""
    jid = job_id if isinstance(job_id, uuid.UUID) else uuid.UUID(str(job_id))
    conn = session.connection()
    app = (
        conn.execute(
            text(
                "SELECT a.id, a.theme, a.gml_id, a.radiometry, b.id AS building_row FROM appearance a "
                "JOIN building b ON b.id = a.building_id WHERE a.job_id = :j AND b.city_model_id = :m "
                "AND b.gml_id = :g AND NOT b.is_part"
            ),
            {"j": jid, "m": model_id, "g": building_gml_id},
        )
        .mappings()
        .first()
    )
    if app is None:
        raise NotFoundError(f"no result of job {jid} for building {building_gml_id!r} in model {model_id}")
    aid, bid = app["id"], app["building_row"]
    rad_d = app["radiometry"] or {}
    radiometry = Radiometry(
        unit=rad_d.get("unit", "K"), scale=rad_d.get("scale", 0.01), offset=rad_d.get("offset", 0.0)
    )
    sds = (
        conn.execute(text("SELECT * FROM surface_data WHERE appearance_id = :a ORDER BY ordinal"), {"a": aid})
        .mappings()
        .all()
    )
    params = load_texture_params(conn, [sd["id"] for sd in sds])
    data = tuple(surface_data_from_rows(sd, params.get(sd["id"], [])) for sd in sds)
    appearance = Appearance(theme=app["theme"], surface_data=data, id=app["gml_id"]) if data else None
    tiles = tuple(
        TextureTile(uri, cv2.imdecode(np.frombuffer(bytes(img), np.uint8), cv2.IMREAD_UNCHANGED))
        for uri, img in conn.execute(
            text("SELECT uri, image FROM tex_image WHERE appearance_id = :a ORDER BY id"), {"a": aid}
        ).all()
    )
    surfaces = tuple(
        SurfaceStats(
            polygon_id=r["gml_id"],
            building_id=r["owner"],
            surface_class=r["surface_class"],
            texels_total=r["texels_total"],
            texels_observed=r["texels_observed"],
            frames_used=tuple(r["frames_used"] or ()),
            mean_resolution_m=_nan(r["resolution_m"]),
            mean_view_angle_deg=_nan(r["view_angle_deg"]),
            temperature={k: _nan(v) for k, v in (r["temperature"] or {}).items()},
            resolution_px_per_m=_nan(r["resolution_px_per_m"]),
            best_resolution_m=_nan(r["best_resolution_m"]),
            mean_observations=_nan(r["mean_observations"]),
            reason=r["reason"] or "",
            typical=from_kelvin(r["typical_k"], r["unit"]),
            spread=_nan(r["spread_k"]),
            hot_share=_nan(r["hot_share"]),
            window_share=_nan(r["window_share"]),
            heat_loss_index=_nan(r["heat_loss_index"]),
            windows=int(r["windows"] or 0),
            leaks=int(r["leaks"] or 0),
        )
        for r in conn.execute(
            text(
                "SELECT s.gml_id, ob.gml_id AS owner, s.surface_class, st.* FROM surface_thermal st "
                "JOIN surface s ON s.id = st.surface_id JOIN building ob ON ob.id = s.building_id "
                "WHERE st.appearance_id = :a ORDER BY ob.ordinal, s.ordinal"
            ),
            {"a": aid},
        ).mappings()
    )
    poses = tuple(
        FramePose(
            frame=r["frame_index"],
            building_id=building_gml_id,
            pose=Pose(
                np.array(r["refined_rotation"], dtype=np.float64).reshape(3, 3),
                np.array(r["refined_center"], dtype=np.float64),
            ),
            status=r["status"],
            rms_px=_nan(r["rms_px"]),
            matches=r["matches"],
        )
        for r in conn.execute(
            text("SELECT * FROM frame_pose WHERE job_id = :j AND building_id = :b ORDER BY frame_index"),
            {"j": jid, "b": bid},
        ).mappings()
    )
    srs = conn.execute(text("SELECT srs_name FROM city_model WHERE id = :m"), {"m": model_id}).scalar_one()
    back = from_database(srs, database_srid(conn))  # outlines are stored in the database SRID
    rows = conn.execute(
        text(
            "SELECT s.gml_id AS surface, ST_AsBinary(ta.outline) AS outline_wkb, ta.* "
            "FROM thermal_anomaly ta "
            "LEFT JOIN surface s ON s.id = ta.surface_id WHERE ta.appearance_id = :a ORDER BY ta.id"
        ),
        {"a": aid},
    ).mappings()
    anomalies = [anomaly_from_row(r, building_gml_id, back) for r in rows]
    timings = conn.execute(
        text("SELECT timings_s FROM job_unit WHERE job_id = :j AND building_id = :b"), {"j": jid, "b": bid}
    ).scalar()
    return BuildingResult(
        building_id=building_gml_id,
        appearance=appearance,
        tiles=tiles,
        radiometry=radiometry,
        surfaces=surfaces,
        poses=poses,
        anomalies=tuple(anomalies),
        timings_s=dict(timings or {}),
    )

"""Registered sequences: a sequence package's manifest, frames and trajectory as rows.

In: a `Session` (the caller's unit of work commits), a read `SequenceManifest`, where the package
is stored. Out: rows of `sequence` and `frame`; geometries in the database SRID (`db.srid`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from sqlalchemy import text
from sqlalchemy.orm import Session

from db.errors import InputDataError
from db.geomcodec import encode_linestring_z, encode_point_z
from db.srid import database_srid
from workers.pipeline.geometry.georef import GeorefError, transform_positions
from workers.pipeline.geometry.manifest import SequenceManifest
from workers.pipeline.geometry.pose import Pose

__all__ = ["register_sequence"]


def register_sequence(
    session: Session,
    *,
    name: str,
    manifest: SequenceManifest,
    manifest_json: Mapping[str, Any],
    storage_location: str,
    srid: int,
    priors: Sequence[Pose] | None = None,
) -> int:
    """Insert a sequence (its `sequence.json` as jsonb, where it is stored), one row per frame
    (with the prior pose when `priors[i]` is given) and the trajectory of the frame positions.
    `srid` is the EPSG code of the manifest CRS (kept in `sequence.srid`; 0 for `"model"`); the
    trajectory (`LINESTRING Z`) and the prior centres (`POINT Z`, given in the manifest's CRS)
    are stored in the database SRID, heights kept (geographic positions are `[lat, lon, h]`:
    `georef.transform_positions`). A sequence in `"model"` coordinates gets neither (its model is
    known only with a job). Raises `InputDataError` naming `crs` for a CRS that cannot be placed.
    Returns the sequence id."""
    db_srid = database_srid(session.connection())
    in_model = manifest.crs.strip().lower() == "model"

    def to_db(points: np.ndarray) -> np.ndarray:
        try:
            return transform_positions(points, manifest.crs, f"EPSG:{db_srid}")
        except (GeorefError, ValueError) as exc:
            raise InputDataError(f"crs: {manifest.crs!r} cannot be placed in EPSG:{db_srid}: {exc}") from exc

    pos = np.array([f.position for f in manifest.frames], dtype=np.float64).reshape(-1, 3)
    traj = encode_linestring_z(to_db(pos), db_srid) if len(pos) >= 2 and not in_model else None
    centres: list[np.ndarray | None] = [None] * len(manifest.frames)
    if priors is not None and not in_model:
        given = [i for i, p in enumerate(priors) if p is not None]
        if given:
            moved = to_db(np.array([priors[i].center for i in given], dtype=np.float64))
            for i, c in zip(given, moved, strict=True):
                centres[i] = c
    sid = session.execute(
        text(
            "INSERT INTO sequence (name, manifest, storage_location, frame_count, srs_name, srid, "
            "trajectory) "
            "VALUES (:n, CAST(:m AS jsonb), :loc, :fc, :srs, :srid, CAST(:t AS geometry)) RETURNING id"
        ),
        {
            "n": name,
            "m": json.dumps(manifest_json),
            "loc": storage_location,
            "fc": len(manifest.frames),
            "srs": manifest.crs,
            "srid": srid,
            "t": traj,
        },
    ).scalar_one()
    rows = []
    for i, f in enumerate(manifest.frames):
        prior = priors[i] if priors is not None else None
        rows.append(
            {
                "s": sid,
                "i": f.index,
                "f": f.file,
                "t": f.time,
                "c": None if centres[i] is None else encode_point_z(centres[i], db_srid),
                "r": prior.R_world_from_cam.ravel().tolist() if prior is not None else None,
                "rec": json.dumps({"position": f.position.tolist(), "attitude_deg": f.attitude_deg.tolist()}),
            }
        )
    if rows:
        session.execute(
            text(
                "INSERT INTO frame (sequence_id, index, file, time_s, prior_center, prior_rotation, record) "
                "VALUES (:s, :i, :f, :t, CAST(:c AS geometry), :r, CAST(:rec AS jsonb))"
            ),
            rows,
        )
    return int(sid)

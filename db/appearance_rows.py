"""Appearances <-> rows of `appearance`, `surface_data`, `texture_param`.

In: `citymodel.Appearance`s (from the reader or a job's result), the row id of the building
they belong to (None for CityModel-level ones), polygon id -> surface row id. Out: COPY rows,
written with reserved ids; and back, rows -> `Appearance` dataclasses for the export.

Texture coordinates are kept per target polygon as `ring_ids text[]` plus `tex_coords jsonb`
(`[[[s, t], ...] per ring]`, closing vertex included): JSON keeps every double exactly (Python
writes the shortest repr, PostgreSQL's numeric keeps the digits).
"""

from __future__ import annotations

import uuid
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from psycopg.types.json import Jsonb
from sqlalchemy import Connection, text

from workers.pipeline.geometry.citymodel import (
    Appearance,
    GeoreferencedTexture,
    ParameterizedTexture,
    SurfaceData,
    TextureTarget,
    X3DMaterial,
)

__all__ = [
    "APPEARANCE_COLUMNS",
    "SURFACE_DATA_COLUMNS",
    "TEXTURE_PARAM_COLUMNS",
    "AppearanceRows",
    "collect_appearance_rows",
    "surface_data_from_rows",
]

APPEARANCE_COLUMNS = (
    "id",
    "city_model_id",
    "building_id",
    "job_id",
    "theme",
    "gml_id",
    "ordinal",
    "radiometry",
)
SURFACE_DATA_COLUMNS = (
    "id",
    "appearance_id",
    "ordinal",
    "kind",
    "gml_id",
    "is_front",
    "image_uri",
    "mime_type",
    "texture_type",
    "wrap_mode",
    "border_color",
    "diffuse_color",
    "specular_color",
    "emissive_color",
    "ambient_intensity",
    "shininess",
    "transparency",
    "is_smooth",
    "reference_point",
    "orientation",
    "prefer_world_file",
)
TEXTURE_PARAM_COLUMNS = (
    "surface_data_id",
    "ordinal",
    "target_gml_id",
    "surface_id",
    "ring_ids",
    "tex_coords",
)

CopyFn = Callable[[Connection, str, Sequence[str], Sequence[tuple]], None]
ReserveFn = Callable[[Connection, str, int], list[int]]


@dataclass
class _Pending:
    appearance: Appearance
    ordinal: int
    model_id: int
    building_row: int | None
    job_id: uuid.UUID | None
    surface_row: Mapping[str, int]
    radiometry: dict[str, Any] | None


@dataclass
class AppearanceRows:
    """Appearances collected for one COPY round (a batch of buildings or one result)."""

    items: list[_Pending] = field(default_factory=list)

    @property
    def count(self) -> int:
        """Number of appearances collected."""
        return len(self.items)

    def write(self, conn: Connection, copy: CopyFn, reserve: ReserveFn) -> list[int]:
        """Write the appearances with their surface data and texture parameterisations; returns
        the appearance row ids (in collection order)."""
        if not self.items:
            return []
        app_ids = reserve(conn, "appearance", len(self.items))
        app_rows = []
        sd_items: list[tuple[int, int, SurfaceData, Mapping[str, int]]] = []
        for aid, it in zip(app_ids, self.items, strict=True):
            a = it.appearance
            app_rows.append(
                (
                    aid,
                    it.model_id,
                    it.building_row,
                    it.job_id,
                    a.theme,
                    a.id,
                    it.ordinal,
                    Jsonb(it.radiometry) if it.radiometry is not None else None,
                )
            )
            for k, sd in enumerate(a.surface_data):
                sd_items.append((aid, k, sd, it.surface_row))
        copy(conn, "appearance", APPEARANCE_COLUMNS, app_rows)
        sd_ids = reserve(conn, "surface_data", len(sd_items))
        sd_rows = []
        tp_rows = []
        for sid, (aid, k, sd, surface_row) in zip(sd_ids, sd_items, strict=True):
            sd_rows.append(_surface_data_row(sid, aid, k, sd))
            tp_rows.extend(_texture_param_rows(sid, sd, surface_row))
        copy(conn, "surface_data", SURFACE_DATA_COLUMNS, sd_rows)
        copy(conn, "texture_param", TEXTURE_PARAM_COLUMNS, tp_rows)
        return app_ids


def collect_appearance_rows(
    rows: AppearanceRows,
    appearances: Sequence[Appearance],
    *,
    model_id: int,
    building_row: int | None,
    surface_row: Mapping[str, int],
    job_id: uuid.UUID | None = None,
    radiometry: dict[str, Any] | None = None,
) -> None:
    """Add appearances (of one building, or CityModel-level with `building_row` None)."""
    for k, a in enumerate(appearances):
        rows.items.append(_Pending(a, k, model_id, building_row, job_id, surface_row, radiometry))


def _floats(v: Sequence[float] | None) -> list[float] | None:
    return None if v is None else [float(x) for x in v]


def _surface_data_row(sid: int, aid: int, k: int, sd: SurfaceData) -> tuple:
    if isinstance(sd, ParameterizedTexture):
        return (
            sid,
            aid,
            k,
            "ParameterizedTexture",
            sd.id,
            True,
            sd.image_uri,
            sd.mime_type,
            sd.texture_type,
            sd.wrap_mode,
            sd.border_color,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
        )
    if isinstance(sd, X3DMaterial):
        return (
            sid,
            aid,
            k,
            "X3DMaterial",
            sd.id,
            sd.is_front,
            None,
            None,
            None,
            None,
            None,
            _floats(sd.diffuse_color),
            _floats(sd.specular_color),
            _floats(sd.emissive_color),
            sd.ambient_intensity,
            sd.shininess,
            sd.transparency,
            sd.is_smooth,
            None,
            None,
            None,
        )
    if isinstance(sd, GeoreferencedTexture):
        return (
            sid,
            aid,
            k,
            "GeoreferencedTexture",
            sd.id,
            True,
            sd.image_uri,
            sd.mime_type,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
            None,
            _floats(sd.reference_point),
            _floats(sd.orientation),
            sd.prefer_world_file,
        )
    raise TypeError(f"unknown surface data type {type(sd).__name__}")


def _texture_param_rows(sid: int, sd: SurfaceData, surface_row: Mapping[str, int]) -> list[tuple]:
    out = []
    if isinstance(sd, ParameterizedTexture):
        for j, t in enumerate(sd.targets):
            ring_ids = list(t.ring_coords.keys())
            coords = [np.asarray(t.ring_coords[r], dtype=np.float64).tolist() for r in ring_ids]
            out.append((sid, j, t.polygon_id, surface_row.get(t.polygon_id), ring_ids, Jsonb(coords)))
    else:
        for j, target in enumerate(sd.targets):
            out.append((sid, j, target, surface_row.get(target), None, None))
    return out


def _tuple(v: Sequence[float] | None) -> tuple[float, ...] | None:
    return None if v is None else tuple(float(x) for x in v)


def surface_data_from_rows(sd: Mapping[str, Any], params: Sequence[Mapping[str, Any]]) -> SurfaceData:
    """One `surface_data` row (as a mapping) and its `texture_param` rows (in ordinal order)
    -> the `SurfaceData` dataclass."""
    kind = sd["kind"]
    if kind == "ParameterizedTexture":
        targets = tuple(
            TextureTarget(
                polygon_id=p["target_gml_id"],
                ring_coords={
                    r: np.asarray(c, dtype=np.float64).reshape(-1, 2)
                    for r, c in zip(p["ring_ids"] or [], p["tex_coords"] or [], strict=True)
                },
            )
            for p in params
        )
        return ParameterizedTexture(
            id=sd["gml_id"],
            image_uri=sd["image_uri"],
            targets=targets,
            mime_type=sd["mime_type"] or "image/png",
            texture_type=sd["texture_type"],
            wrap_mode=sd["wrap_mode"],
            border_color=sd["border_color"],
        )
    targets_s = tuple(p["target_gml_id"] for p in params)
    if kind == "X3DMaterial":
        color = {k: _tuple(sd[k]) for k in ("diffuse_color", "specular_color", "emissive_color")}
        return X3DMaterial(
            id=sd["gml_id"],
            targets=targets_s,
            ambient_intensity=sd["ambient_intensity"],
            shininess=sd["shininess"],
            transparency=sd["transparency"],
            is_smooth=sd["is_smooth"],
            is_front=sd["is_front"],
            **color,
        )
    return GeoreferencedTexture(
        id=sd["gml_id"],
        image_uri=sd["image_uri"],
        targets=targets_s,
        mime_type=sd["mime_type"],
        reference_point=_tuple(sd["reference_point"]),
        orientation=_tuple(sd["orientation"]),  # type: ignore[arg-type]
        prefer_world_file=sd["prefer_world_file"],
    )


def load_texture_params(
    conn: Connection, surface_data_ids: Sequence[int]
) -> dict[int, list[Mapping[str, Any]]]:
    """`texture_param` rows of the given surface data, grouped by surface data id, in their
    original order (the input for `surface_data_from_rows`)."""
    params: dict[int, list[Mapping[str, Any]]] = defaultdict(list)
    rows = conn.execute(
        text(
            "SELECT surface_data_id, target_gml_id, ring_ids, tex_coords FROM texture_param "
            "WHERE surface_data_id = ANY(:s) ORDER BY surface_data_id, ordinal"
        ),
        {"s": list(surface_data_ids)},
    ).mappings()
    for tp in rows:
        params[tp["surface_data_id"]].append(tp)
    return params

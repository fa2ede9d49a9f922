"""Geometry checks of surfaces as stored in `surface.checks` (jsonb).

In: a batch's `EncodedPolygons` (vectorised planes) or the reader family's `check_building`.
Out: JSON per polygon: `level` ("fast" or "full"), `vertices`, `planarity_m`, `area_m2`,
`unclosed_rings`, `problems` (names as in `db.citygml.checks.PolygonCheck.problems`), and for
"full" also `normal_outward`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from psycopg.types.json import Jsonb

from db.citygml.checks import CheckOptions
from db.geomcodec import EncodedPolygons
from workers.pipeline.citymodel import Building, Polygon

__all__ = ["fast_checks", "full_checks", "jsonable", "surface_checks"]


def full_checks(tops: Sequence[Building]) -> dict[tuple[str, str], Any]:
    """The reader family's full per-polygon checks (`db.citygml.checks.check_building`: plane,
    planarity, area, vertices, self-intersection, unclosed rings, outward wall normals), keyed by
    (building id, polygon id), as JSON."""
    from db.citygml.checks import check_building

    out: dict[tuple[str, str], Any] = {}
    for t in tops:
        for c in check_building(t):
            out[(c.building_id, c.polygon_id)] = Jsonb(
                jsonable(
                    {
                        "level": "full",
                        "vertices": c.vertices,
                        "planarity_m": c.planarity_m,
                        "area_m2": c.area_m2,
                        "unclosed_rings": list(c.unclosed_rings),
                        "normal_outward": c.normal_outward,
                        "problems": list(c.problems),
                    }
                )
            )
    return out


def fast_checks(enc: EncodedPolygons, k: int, polygon: Polygon) -> Jsonb:
    """Vectorised checks from the batch encoding: vertices, planarity, area, unclosed rings (the
    same tolerances as `db.citygml.checks.CheckOptions`; no self-intersection or outward test)."""
    opt = CheckOptions()
    planarity = float(enc.planarity[k])
    area = float(enc.area[k])
    unclosed = [r.id for r, c in zip(polygon.rings, enc.ring_closed[k], strict=True) if not c]
    problems = []
    if enc.min_vertices[k] < 3:
        problems.append("too_few_vertices")
    if not np.isfinite(area) or area < opt.min_area_m2:
        problems.append("zero_area")
    if np.isfinite(planarity) and planarity > opt.planarity_tolerance_m:
        problems.append("non_planar")
    if unclosed:
        problems.append("unclosed_ring")
    return Jsonb(
        jsonable(
            {
                "level": "fast",
                "vertices": int(enc.min_vertices[k]),
                "planarity_m": planarity,
                "area_m2": area,
                "unclosed_rings": unclosed,
                "problems": problems,
            }
        )
    )


def jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return jsonable(v.tolist())
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, float) and not np.isfinite(v):
        return None
    return v


def surface_checks(
    mode: str, full: dict[tuple[str, str], Any], enc: EncodedPolygons, k: int, p: Polygon, bid: str
) -> Jsonb | None:
    if mode == "full":
        return full.get((bid, p.id))
    if mode == "fast":
        return fast_checks(enc, k, p)
    return None

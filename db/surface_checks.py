"""Geometry checks of surfaces as stored in `surface.checks` (jsonb).

In: a batch's `EncodedPolygons` (vectorised planes) or the reader family's `check_building`.
Out: JSON text per polygon: `level` ("fast" or "full"), `vertices`, `planarity_m`, `area_m2`,
`unclosed_rings`, `problems` (names as in `db.citygml.checks.PolygonCheck.problems`), and for
"full" also `normal_outward`.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

import numpy as np

from db.citygml.checks import CheckOptions
from db.compiled import fmt as _fmt  # `repr` of floats in C (Ryu), None: Python's `repr`
from db.geomcodec import EncodedPolygons
from workers.pipeline.geometry.citymodel import Building, Polygon

__all__ = ["fast_checks", "full_checks", "jsonable", "surface_checks"]


def full_checks(tops: Sequence[Building]) -> dict[tuple[str, str], str]:
    """The reader family's full per-polygon checks (`db.citygml.checks.check_building`: plane,
    planarity, area, vertices, self-intersection, unclosed rings, outward wall normals), keyed by
    (building id, polygon id), as JSON text."""
    from db.citygml.checks import check_building

    out: dict[tuple[str, str], str] = {}
    for t in tops:
        for c in check_building(t):
            out[(c.building_id, c.polygon_id)] = json.dumps(
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


def _nums(values: np.ndarray, texts: Sequence[str] | None = None) -> list[str]:
    """Floats `(P,)` -> JSON numbers (shortest round-trip decimals; null for NaN and inf);
    `texts`: their `repr`s where finite, if made already (any text where not)."""
    if texts is None and _fmt is not None:
        return _fmt.float_texts(values, "null", "null")
    if texts is None:
        finite = np.isfinite(values).tolist()
        return [repr(v) if ok else "null" for v, ok in zip(values.tolist(), finite, strict=True)]
    out = list(texts)
    for i in np.flatnonzero(~np.isfinite(values)).tolist():
        out[i] = "null"
    return out


#: problem names of the vectorised checks, by bit (1: too few vertices, 2: zero area, 4: non-planar)
_PROBLEMS = [
    [name for bit, name in ((1, '"too_few_vertices"'), (2, '"zero_area"'), (4, '"non_planar"')) if code & bit]
    for code in range(8)
]


def fast_checks(
    enc: EncodedPolygons, polygons: Sequence[Polygon], area_text: Sequence[str] | None = None
) -> list[str]:
    """Vectorised checks from the batch encoding, JSON text per polygon: vertices, planarity,
    area, unclosed rings (the tolerances of `db.citygml.checks.CheckOptions`; no self-intersection
    or outward test). `area_text`: `repr` of each finite area, if made already."""
    opt = CheckOptions()
    with np.errstate(invalid="ignore"):
        few = enc.min_vertices < 3
        zero = ~np.isfinite(enc.area) | (enc.area < opt.min_area_m2)
        nonplanar = np.isfinite(enc.planarity) & (enc.planarity > opt.planarity_tolerance_m)
    codes = (few.astype(np.int64) | (zero.astype(np.int64) << 1) | (nonplanar.astype(np.int64) << 2)).tolist()
    joined = [", ".join(names) for names in _PROBLEMS]
    verts, plan, area = enc.min_vertices.tolist(), _nums(enc.planarity), _nums(enc.area, area_text)
    out = []
    for k, closed in enumerate(enc.ring_closed):
        unclosed = "[]"
        problems = joined[codes[k]]
        if not all(closed):
            p = polygons[k]
            unclosed = json.dumps([r.id for r, c in zip(p.rings, closed, strict=True) if not c])
            problems = ", ".join([*_PROBLEMS[codes[k]], '"unclosed_ring"'])
        out.append(
            f'{{"level": "fast", "vertices": {verts[k]}, '
            f'"planarity_m": {plan[k]}, "area_m2": {area[k]}, '
            f'"unclosed_rings": {unclosed}, "problems": [{problems}]}}'
        )
    return out


def jsonable(v: Any) -> Any:
    """A JSON-safe copy: numpy values to Python, NaN/inf to None."""
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return jsonable(v.tolist())
    if isinstance(v, np.generic):
        return jsonable(v.item())
    if isinstance(v, float) and not np.isfinite(v):
        return None
    return v


def surface_checks(
    mode: str,
    enc: EncodedPolygons,
    polygons: Sequence[Polygon],
    owners: Sequence[str],
    tops: Sequence[Building],
    area_text: Sequence[str] | None = None,
) -> list[str | None]:
    """JSON text of the checks of each polygon of a batch (`owners[k]`: id of the building or part
    owning polygon k), for `mode` "fast", "full" or "none" (`area_text`: see `fast_checks`)."""
    if mode == "fast":
        return list(fast_checks(enc, polygons, area_text))
    if mode == "full":
        full = full_checks(tops)
        return [full.get((b, p.id)) for b, p in zip(owners, polygons, strict=True)]
    return [None] * len(polygons)

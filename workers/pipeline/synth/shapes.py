"""2D shape helpers of the synthetic scene generator (shapely): footprints, corners, sampling.

In: buildings (model CRS, metres) or shapely polygons in a surface's `(s, t)` frame.
Out: footprints (x, y), footprint corner vertices `(K, 2)`, random interior points `(2,)`.
"""

from __future__ import annotations

import numpy as np
import shapely

from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.polygons import open_ring


def footprint(building: Building) -> shapely.Geometry:
    """2D footprint (x, y) of a building: union of its non-vertical polygons projected down."""
    shapes = []
    for poly in building.iter_polygons():
        xy = open_ring(poly.exterior.coords)[:, :2]
        if len(xy) >= 3:
            g = shapely.Polygon(xy).buffer(0)
            if g.area > 0.01:
                shapes.append(g)
    if not shapes:
        lo, hi = building.bounds()
        return shapely.box(lo[0], lo[1], hi[0], hi[1])
    return shapely.union_all(shapes).buffer(0.05).buffer(-0.05)


def footprint_corners(building: Building) -> np.ndarray:
    """Corner vertices `(K, 2)` (turning angle > 20°) of a building's footprint outline."""
    fp = footprint(building).simplify(0.05)
    rings = [g.exterior for g in getattr(fp, "geoms", [fp])] + [
        r for g in getattr(fp, "geoms", [fp]) for r in g.interiors
    ]
    out = []
    for ring in rings:
        c = np.asarray(ring.coords)[:-1, :2]
        if len(c) < 3:
            continue
        a, b = c - np.roll(c, 1, axis=0), np.roll(c, -1, axis=0) - c
        cosang = np.sum(a * b, axis=1) / np.maximum(
            np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12
        )
        out.append(c[cosang < np.cos(np.radians(20.0))])
    return np.concatenate(out) if out else np.zeros((0, 2))


def point_inside(
    shape: shapely.Geometry | None, margin: float, rng: np.random.Generator
) -> np.ndarray | None:
    """A random point `(2,)` inside `shape` at least `margin` from its outline (None if none fits)."""
    if shape is None or shape.is_empty:
        return None
    inner = shape.buffer(-margin)
    target = inner if not inner.is_empty else shape
    x0, y0, x1, y1 = target.bounds
    for _ in range(64):
        q = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        if shapely.contains_xy(target, q[0], q[1]):
            return q
    rp = target.representative_point()
    return np.array([rp.x, rp.y])

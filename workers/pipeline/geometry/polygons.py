"""Planar polygon geometry: plane fit, local surface frames, triangulation.

In: rings `(N, 3)` float64 in the model CRS (metres). Out: planes (unit normal, offset), local
2D frames on a surface `(s, t)`, and triangles for ray casting.

Conventions: the normal of a ring follows the right-hand rule (counter-clockwise seen from the
side the normal points to); CityGML orders exterior rings so that normals point out of the
building. Surface frames: `s` horizontal to the right for a viewer outside looking at the
surface, `t = n × s` (upwards on walls, up-slope on roofs).
"""

from __future__ import annotations

from dataclasses import dataclass

import mapbox_earcut
import numpy as np

from workers.pipeline.geometry.citymodel import Polygon

_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True, eq=False)
class Plane:
    """A plane `normal · x = offset` fitted to a polygon.

    Attributes:
        normal: `(3,)` unit normal (right-hand rule of the exterior ring).
        offset: signed distance of the plane from the origin along `normal`, metres.
        centroid: `(3,)` mean of the exterior ring's distinct vertices.
        max_deviation: largest distance of any vertex from the plane, metres (non-planarity).
        area: polygon area in the plane (holes subtracted), m².
    """

    normal: np.ndarray
    offset: float
    centroid: np.ndarray
    max_deviation: float
    area: float


def open_ring(coords: np.ndarray) -> np.ndarray:
    """Drop the closing vertex of a ring `(N, 3)` when it repeats the first -> `(M, 3)`."""
    coords = np.asarray(coords, dtype=np.float64)
    if len(coords) > 1 and np.array_equal(coords[0], coords[-1]):
        return coords[:-1]
    return coords


def newell_normal(ring: np.ndarray) -> np.ndarray:
    """Newell's area vector of a ring `(N, 3)` (closed or open) -> `(3,)`, length = 2 × area.

    Robust for non-convex and slightly non-planar rings; its direction follows the right-hand rule.

    >>> newell_normal(np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)).round(6).tolist()
    [0.0, 0.0, 2.0]
    """
    p = open_ring(ring)
    p = p - p.mean(axis=0)
    q = np.roll(p, -1, axis=0)
    return np.array(
        [
            np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
            np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
            np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])),
        ]
    )


def fit_plane(polygon: Polygon) -> Plane | None:
    """Least-squares plane of a polygon, oriented by its exterior ring; None when degenerate.

    The normal is the smallest singular vector of all ring vertices (centred), with its sign taken
    from Newell's vector of the exterior ring, so it is exact for planar polygons and the best
    fit for slightly non-planar ones.
    """
    ext = open_ring(polygon.exterior.coords)
    if len(ext) < 3:
        return None
    nv = newell_normal(ext)
    n_len = np.linalg.norm(nv)
    if not np.isfinite(n_len) or n_len < 1e-12:
        return None
    pts = np.concatenate([ext] + [open_ring(r.coords) for r in polygon.interiors], axis=0)
    centroid = ext.mean(axis=0)
    centred = pts - centroid
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    normal = vt[-1]
    if normal @ nv < 0:
        normal = -normal
    offset = float(normal @ centroid)
    dev = float(np.max(np.abs(pts @ normal - offset)))
    area = 0.5 * abs(float(newell_normal(ext) @ normal))
    for r in polygon.interiors:
        if len(open_ring(r.coords)) >= 3:
            area -= 0.5 * abs(float(newell_normal(r.coords) @ normal))
    return Plane(normal=normal, offset=offset, centroid=centroid, max_deviation=dev, area=area)


def surface_axes(normal: np.ndarray, ring: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Local texture axes `(s, t)` `(3,)` each for a surface with unit `normal`.

    `s = up × n` (horizontal, to the right of a viewer outside), `t = n × s`. For horizontal
    surfaces (|n_z| > 0.999) `s` follows the longest edge of `ring` (or east without a ring).
    """
    n = np.asarray(normal, dtype=np.float64)
    s = np.cross(_UP, n)
    if np.linalg.norm(s) < 0.0447:  # surface within ~2.5 degrees of horizontal
        s = np.array([1.0, 0.0, 0.0])
        if ring is not None:
            p = open_ring(ring)
            e = np.roll(p, -1, axis=0) - p
            e = e - np.outer(e @ n, n)
            k = int(np.argmax(np.linalg.norm(e, axis=1)))
            if np.linalg.norm(e[k]) > 1e-9:
                s = e[k]
        s = s - (s @ n) * n
    s = s / np.linalg.norm(s)
    t = np.cross(n, s)
    return s, t / np.linalg.norm(t)


def to_plane_2d(points: np.ndarray, origin: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World points `(N, 3)` -> plane coordinates `(N, 2)` along axes `s`, `t` from `origin`."""
    d = np.asarray(points, dtype=np.float64) - origin
    return np.stack([d @ s, d @ t], axis=-1)


def triangulate(polygon: Polygon, plane: Plane | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate a polygon with holes in its own plane (ear clipping, mapbox-earcut).

    Returns `(vertices (M, 3) float64 world, triangles (K, 3) int64)`; triangles wind like the
    exterior ring (right-hand normal = the polygon's normal). Degenerate polygons give `K = 0`.
    """
    plane = plane if plane is not None else fit_plane(polygon)
    empty = (np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    if plane is None:
        return empty
    rings = [open_ring(polygon.exterior.coords)] + [
        open_ring(r.coords) for r in polygon.interiors if len(open_ring(r.coords)) >= 3
    ]
    verts = np.concatenate(rings, axis=0)
    s, t = surface_axes(plane.normal, rings[0])
    uv = to_plane_2d(verts, plane.centroid, s, t)
    ends = np.cumsum([len(r) for r in rings]).astype(np.uint32)
    idx = np.asarray(mapbox_earcut.triangulate_float64(uv, ends), dtype=np.int64).reshape(-1, 3)
    if len(idx) == 0:
        return empty
    # earcut's winding depends on the input; enforce the polygon's normal (s, t, n right-handed).
    a, b, c = uv[idx[:, 0]], uv[idx[:, 1]], uv[idx[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    flip = cross < 0
    idx[flip] = idx[flip][:, [0, 2, 1]]
    return verts, idx

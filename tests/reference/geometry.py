"""Plane geometry of the reference texturer: scene polygons and their own texel grids.

In: polygon vertex coordinates (world = the city model's projected CRS, metres, x east, y north,
z up), read as plain arrays from the product's `citymodel.Building` objects. Out: `ScenePolygon`
(rings, plane, bounding sphere: what the z-buffer rasterizes) and `RefGrid` (a regular texel grid
on one planar polygon, texel centres inside the polygon).

Nothing here comes from the product's geometry code: the plane is Newell's normal through the
vertex mean, the in-plane axes are chosen here, the inside test is shapely's.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import shapely

#: sentinel ids of the z-buffer (polygon ids are >= 0)
SKY, GROUND, MIXED = -1, -2, -3


@dataclass(frozen=True, eq=False)
class ScenePolygon:
    """One planar scene polygon as the reference sees it.

    Attributes:
        index: position in the scene list (the z-buffer's id).
        polygon_id, building_id: `gml:id`s (building = the top-level building).
        surface_class: CityGML class (`WallSurface`, `RoofSurface`, ...).
        rings: exterior first, then holes; each `(N, 3)` float64 world, open (no repeated vertex).
        normal: `(3,)` unit normal (Newell; outward for CityGML's counter-clockwise exteriors).
        offset: plane offset `d` of `normal · X = d`, metres.
        centre: `(3,)` mean of the exterior vertices; radius: bounding-sphere radius about it, m.
        area: polygon area, m² (holes subtracted).
    """

    index: int
    polygon_id: str
    building_id: str
    surface_class: str
    rings: tuple[np.ndarray, ...]
    normal: np.ndarray
    offset: float
    centre: np.ndarray
    radius: float
    area: float


def newell_normal(ring: np.ndarray) -> tuple[np.ndarray, float]:
    """Newell's normal of an open ring `(N, 3)` -> (unit normal `(3,)`, area m²); zero normal and
    area 0 for a degenerate ring.

    >>> n, a = newell_normal(np.array([[0., 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]]))
    >>> n.tolist(), round(a, 6)
    ([0.0, 0.0, 1.0], 2.0)
    """
    p = ring - ring.mean(axis=0)
    q = np.roll(p, -1, axis=0)
    n = np.array(
        [
            np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
            np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
            np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])),
        ]
    )
    length = float(np.linalg.norm(n))
    if length < 1e-12:
        return np.zeros(3), 0.0
    return n / length, 0.5 * length


def _open(coords: np.ndarray) -> np.ndarray:
    """A ring `(N, 3)` without its closing vertex."""
    c = np.asarray(coords, dtype=np.float64)
    return c[:-1] if len(c) > 1 and np.allclose(c[0], c[-1]) else c


def scene_polygons(buildings: Iterable[object]) -> list[ScenePolygon]:
    """Every non-degenerate polygon of `buildings` (citymodel `Building`s, parts included), in
    a fixed order; each is owned by its top-level building. Reads only `id`, `iter_polygons()`,
    `exterior.coords`, `interiors[].coords` and `surface_class`."""
    out: list[ScenePolygon] = []
    for b in buildings:
        for poly in b.iter_polygons():  # type: ignore[attr-defined]
            ext = _open(poly.exterior.coords)
            if len(ext) < 3:
                continue
            normal, area = newell_normal(ext)
            if area < 1e-4:
                continue
            holes = tuple(_open(r.coords) for r in poly.interiors if len(_open(r.coords)) >= 3)
            area -= sum(newell_normal(h)[1] for h in holes)
            centre = ext.mean(axis=0)
            radius = float(np.max(np.linalg.norm(ext - centre, axis=1)))
            out.append(
                ScenePolygon(
                    index=len(out),
                    polygon_id=poly.id,
                    building_id=b.id,  # type: ignore[attr-defined]
                    surface_class=poly.surface_class,
                    rings=(ext, *holes),
                    normal=normal,
                    offset=float(normal @ centre),
                    centre=centre,
                    radius=radius,
                    area=float(area),
                )
            )
    return out


def plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """In-plane unit axes `(s, t)` `(3,)` each for a unit `normal`: `s` horizontal (along a
    wall), `t = normal × s` (up the wall); for near-horizontal planes `s` follows world x."""
    up = np.array([0.0, 0.0, 1.0])
    s = np.cross(up, normal)
    if np.linalg.norm(s) < 1e-6:
        s = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
    s /= np.linalg.norm(s)
    t = np.cross(normal, s)
    return s, t / np.linalg.norm(t)


@dataclass(frozen=True, eq=False)
class RefGrid:
    """A texel grid on one scene polygon.

    Texel `(row, col)` has its centre at plane coordinates `s = s0 + (col + 0.5)·size`,
    `t = t0 − (row + 0.5)·size` (rows from the top), i.e. at world
    `origin + s·s_axis + t·t_axis`. Only texels whose centre is inside the polygon exist.

    Attributes:
        polygon: the scene polygon.
        size: texel edge, metres.
        s_axis, t_axis: `(3,)` unit in-plane axes; origin: `(3,)` world point on the plane.
        s0, t0: plane coordinates of the raster's top-left corner, metres.
        shape: `(H, W)` of the bounding raster.
        rows, cols: `(N,)` int indices of the texels inside the polygon.
        centres: `(N, 3)` float64 world texel centres.
    """

    polygon: ScenePolygon
    size: float
    s_axis: np.ndarray
    t_axis: np.ndarray
    origin: np.ndarray
    s0: float
    t0: float
    shape: tuple[int, int]
    rows: np.ndarray
    cols: np.ndarray
    centres: np.ndarray

    def plane_st(self, points: np.ndarray) -> np.ndarray:
        """World points `(N, 3)` -> plane coordinates `(N, 2)` (s, t) metres (orthogonal projection)."""
        d = np.asarray(points, dtype=np.float64) - self.origin
        return np.stack([d @ self.s_axis, d @ self.t_axis], axis=1)

    def index_raster(self) -> np.ndarray:
        """`(H, W)` int: texel number (position in `rows`/`cols`) per raster cell, -1 outside."""
        r = np.full(self.shape, -1, np.int64)
        r[self.rows, self.cols] = np.arange(len(self.rows))
        return r

    def cell_of(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points `(N, 3)` -> raster cell `(row, col)` `(N,)` int each (may lie outside)."""
        st = self.plane_st(points)
        col = np.floor((st[:, 0] - self.s0) / self.size).astype(np.int64)
        row = np.floor((self.t0 - st[:, 1]) / self.size).astype(np.int64)
        return row, col


def ref_grid(polygon: ScenePolygon, texels_per_m: float, max_side: int = 4000) -> RefGrid | None:
    """A texel grid of `texels_per_m` on `polygon` (coarser if a side would pass `max_side`);
    None when no texel centre falls inside the polygon."""
    s_axis, t_axis = plane_axes(polygon.normal)
    origin = polygon.centre
    rings2d = [np.stack([(r - origin) @ s_axis, (r - origin) @ t_axis], axis=1) for r in polygon.rings]
    ext = rings2d[0]
    s0, t_min = ext.min(axis=0)
    s_max, t0 = ext.max(axis=0)
    size = 1.0 / texels_per_m
    size = max(size, max(s_max - s0, t0 - t_min) / max_side)
    W = max(1, math.ceil((s_max - s0) / size))
    H = max(1, math.ceil((t0 - t_min) / size))
    shape = shapely.make_valid(shapely.Polygon(ext, [h for h in rings2d[1:]]))
    S, T = np.meshgrid(s0 + (np.arange(W) + 0.5) * size, t0 - (np.arange(H) + 0.5) * size)
    inside = shapely.contains_xy(shape, S.ravel(), T.ravel()).reshape(H, W)
    rows, cols = np.nonzero(inside)
    if len(rows) == 0:
        return None
    centres = origin + S[rows, cols][:, None] * s_axis + T[rows, cols][:, None] * t_axis
    return RefGrid(
        polygon, float(size), s_axis, t_axis, origin, float(s0), float(t0), (H, W), rows, cols, centres
    )


def coplanar_groups(
    polygons: list[ScenePolygon], angle_tol: float = 1e-4, offset_tol_m: float = 0.02
) -> np.ndarray:
    """`(P,)` int group per polygon: polygons of the same building and class lying in one plane
    (normals within `angle_tol` of parallel, same side, offsets within `offset_tol_m`) share the
    smallest index among them; all others are their own group."""
    group = np.arange(len(polygons))
    by_key: dict[tuple[str, str], list[ScenePolygon]] = {}
    for p in polygons:
        by_key.setdefault((p.building_id, p.surface_class), []).append(p)
    for members in by_key.values():
        for i, a in enumerate(members):
            for b in members[:i]:
                if a.normal @ b.normal > 1 - angle_tol and abs(a.offset - b.offset) < offset_tol_m:
                    group[a.index] = group[b.index]
                    break
    return group

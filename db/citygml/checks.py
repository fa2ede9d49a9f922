"""Geometry checks per polygon, reported and never fixed.

In: `citymodel.Building`s (rings `(N, 3)` float64 in the model CRS, metres). Out: one
`PolygonCheck` per polygon: plane (normal, offset) from `geometry.fit_plane`, non-planarity (max
vertex distance to the best-fit plane, m), area (m²), distinct vertex count, and the flags
too few vertices, zero area, non-planar, self-intersecting ring (in the polygon's plane, shapely),
unclosed rings, and for walls whether the normal points away from the building.

Outward test: a ray leaves the wall's centroid along its normal (slightly tilted, to avoid
grazing edges) and its crossings with the building's triangulated surfaces are counted; an odd
count means the normal points into the building. The surfaces used are the building's solid
(`in_solid` polygons) where it has one, else all its polygons; each building part is tested
against its own surfaces. The ray starts just outside the centre of the polygon's largest
triangle; three slightly different directions vote. Result `None` when the building has too
few surfaces to enclose a volume, and for a wall modelled twice between two sections of one
building (a party wall, once per section, the copies facing opposite ways), which faces the
inside of one section or the other whatever its orientation.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np
import shapely

from workers.pipeline.geometry.citymodel import Building, Polygon
from workers.pipeline.geometry.polygons import fit_plane, open_ring, surface_axes, to_plane_2d, triangulate

__all__ = ["CheckOptions", "PolygonCheck", "check_building", "check_buildings", "check_polygon"]


@dataclass(frozen=True)
class CheckOptions:
    """Tolerances of the geometry checks.

    Attributes:
        planarity_tolerance_m: largest vertex distance from the best-fit plane before a polygon
            is reported non-planar (m). CityGML QA practice uses 1 cm; 5 cm suits survey data.
        min_area_m2: polygons with a smaller area are reported as zero-area (m²).
        closure_tolerance_m: a ring whose last vertex is farther than this from its first is
            reported unclosed (m); 0 demands exact repetition, as GML does.
        outward_offset_m: distance from the wall centroid where the outward ray starts (m).
    """

    planarity_tolerance_m: float = 0.05
    min_area_m2: float = 1e-4
    closure_tolerance_m: float = 0.0
    outward_offset_m: float = 1e-3


@dataclass(frozen=True, eq=False)
class PolygonCheck:
    """Check result of one polygon.

    Attributes:
        building_id: id of the building or part owning the polygon.
        polygon_id: the polygon's id.
        surface_class: its semantic class.
        vertices: number of distinct exterior vertices (closing vertex not counted).
        normal: `(3,)` unit normal of the best-fit plane (right-hand rule of the exterior ring),
            None when degenerate.
        offset: plane offset `normal · x` (m), NaN when degenerate.
        planarity_m: max distance of any vertex to the plane (m), NaN when degenerate.
        area_m2: area in the plane, holes subtracted (m²).
        too_few_vertices: fewer than 3 distinct vertices in some ring.
        zero_area: area below `min_area_m2` (or no plane).
        non_planar: `planarity_m` above the tolerance.
        self_intersecting: a ring crosses itself in the polygon's plane.
        unclosed_rings: ids of rings whose last vertex does not repeat the first.
        normal_outward: walls only: True when the normal points away from the building, False
            when into it, None when not tested.
    """

    building_id: str
    polygon_id: str
    surface_class: str
    vertices: int
    normal: np.ndarray | None
    offset: float
    planarity_m: float
    area_m2: float
    too_few_vertices: bool
    zero_area: bool
    non_planar: bool
    self_intersecting: bool
    unclosed_rings: tuple[str, ...]
    normal_outward: bool | None = None

    @property
    def problems(self) -> tuple[str, ...]:
        """Names of the failed checks (empty when the polygon passed all)."""
        out = []
        for name in ("too_few_vertices", "zero_area", "non_planar", "self_intersecting"):
            if getattr(self, name):
                out.append(name)
        if self.unclosed_rings:
            out.append("unclosed_ring")
        if self.normal_outward is False:
            out.append("wall_normal_inward")
        return tuple(out)

    @property
    def ok(self) -> bool:
        """True when no check failed."""
        return not self.problems


def _distinct(coords: np.ndarray) -> int:
    """Number of distinct vertices of a ring (to 1e-9 m)."""
    return len({tuple(v) for v in np.round(coords, 9).tolist()})


def _distinct_ok(polygon: Polygon) -> bool:
    """Every ring has at least 3 distinct vertices."""
    return all(_distinct(r.coords) >= 3 for r in polygon.rings)


_UNSET = object()


def check_polygon(
    polygon: Polygon,
    building_id: str = "",
    options: CheckOptions | None = None,
    *,
    plane: object = _UNSET,
) -> PolygonCheck:
    """Check one polygon (the outward-normal test needs the building: see `check_building`).

    `plane`: its `geometry.fit_plane` result when already computed."""
    opt = options or CheckOptions()
    rings = polygon.rings
    unclosed = tuple(
        r.id
        for r in rings
        if len(r.coords) < 2 or float(np.linalg.norm(r.coords[0] - r.coords[-1])) > opt.closure_tolerance_m
    )
    too_few = not _distinct_ok(polygon)
    if plane is _UNSET:
        plane = None if too_few else fit_plane(polygon)
    selfx = False
    frame = None
    if plane is not None:
        frame = (plane.normal, plane.centroid)
    elif not too_few:  # zero net area (e.g. a bow-tie): a plane through the points still exists
        pts = open_ring(polygon.exterior.coords)
        centre = pts.mean(axis=0)
        _, sv, vt = np.linalg.svd(pts - centre, full_matrices=False)
        if len(sv) >= 2 and sv[1] > 1e-9:
            frame = (vt[-1], centre)
    if frame is not None:
        s, t = surface_axes(frame[0], polygon.exterior.coords)
        for r in rings:
            uv = to_plane_2d(open_ring(r.coords), frame[1], s, t)
            if len(uv) >= 3 and not shapely.is_simple(shapely.linearrings(uv)):
                selfx = True
                break
    area = plane.area if plane is not None else 0.0
    return PolygonCheck(
        building_id=building_id,
        polygon_id=polygon.id,
        surface_class=polygon.surface_class,
        vertices=_distinct(polygon.exterior.coords),
        normal=None if plane is None else plane.normal,
        offset=float("nan") if plane is None else plane.offset,
        planarity_m=float("nan") if plane is None else plane.max_deviation,
        area_m2=area,
        too_few_vertices=too_few,
        zero_area=plane is None or area < opt.min_area_m2,
        non_planar=plane is not None and plane.max_deviation > opt.planarity_tolerance_m,
        self_intersecting=selfx,
        unclosed_rings=unclosed,
    )


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of broadcastable `(..., 3)` arrays (cheaper than `np.cross`)."""
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def _ray_crossings(
    origins: np.ndarray, directions: np.ndarray, tri: np.ndarray, t_max: float = np.inf
) -> np.ndarray:
    """Crossings `(R,)` of rays (origins, unit directions `(R, 3)`) with triangles `(T, 3, 3)`
    (Möller-Trumbore, hits at 0 < t < t_max counted)."""
    v0 = tri[None, :, 0]
    e1 = (tri[:, 1] - tri[:, 0])[None]
    e2 = (tri[:, 2] - tri[:, 0])[None]
    d = directions[:, None, :]
    p = _cross(d, e2)
    det = np.sum(e1 * p, axis=-1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tv = origins[:, None, :] - v0
    u = np.sum(tv * p, axis=-1) * inv
    q = _cross(tv, e1)
    v = np.sum(q * d, axis=-1) * inv
    t = np.sum(e2 * q, axis=-1) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9) & (t < t_max)
    return np.count_nonzero(hit, axis=1)


#: Small fixed tilts of the outward ray (three votes; avoids rays grazing edges or faces).
_TILTS = np.array([[0.013, 0.021, 0.017], [-0.019, 0.011, -0.023], [0.007, -0.029, 0.031]])


def _triangles(polys: list[Polygon], planes: list, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles `(T, 3, 3)` relative to `origin` and the index of their polygon `(T,)`."""
    out, owner = [], []
    for k, (p, plane) in enumerate(zip(polys, planes, strict=True)):
        if plane is None:
            continue
        verts, idx = triangulate(p, plane)
        if len(idx):
            out.append((verts - origin)[idx])
            owner.append(np.full(len(idx), k))
    if not out:
        return np.zeros((0, 3, 3)), np.zeros(0, dtype=int)
    return np.concatenate(out, axis=0), np.concatenate(owner)


def _outward(b: Building, checks: list[PolygonCheck], planes: list, opt: CheckOptions) -> list[PolygonCheck]:
    polys = list(b.polygons)
    solid = [p.in_solid for p in polys]
    use = solid if sum(solid) >= 4 else [True] * len(polys)
    if sum(use) < 4:
        return checks
    origin = np.mean([p.exterior.coords[0] for p in polys], axis=0)
    tri, owner = _triangles(polys, planes, origin)
    hull = tri[np.asarray(use)[owner]] if len(tri) else tri
    walls = [k for k, (p, c) in enumerate(zip(polys, checks, strict=True))
             if p.surface_class == "WallSurface" and c.normal is not None and np.any(owner == k)]  # fmt: skip
    if not len(hull) or not walls:
        return checks
    starts, dirs = [], []
    for k in walls:
        own = tri[owner == k]
        areas = np.linalg.norm(_cross(own[:, 1] - own[:, 0], own[:, 2] - own[:, 0]), axis=1)
        n = checks[k].normal
        start = own[int(np.argmax(areas))].mean(axis=0) + opt.outward_offset_m * n
        d = n[None, :] + _TILTS
        starts.append(np.repeat(start[None], len(_TILTS), axis=0))
        dirs.append(d / np.linalg.norm(d, axis=1, keepdims=True))
    o, d = np.concatenate(starts), np.concatenate(dirs)
    odd = _ray_crossings(o, d, hull) % 2
    votes = odd.reshape(len(walls), len(_TILTS)).sum(axis=1)
    # a wall modelled twice (party wall between two sections, the other copy facing the other
    # way): a short ray back through the wall crosses both copies; its side cannot be judged
    back = _ray_crossings(o, -d, tri, t_max=3.0 * opt.outward_offset_m)
    shared = back.reshape(len(walls), len(_TILTS)).min(axis=1) >= 2
    out = list(checks)
    for k, v, sh in zip(walls, votes, shared, strict=True):
        out[k] = PolygonCheck(**{**checks[k].__dict__, "normal_outward": None if sh else bool(v < 2)})
    return out


def check_building(building: Building, options: CheckOptions | None = None) -> list[PolygonCheck]:
    """Checks of every polygon of a building and its parts (own polygons first, then parts)."""
    opt = options or CheckOptions()
    out: list[PolygonCheck] = []
    for b in building.iter_buildings():
        planes = [fit_plane(p) if _distinct_ok(p) else None for p in b.polygons]
        checks = [check_polygon(p, b.id, opt, plane=pl) for p, pl in zip(b.polygons, planes, strict=True)]
        out.extend(_outward(b, checks, planes, opt))
    return out


def check_buildings(
    buildings: Iterable[Building], options: CheckOptions | None = None
) -> Iterator[PolygonCheck]:
    """`check_building` over many buildings, streamed."""
    for b in buildings:
        yield from check_building(b, options)

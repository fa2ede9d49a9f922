"""Ray casting through the triangulated city model (Open3D `RaycastingScene`, Embree inside).

In: buildings (`citymodel.Building`), rays or point/centre pairs in world coordinates (model
CRS, metres). Out: a picklable `SceneMesh` (triangles with their polygon of origin) and, per ray,
the hit distance, the polygon hit and its normal; per point, whether it is visible from a centre.

Open3D works in float32, which resolves only ~0.5 m at UTM northings (~5.3e6 m): the mesh is
therefore stored relative to a local `origin` (float64) and every query is shifted by it before
the float32 cast. `RayCaster` holds native Open3D objects and is not picklable; build one per
process from the `SceneMesh`.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from workers.pipeline.geometry.citymodel import Building, Polygon
from workers.pipeline.geometry.open3d_light import load_open3d
from workers.pipeline.geometry.polygons import fit_plane, triangulate


@dataclass(frozen=True, eq=False)
class SceneMesh:
    """Triangulated surfaces of a set of buildings.

    Attributes:
        origin: `(3,)` float64 local origin in the model CRS; `vertices` are relative to it.
        vertices: `(V, 3)` float32 vertex positions minus `origin`, metres.
        triangles: `(T, 3)` int32 vertex indices, wound like their polygon's exterior ring.
        triangle_polygon: `(T,)` int32 index into `polygon_ids` of each triangle's polygon.
        polygon_ids: `(P,)` polygon ids, in the order the buildings and polygons were given.
        polygon_building: `(P,)` id of the top-level building owning each polygon.
        polygon_normals: `(P, 3)` float64 unit normals (right-hand rule of the exterior ring).
    """

    origin: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray
    triangle_polygon: np.ndarray
    polygon_ids: tuple[str, ...]
    polygon_building: tuple[str, ...]
    polygon_normals: np.ndarray

    @property
    def n_polygons(self) -> int:
        """Number of polygons P."""
        return len(self.polygon_ids)

    def polygon_index(self) -> dict[str, int]:
        """Polygon id -> index into `polygon_ids`."""
        return {pid: i for i, pid in enumerate(self.polygon_ids)}


def build_scene_mesh(buildings: Iterable[Building], origin: np.ndarray | None = None) -> SceneMesh:
    """Triangulate every polygon of `buildings` (parts included) into one mesh.

    Args:
        buildings: top-level buildings; polygons that cannot be triangulated (degenerate) are kept
            in `polygon_ids` with no triangles and a zero normal.
        origin: local origin `(3,)`; default: the minimum corner of all vertices, rounded to 1 m.
    """
    verts: list[np.ndarray] = []
    tris: list[np.ndarray] = []
    tri_poly: list[np.ndarray] = []
    pids: list[str] = []
    pbld: list[str] = []
    normals: list[np.ndarray] = []
    n_verts = 0
    for building in buildings:
        for poly in building.iter_polygons():
            normal, v, t = _polygon_mesh(poly)
            k = len(pids)
            pids.append(poly.id)
            pbld.append(building.id)
            normals.append(normal)
            if len(t):
                verts.append(v)
                tris.append(np.asarray(t, dtype=np.int64) + n_verts)
                tri_poly.append(np.full(len(t), k, dtype=np.int32))
                n_verts += len(v)
    all_v = np.concatenate(verts, axis=0) if verts else np.zeros((0, 3))
    if origin is None:
        origin = np.floor(all_v.min(axis=0)) if len(all_v) else np.zeros(3)
    origin = np.asarray(origin, dtype=np.float64)
    return SceneMesh(
        origin=origin,
        vertices=(all_v - origin).astype(np.float32),
        triangles=(np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)).astype(np.int32),
        triangle_polygon=np.concatenate(tri_poly) if tri_poly else np.zeros(0, np.int32),
        polygon_ids=tuple(pids),
        polygon_building=tuple(pbld),
        polygon_normals=np.array(normals, dtype=np.float64).reshape(-1, 3),
    )


#: triangulated polygons of this process, by id and coordinates (a neighbour is an occluder of
#: many units: a flight's units triangulated the same polygons dozens of times)
_MESH_CACHE: OrderedDict[tuple[str, bytes], tuple[np.ndarray, np.ndarray, np.ndarray]] = OrderedDict()
_MESH_CACHE_SIZE = 200_000


def _polygon_mesh(poly: Polygon) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(normal (3,), vertices (M, 3) float64 world, triangles (K, 3) int64)` of a polygon
    (zero normal and no triangles when degenerate), cached per process by id and coordinates."""
    h = hashlib.blake2b(digest_size=16)
    for r in poly.rings:
        h.update(np.ascontiguousarray(r.coords, dtype=np.float64).tobytes())
        h.update(b"|")
    key = (poly.id, h.digest())
    hit = _MESH_CACHE.get(key)
    if hit is not None:
        _MESH_CACHE.move_to_end(key)
        return hit
    plane = fit_plane(poly)
    if plane is None:
        out = (np.zeros(3), np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    else:
        v, t = triangulate(poly, plane)
        out = (plane.normal, v, np.asarray(t, np.int64))
    _MESH_CACHE[key] = out
    if len(_MESH_CACHE) > _MESH_CACHE_SIZE:
        _MESH_CACHE.popitem(last=False)
    return out


@dataclass(frozen=True, eq=False)
class RayHits:
    """First hits of a batch of rays.

    Attributes:
        t: `(N,)` float64 distance along the (unit) ray to the hit, metres; `inf` on a miss.
        polygon: `(N,)` int32 index into `SceneMesh.polygon_ids`; -1 on a miss.
        normal: `(N, 3)` float64 unit normal of the triangle hit (zeros on a miss).
    """

    t: np.ndarray
    polygon: np.ndarray
    normal: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        """`(N,)` bool: the ray hit something."""
        return self.polygon >= 0


def open3d_scene(mesh: SceneMesh) -> Any:
    """An Open3D `RaycastingScene` over `mesh.vertices` (the mesh's local frame)."""
    o3d = load_open3d()  # here: heavy, and only the processes that cast need it

    scene = o3d.t.geometry.RaycastingScene()
    if len(mesh.triangles):
        scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(mesh.triangles, dtype=np.uint32)),
        )
    return scene


class RayCaster:
    """Ray queries against a `SceneMesh` (Open3D `RaycastingScene`, multi-threaded)."""

    def __init__(self, mesh: SceneMesh) -> None:
        o3d = load_open3d()  # here: heavy, and only the processes that cast need it

        self.mesh = mesh
        self._o3d = o3d
        self._scene = open3d_scene(mesh)
        self._empty = len(mesh.triangles) == 0

    def cast_local(self, rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cast rays given directly in the mesh's local frame, for hot loops that build them in
        float32 themselves.

        Args:
            rays: `(N, 6)` float32 `[ox, oy, oz, dx, dy, dz]`, origins relative to `mesh.origin`.

        Returns:
            `(t (N,) float32, polygon (N,) int32)`: distance in units of the direction's length
            (inf on a miss) and the index into `polygon_ids` (-1 on a miss).
        """
        n = len(rays)
        if self._empty or n == 0:
            return np.full(n, np.inf, np.float32), np.full(n, -1, np.int32)
        ans = self._scene.cast_rays(self._o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays, np.float32)))
        t = ans["t_hit"].numpy()
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        polygon = np.full(n, -1, np.int32)
        hit = np.isfinite(t)
        polygon[hit] = self.mesh.triangle_polygon[prim[hit]]
        return t, polygon

    def _rays(self, origins: np.ndarray, directions: np.ndarray) -> object:
        o = np.asarray(origins, dtype=np.float64) - self.mesh.origin
        d = np.asarray(directions, dtype=np.float64)
        o, d = np.broadcast_arrays(o, d)
        rays = np.concatenate([o, d], axis=-1).reshape(-1, 6).astype(np.float32)
        return self._o3d.core.Tensor(np.ascontiguousarray(rays))

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> RayHits:
        """First hit of rays `origins (N, 3)` world + s·`directions (N, 3)` (unit vectors), s > 0."""
        n = int(np.broadcast_shapes(np.shape(origins), np.shape(directions))[0])
        if self._empty or n == 0:
            return RayHits(np.full(n, np.inf), np.full(n, -1, np.int32), np.zeros((n, 3)))
        ans = self._scene.cast_rays(self._rays(origins, directions))
        t = ans["t_hit"].numpy().astype(np.float64)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t)
        polygon = np.full(n, -1, np.int32)
        polygon[hit] = self.mesh.triangle_polygon[prim[hit]]
        normal = np.zeros((n, 3))
        normal[hit] = ans["primitive_normals"].numpy()[hit]
        return RayHits(t=np.where(hit, t, np.inf), polygon=polygon, normal=normal)

    def visible(self, points: np.ndarray, center: np.ndarray, tolerance_m: float = 0.05) -> np.ndarray:
        """`(N,)` bool: nothing in the mesh lies between `center (3,)` and each point `(N, 3)`.

        Rays start at the centre and stop `tolerance_m` before the point, so a point lying on a
        surface does not occlude itself.
        """
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if self._empty or len(pts) == 0:
            return np.ones(len(pts), dtype=bool)
        d = pts - np.asarray(center, dtype=np.float64)
        dist = np.linalg.norm(d, axis=1)
        # Open3D's tfar is one scalar: scale each direction so that t = 1 is `tolerance_m` short
        # of its point, and test occlusions on t in (0, 1).
        scale = np.maximum(dist - tolerance_m, 0.0) / np.maximum(dist, 1e-12)
        occluded = self._scene.test_occlusions(
            self._rays(np.broadcast_to(center, pts.shape), d * scale[:, None]), tnear=0.0, tfar=1.0
        )
        return ~occluded.numpy().astype(bool)

"""The synthetic world's ground: a horizontal plane, or a terrain through the buildings' feet.

A real LoD2 model's walls end at the terrain. One ground plane at the cluster's median base
height is right for procedural blocks (every base at one height) but, on hilly terrain (the NRW
tile's bases span 2.4 m), it buries the foot of the lower-standing walls and floats under the
higher ones: a wall whose lower half the world hides is one the city model, and so the product,
takes for visible.

`terrain_ground(buildings, z0)` -> `Ground`: a TIN (`scipy.spatial.Delaunay` in x/y) through the
buildings' foot points, the vertices of their `GroundSurface` rings (the bottom vertices of their
walls where a building has none) densified every `spacing_m` along the footprint edges so that the
TIN follows them (the terrain meets every wall at its foot, within millimetres), surrounded by an
outer square `margin_m` beyond the points at `z0`; beyond that square the ground is the plane
`z = z0`. Where foot points of different buildings coincide in x/y (shared walls) the lower one is
kept: the ground never cuts a wall above its foot. When every foot point lies within `flat_tol_m`
of the others, the ground is the plane `z = z0` alone (`Ground.flat`): the same world, bit for
bit, as before the terrain existed.

Coordinates: model CRS, metres (world); `Ground.height` takes `(N, 2)` x/y and returns `(N,)` z.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.synth.common import SynthError


@dataclass(frozen=True, eq=False)
class Ground:
    """The ground of a synthetic scene.

    Attributes:
        z: height of the plane (the whole ground when `flat`, else beyond the TIN's outer square), m.
        vertices: `(V, 3)` float64 TIN vertices (world, m); empty when flat.
        triangles: `(T, 3)` int32 vertex indices, counter-clockwise seen from above; empty when flat.
    """

    z: float
    vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    triangles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int32))

    @property
    def flat(self) -> bool:
        """True when the ground is the plane `z = self.z` everywhere."""
        return len(self.triangles) == 0

    @property
    def top(self) -> float:
        """The highest ground height anywhere, m: no point above it is below the ground."""
        return float(max(self.z, self.vertices[:, 2].max())) if len(self.vertices) else float(self.z)

    @cached_property
    def _locator(self) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
        """A bucket grid over the TIN: (grid origin `(2,)`, cell size m, grid shape `(2,)`,
        CSR start per cell `(C + 1,)`, triangle indices `(K,)`) of the triangles whose x/y box
        meets each cell."""
        V, T = self.vertices, self.triangles
        lo, hi = V[:, :2].min(axis=0), V[:, :2].max(axis=0)
        a, b, c = V[T[:, 0], :2], V[T[:, 1], :2], V[T[:, 2], :2]
        tlo, thi = np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)
        # cells about the size of a typical (median) triangle
        cell = max(float(np.median(np.max(thi - tlo, axis=1))), 1e-3)
        shape = np.maximum(np.ceil((hi - lo) / cell).astype(np.int64), 1)
        shape = np.minimum(shape, 4096)
        cell = float(np.max((hi - lo) / shape)) * (1 + 1e-9)
        c0 = np.clip(((tlo - lo) / cell).astype(np.int64), 0, shape - 1)
        c1 = np.clip(((thi - lo) / cell).astype(np.int64), 0, shape - 1)
        cells, tris = [], []
        for t in range(len(T)):
            ix, iy = np.meshgrid(np.arange(c0[t, 0], c1[t, 0] + 1), np.arange(c0[t, 1], c1[t, 1] + 1))
            cells.append((ix * shape[1] + iy).ravel())
            tris.append(np.full(ix.size, t))
        cid, tid = np.concatenate(cells), np.concatenate(tris)
        order = np.argsort(cid, kind="stable")
        start = np.searchsorted(cid[order], np.arange(shape[0] * shape[1] + 1))
        return lo, cell, shape, start, tid[order]

    def height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height `(N,)` float64 m under world points `xy` `(N, 2)` (or `(N, 3)`, z ignored):
        on the TIN's triangles (barycentric), `z` outside them."""
        out = np.full(len(xy), self.z)
        if self.flat or len(xy) == 0:
            return out
        P = np.asarray(xy, dtype=np.float64).reshape(len(xy), -1)[:, :2]
        lo, cell, shape, start, tris = self._locator
        g = np.floor((P - lo) / cell).astype(np.int64)
        idx = np.flatnonzero(np.all((g >= 0) & (g < shape), axis=1))
        if len(idx) == 0:
            return out
        c = g[idx, 0] * shape[1] + g[idx, 1]
        first, count = start[c], start[c + 1] - start[c]
        V, T = self.vertices, self.triangles
        # each point tries its cell's triangles in order until one holds it; only the points not
        # yet placed go on to the next round (a cell under the outer square's long triangles holds
        # many, so rounds over every point cost O(points x triangles per cell))
        m = np.arange(len(idx))
        k = 0
        while len(m):
            m = m[count[m] > k]
            if len(m) == 0:
                break
            t = T[tris[first[m] + k]]
            a, b, cc = V[t[:, 0]], V[t[:, 1]], V[t[:, 2]]
            e1, e2, r = b[:, :2] - a[:, :2], cc[:, :2] - a[:, :2], P[idx[m]] - a[:, :2]
            det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                u = (r[:, 0] * e2[:, 1] - r[:, 1] * e2[:, 0]) / det
                v = (e1[:, 0] * r[:, 1] - e1[:, 1] * r[:, 0]) / det
            eps = 1e-9
            hit = (det != 0) & (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps)
            h = m[hit]
            out[idx[h]] = a[hit, 2] + u[hit] * (b[hit, 2] - a[hit, 2]) + v[hit] * (cc[hit, 2] - a[hit, 2])
            m = m[~hit]
            k += 1
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON form (the truth file's `ground`): `{"z", "vertices", "triangles"}`."""
        return {
            "z": float(self.z),
            "vertices": np.round(self.vertices, 4).tolist(),
            "triangles": self.triangles.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Ground:
        """Inverse of `to_dict`; raises `SynthError` on a malformed TIN."""
        V = np.asarray(d.get("vertices") or [], dtype=np.float64).reshape(-1, 3)
        T = np.asarray(d.get("triangles") or [], dtype=np.int32).reshape(-1, 3)
        if len(T) and (T.min() < 0 or T.max() >= len(V)):
            raise SynthError("ground: a triangle indexes a missing vertex")
        return cls(float(d["z"]), V, T)


def foot_points(buildings: Sequence[Building], spacing_m: float) -> np.ndarray:
    """`(N, 3)` world points along the buildings' footprint edges: the rings of every
    `GroundSurface` of a building and its parts (for a building or part without one: the vertices
    of its walls within 1 cm of its lowest point), each edge divided into pieces of at most
    `spacing_m` metres."""
    out: list[np.ndarray] = []
    for b in buildings:
        for part in b.iter_buildings():
            rings = [r.coords for p in part.polygons if p.surface_class == "GroundSurface" for r in p.rings]
            if not rings:
                walls = [r.coords for p in part.polygons if p.surface_class == "WallSurface" for r in p.rings]
                if walls:
                    pts = np.concatenate(walls)
                    out.append(pts[pts[:, 2] <= pts[:, 2].min() + 0.01])
                continue
            for ring in rings:
                R = np.asarray(ring, dtype=np.float64)
                for a, c in zip(R, np.roll(R, -1, axis=0), strict=True):
                    n = max(int(np.ceil(np.linalg.norm(c[:2] - a[:2]) / spacing_m)), 1)
                    s = np.arange(n)[:, None] / n
                    out.append(a + s * (c - a))
    return np.concatenate(out) if out else np.zeros((0, 3))


def terrain_ground(
    buildings: Sequence[Building],
    z0: float,
    spacing_m: float = 1.0,
    margin_m: float = 200.0,
    flat_tol_m: float = 1e-3,
) -> Ground:
    """The ground of a scene of `buildings` (see the module docstring): the plane `z = z0` when
    their foot points lie within `flat_tol_m` of each other (or there are fewer than 3), else the
    TIN through them inside an outer square at `z0`, `margin_m` beyond them."""
    from scipy.spatial import Delaunay

    pts = foot_points(buildings, spacing_m)
    if len(pts) < 3 or float(np.ptp(pts[:, 2])) <= flat_tol_m:
        return Ground(float(z0))
    # one point per centimetre cell of x/y: the lowest (shared walls of buildings at two heights)
    key = np.round(pts[:, :2] * 100.0).astype(np.int64)
    order = np.lexsort((pts[:, 2], key[:, 1], key[:, 0]))
    key, pts = key[order], pts[order]
    first = np.ones(len(pts), bool)
    first[1:] = np.any(key[1:] != key[:-1], axis=1)
    pts = pts[first]
    lo, hi = pts[:, :2].min(axis=0) - margin_m, pts[:, :2].max(axis=0) + margin_m
    square = np.array([[lo[0], lo[1], z0], [hi[0], lo[1], z0], [hi[0], hi[1], z0], [lo[0], hi[1], z0]])
    V = np.concatenate([pts, square])
    origin = V[:, :2].mean(axis=0)
    tri = Delaunay(V[:, :2] - origin).simplices.astype(np.int32)
    # counter-clockwise seen from above (upward normals)
    e1 = V[tri[:, 1], :2] - V[tri[:, 0], :2]
    e2 = V[tri[:, 2], :2] - V[tri[:, 0], :2]
    cw = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0
    tri[cw] = tri[cw][:, [0, 2, 1]]
    return Ground(float(z0), V, tri)

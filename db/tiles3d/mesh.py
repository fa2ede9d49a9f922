"""A building's polygons as triangles with texture coordinates, ready for glTF.

In: a top-level `Building` (parts nested) in the model CRS and the appearance theme to texture
it with. Out: a `BuildingMesh`: vertices `(V, 3)` float64 in the model CRS, glTF texture
coordinates `(V, 2)` float32, triangles `(T, 3)` with the surface and the image each one belongs
to, and the surfaces (building, polygon and semantic class) in order.

Triangulation is the pipeline's own (`workers.pipeline.geometry.polygons.triangulate`: ear
clipping in the polygon's plane, holes respected, triangles wound like the exterior ring). Its
vertices are the open rings, exterior first, then every interior ring with 3 vertices or more;
texture coordinates follow the same order, closing vertex dropped. CityGML's `(s, t)` (t upwards,
(0, 0) the lower-left corner) become glTF's `(u, v) = (s, 1 - t)` (v downwards from the top
row). A polygon whose target lacks a ring's coordinates, or has the wrong number of them, is
kept untextured.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.citymodel import Appearance, Building, ParameterizedTexture, TextureTarget
from workers.pipeline.geometry.polygons import open_ring, triangulate

__all__ = ["BuildingMesh", "SurfaceRef", "building_mesh", "theme_appearance"]


@dataclass(frozen=True)
class SurfaceRef:
    """One polygon of a building: ids as written (`gml:id`) and its semantic class."""

    building: str
    surface: str
    surface_class: str


@dataclass(frozen=True, eq=False)
class BuildingMesh:
    """Triangles of one top-level building.

    Attributes:
        building_id: `gml:id` of the top-level building.
        vertices: `(V, 3)` float64, model CRS, metres.
        uv: `(V, 2)` float32 glTF texture coordinates (u right, v down); 0 where untextured.
        triangles: `(T, 3)` int64 indices into `vertices`, wound like the polygons' exterior rings.
        triangle_surface: `(T,)` int32 index into `surfaces`.
        triangle_image: `(T,)` int32 index into `images`, -1 for an untextured polygon.
        surfaces: the building's polygons (parts included), document order.
        images: texture image URIs (relative to the results folder), first use order.
    """

    building_id: str
    vertices: np.ndarray
    uv: np.ndarray
    triangles: np.ndarray
    triangle_surface: np.ndarray
    triangle_image: np.ndarray
    surfaces: tuple[SurfaceRef, ...]
    images: tuple[str, ...]

    def centre(self) -> np.ndarray:
        """`(3,)` centre of the vertices' bounding box (model CRS), or of nothing: NaN."""
        if not len(self.vertices):
            return np.full(3, np.nan)
        return 0.5 * (self.vertices.min(axis=0) + self.vertices.max(axis=0))


def theme_appearance(building: Building, theme: str) -> Appearance | None:
    """The building's appearance of `theme` with textures: the last one (a job's appearance is
    written after those that came with the input model), looked for in the parts too."""
    found = None
    for b in building.iter_buildings():
        for app in b.appearances:
            if app.theme == theme and any(isinstance(sd, ParameterizedTexture) for sd in app.surface_data):
                found = app
    return found


def _targets(app: Appearance | None) -> dict[str, tuple[str, TextureTarget]]:
    """polygon id -> (image URI, target) of an appearance's parameterized textures."""
    out: dict[str, tuple[str, TextureTarget]] = {}
    if app is None:
        return out
    for sd in app.surface_data:
        if isinstance(sd, ParameterizedTexture):
            for t in sd.targets:
                out[t.polygon_id] = (sd.image_uri, t)
    return out


def _ring_uv(target: TextureTarget, ring_id: str, n: int) -> np.ndarray | None:
    """`(n, 2)` glTF UV of a ring's `n` open vertices, or None when the target does not give them."""
    st = target.ring_coords.get(ring_id)
    if st is None:
        return None
    st = np.asarray(st, dtype=np.float64).reshape(-1, 2)
    if len(st) == n + 1 or len(st) == n:
        st = st[:n]
    else:
        return None
    return np.stack([st[:, 0], 1.0 - st[:, 1]], axis=-1)


def building_mesh(building: Building, theme: str) -> BuildingMesh:
    """Triangulate every polygon of `building` (parts included) and give each textured polygon's
    vertices their texture coordinates from the building's `theme` appearance."""
    targets = _targets(theme_appearance(building, theme))
    verts: list[np.ndarray] = []
    uvs: list[np.ndarray] = []
    tris: list[np.ndarray] = []
    tri_surface: list[np.ndarray] = []
    tri_image: list[np.ndarray] = []
    surfaces: list[SurfaceRef] = []
    images: dict[str, int] = {}
    n_verts = 0
    for poly in building.iter_polygons():
        k = len(surfaces)
        surfaces.append(SurfaceRef(building.id, poly.id, poly.surface_class))
        v, t = triangulate(poly)
        if not len(t):
            continue
        uv, image = None, -1
        hit = targets.get(poly.id)
        if hit is not None:
            rings = [poly.exterior] + [r for r in poly.interiors if len(open_ring(r.coords)) >= 3]
            parts = [_ring_uv(hit[1], r.id, len(open_ring(r.coords))) for r in rings]
            if all(p is not None for p in parts):
                uv = np.concatenate(parts, axis=0)  # type: ignore[arg-type]
                image = images.setdefault(hit[0], len(images))
        verts.append(v)
        uvs.append(uv if uv is not None and len(uv) == len(v) else np.zeros((len(v), 2)))
        if uv is None or len(uv) != len(v):
            image = -1
        tris.append(np.asarray(t, dtype=np.int64) + n_verts)
        tri_surface.append(np.full(len(t), k, dtype=np.int32))
        tri_image.append(np.full(len(t), image, dtype=np.int32))
        n_verts += len(v)
    return BuildingMesh(
        building_id=building.id,
        vertices=np.concatenate(verts) if verts else np.zeros((0, 3)),
        uv=(np.concatenate(uvs) if uvs else np.zeros((0, 2))).astype(np.float32),
        triangles=np.concatenate(tris) if tris else np.zeros((0, 3), np.int64),
        triangle_surface=np.concatenate(tri_surface) if tri_surface else np.zeros(0, np.int32),
        triangle_image=np.concatenate(tri_image) if tri_image else np.zeros(0, np.int32),
        surfaces=tuple(surfaces),
        images=tuple(images),
    )

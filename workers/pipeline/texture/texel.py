"""Texel grids: a regular raster laid on each planar surface polygon.

In: a `citymodel.Polygon` (model CRS, metres) and a resolution in texels per metre.
Out: a `TexelGrid` — the polygon's local 2D frame (`s` right, `t` up, as
`geometry.surface_axes`), the texel size, the raster size, the 3D centre of every texel and a
mask of the texels whose centre lies inside the polygon (holes excluded); a polygon too thin to
hold a texel centre gets the texels it overlaps.

Raster convention (the one of texture images): row `i` counts from the top (largest `t`),
column `j` from the left (smallest `s`). The centre of texel `(i, j)` lies at plane coordinates
`s = s_min + (j + 0.5)·size`, `t = t_max − (i + 0.5)·size`; the continuous raster coordinates
`(x, y) = ((s − s_min)/size, (t_max − t)/size)` put texel centres at half integers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely

from workers.pipeline.geometry.citymodel import Polygon
from workers.pipeline.geometry.polygons import fit_plane, open_ring, surface_axes, to_plane_2d


class TexelError(ValueError):
    """Bad input to the texel grid (e.g. a non-positive resolution)."""


@dataclass(frozen=True)
class TexelOptions:
    """Options of the texel-grid stage.

    Attributes:
        resolution_px_per_m: texels per metre on the surface (10 = 0.1 m texels).
        max_side: largest raster side in texels; a larger surface gets coarser texels so that it
            still fits (its texture must fit an atlas tile of 4096 with a gutter).
        min_area_m2: polygons smaller than this get no grid (slivers).
        follow_frames: lay a surface that the frames see only coarsely with coarser texels
            (`texture.sight.surface_resolution`): it gets a texture at the resolution the frames
            support instead of none (a flight at the default resolution).
        oversample: with `follow_frames`, texels may be this many times finer than the best
            pixel footprint on the surface (bilinear up-sampling), no finer.
    """

    resolution_px_per_m: float = 10.0
    max_side: int = 4080
    min_area_m2: float = 0.01
    follow_frames: bool = True
    oversample: float = 1.5

    def __post_init__(self) -> None:
        if not (self.resolution_px_per_m > 0 and math.isfinite(self.resolution_px_per_m)):
            raise TexelError(f"resolution_px_per_m must be positive, got {self.resolution_px_per_m}")
        if self.max_side < 1:
            raise TexelError(f"max_side must be >= 1, got {self.max_side}")


@dataclass(frozen=True, eq=False)
class TexelGrid:
    """A texel raster on one surface polygon.

    Attributes:
        polygon_id, building_id, surface_class: identity of the surface.
        normal: `(3,)` unit outward normal; s_axis, t_axis: `(3,)` unit axes in the plane.
        corner: `(3,)` world point at the top-left corner of the raster (`s_min`, `t_max`).
        size: texel edge length, metres.
        mask: `(H, W)` bool, texel centre inside the polygon (holes excluded).
        s_min, t_max: plane coordinates of `corner` relative to `plane_origin`.
        plane_origin: `(3,)` world origin of the plane coordinates.
    """

    polygon_id: str
    building_id: str
    surface_class: str
    normal: np.ndarray
    s_axis: np.ndarray
    t_axis: np.ndarray
    corner: np.ndarray
    size: float
    mask: np.ndarray
    s_min: float
    t_max: float
    plane_origin: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """`(H, W)` raster size in texels."""
        return self.mask.shape  # type: ignore[return-value]

    @property
    def n_texels(self) -> int:
        """Number of texels inside the polygon."""
        return int(self.mask.sum())

    def centres(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """World centres `(N, 3)` float64 of texels at integer `rows`, `cols` `(N,)`."""
        x = (np.asarray(cols, dtype=np.float64) + 0.5) * self.size
        y = (np.asarray(rows, dtype=np.float64) + 0.5) * self.size
        return self.corner + x[:, None] * self.s_axis - y[:, None] * self.t_axis

    def points_at(self, xy: np.ndarray) -> np.ndarray:
        """Continuous raster coordinates `(N, 2)` `(x, y)` -> world points `(N, 3)` on the plane."""
        xy = np.asarray(xy, dtype=np.float64)
        return self.corner + (xy[:, :1] * self.size) * self.s_axis - (xy[:, 1:2] * self.size) * self.t_axis

    def raster_xy(self, points: np.ndarray) -> np.ndarray:
        """World points `(N, 3)` -> continuous raster coordinates `(N, 2)` `(x, y)` (texel units,
        texel centres at half integers), after orthogonal projection onto the plane."""
        st = to_plane_2d(points, self.plane_origin, self.s_axis, self.t_axis)
        return np.stack([(st[:, 0] - self.s_min) / self.size, (self.t_max - st[:, 1]) / self.size], axis=1)

    def masked_indices(self) -> tuple[np.ndarray, np.ndarray]:
        """`(rows, cols)` `(N,)` int of the texels inside the polygon, row-major order."""
        return np.nonzero(self.mask)


def texel_grid(polygon: Polygon, building_id: str, options: TexelOptions) -> TexelGrid | None:
    """Lay a texel raster on `polygon`; None for degenerate or sliver polygons.

    The raster covers the bounding rectangle of the exterior ring in the plane's `(s, t)` frame;
    texel size is `1 / resolution_px_per_m`, enlarged when a side would exceed `max_side`.
    """
    plane = fit_plane(polygon)
    if plane is None or plane.area < options.min_area_m2:
        return None
    ext = open_ring(polygon.exterior.coords)
    s_axis, t_axis = surface_axes(plane.normal, ext)
    origin = plane.centroid
    ext_st = to_plane_2d(ext, origin, s_axis, t_axis)
    s_min, t_min = ext_st.min(axis=0)
    s_max, t_max = ext_st.max(axis=0)
    size = 1.0 / options.resolution_px_per_m
    extent = max(s_max - s_min, t_max - t_min)
    if extent / size > options.max_side:
        size = extent / options.max_side
    W = max(1, math.ceil((s_max - s_min) / size - 1e-9))
    H = max(1, math.ceil((t_max - t_min) / size - 1e-9))
    holes = [to_plane_2d(open_ring(r.coords), origin, s_axis, t_axis) for r in polygon.interiors]
    shape = shapely.Polygon(ext_st, [h for h in holes if len(h) >= 3])
    if not shape.is_valid:
        shape = shapely.make_valid(shape)
    cs = s_min + (np.arange(W) + 0.5) * size
    ct = t_max - (np.arange(H) + 0.5) * size
    S, T = np.meshgrid(cs, ct)
    shapely.prepare(shape)
    mask = shapely.contains_xy(shape, S.ravel(), T.ravel()).reshape(H, W)
    if not mask.any():  # a thin polygon (a dormer cheek, a roof strip) holds no texel centre
        h = 0.5 * size
        boxes = shapely.box(S.ravel() - h, T.ravel() - h, S.ravel() + h, T.ravel() + h)
        mask = shapely.intersects(shape, boxes).reshape(H, W)
    corner = origin + s_min * s_axis + t_max * t_axis
    return TexelGrid(
        polygon_id=polygon.id,
        building_id=building_id,
        surface_class=polygon.surface_class,
        normal=plane.normal,
        s_axis=s_axis,
        t_axis=t_axis,
        corner=corner,
        size=float(size),
        mask=mask,
        s_min=float(s_min),
        t_max=float(t_max),
        plane_origin=origin,
    )

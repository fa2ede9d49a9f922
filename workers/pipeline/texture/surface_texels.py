"""A surface's texels flattened for projection (`SurfaceTexels`): the texels inside the polygon in
square blocks with their world centres and bounds, so a frame's frustum test skips the blocks it
cannot see (`in_view`). World = model CRS, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.texture.texel import TexelGrid
from workers.pipeline.texture.visibility import boxes_in_frustum, frustum_extent
from workers.pipeline.texture.visibility_options import VisibilityOptions


@dataclass(frozen=True, eq=False)
class SurfaceTexels:
    """A texel grid with its texels inside the polygon flattened for projection, ordered by
    square blocks so that a frame's frustum test can skip the blocks it cannot see.

    Attributes:
        grid: the surface's `TexelGrid`.
        rows, cols: `(N,)` intp raster indices of the texels inside the polygon, block by block.
        points: `(N, 3)` float64 world centres of those texels.
        lo, hi: `(3,)` bounds of `points` (for the frustum test).
        block_start: `(B + 1,)` first texel of each block (and N).
        block_lo, block_hi: `(B, 3)` bounds of each block's texel centres.
    """

    grid: TexelGrid
    rows: np.ndarray
    cols: np.ndarray
    points: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    block_start: np.ndarray
    block_lo: np.ndarray
    block_hi: np.ndarray

    @classmethod
    def of(cls, grid: TexelGrid, block: int = 16) -> SurfaceTexels:
        """Flatten the texels of `grid` inside its polygon, in blocks of `block × block` texels."""
        rows, cols = grid.masked_indices()
        return cls._build(grid, rows, cols, grid.centres(rows, cols), block)

    @classmethod
    def _build(
        cls, grid: TexelGrid, rows: np.ndarray, cols: np.ndarray, pts: np.ndarray, block: int
    ) -> SurfaceTexels:
        n_bc = grid.shape[1] // block + 1
        key = (rows // block) * n_bc + cols // block
        order = np.argsort(key, kind="stable")
        rows, cols, pts, key = rows[order], cols[order], pts[order], key[order]
        if len(pts) == 0:
            z = np.zeros((0, 3))
            return cls(grid, rows, cols, pts, grid.corner, grid.corner, np.zeros(1, np.intp), z, z)
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        bounds = np.r_[starts, len(key)].astype(np.intp)
        return cls(
            grid=grid,
            rows=rows,
            cols=cols,
            points=pts,
            lo=pts.min(axis=0),
            hi=pts.max(axis=0),
            block_start=bounds,
            block_lo=np.minimum.reduceat(pts, starts, axis=0),
            block_hi=np.maximum.reduceat(pts, starts, axis=0),
        )

    def without(self, drop: np.ndarray, block: int = 16) -> SurfaceTexels:
        """The same surface without the texels flagged in `drop (N,)` (e.g. never visible)."""
        if not drop.any():
            return self
        keep = ~drop
        return SurfaceTexels._build(self.grid, self.rows[keep], self.cols[keep], self.points[keep], block)

    def in_view(
        self,
        camera: Camera,
        pose: Pose,
        options: VisibilityOptions,
        fused_resolution: np.ndarray | None = None,
        improve_factor: float = 1.0,
    ) -> np.ndarray:
        """Indices `(M,)` of the texels in the blocks that may appear in the frame at `pose` and
        may get a usable, better observation from it.

        A block is skipped when even the best local resolution the frame could give it (its
        nearest point seen head-on at the image corner's magnification) is coarser than
        `max_texel_ratio` texel sizes, or than what every texel of the block already has
        (`fused_resolution (H, W)`, inf where unobserved, times `improve_factor`).
        """
        ok = boxes_in_frustum(camera, pose, self.block_lo, self.block_hi, options)
        if ok.any():
            a_lo, a_hi, b_lo, b_hi = frustum_extent(camera, 0.0)
            gain = max(camera.fx, camera.fy) * (1.0 + max(a_lo**2, a_hi**2) + max(b_lo**2, b_hi**2))
            nearest = np.linalg.norm(np.clip(pose.center, self.block_lo, self.block_hi) - pose.center, axis=1)
            best = nearest / gain  # lower bound of the local resolution, m/px
            limit = np.full(len(best), options.max_texel_ratio * self.grid.size)
            if fused_resolution is not None:
                worst = np.maximum.reduceat(fused_resolution[self.rows, self.cols], self.block_start[:-1])
                limit = np.minimum(limit, worst * improve_factor)
            ok &= best < limit
        if ok.all():
            return np.arange(len(self.points))
        b = np.nonzero(ok)[0]
        if len(b) == 0:
            return np.zeros(0, np.intp)
        lengths = self.block_start[b + 1] - self.block_start[b]
        offsets = np.repeat(self.block_start[b] - np.r_[0, np.cumsum(lengths)[:-1]], lengths)
        return np.arange(int(lengths.sum())) + offsets

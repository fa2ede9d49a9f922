"""One frame over all surfaces of a unit at once: the texture stage's per-frame pass, vectorised.

In: the `SurfaceTexels` of a unit's surfaces (world = model CRS, metres) stacked once into
`UnitTexels` (every texel in one flat array, surface by surface and block by block), their
`SurfaceTexture`s, a frame's camera and pose. Out: the frame's winning observations before the
occlusion test (`observe`); `fusion.texture_frame` tests, samples and merges them.

Per frame, without a loop over surfaces until the merge: blocks of texels that cannot appear or
cannot improve (frustum, back side, resolution bound against the fused texels) are dropped,
the rest projected once and ranked by local resolution against what is fused; the winners are
then tested for occlusion and clean pixels in one call, sampled once, and merged surface by
surface. The result is the same as handling the surfaces one after the other.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.texture.fused import SurfaceTexture
from workers.pipeline.texture.visibility import VisibilityOptions, boxes_in_frustum, frustum_extent

if TYPE_CHECKING:  # fusion imports this module
    from workers.pipeline.texture.surface_texels import SurfaceTexels


@dataclass(frozen=True, eq=False)
class UnitTexels:
    """The texels of a unit's surfaces in flat arrays (N texels, B blocks, S surfaces).

    Attributes:
        surface: `(N,)` intp surface index of each texel (ascending).
        points: `(N, 3)` float64 world texel centres.
        block_start: `(B + 1,)` first texel of each block (and N); blocks never span surfaces.
        block_lo, block_hi: `(B, 3)` bounds of each block's texel centres.
        block_surface: `(B,)` surface index of each block.
        normal, s_axis, t_axis, corner: `(S, 3)` each surface's unit normal, raster axes and
            grid corner.
        size: `(S,)` texel size of each surface, metres.
        worst: `(N,)` float32 copy of the textures' `worst` at each texel (kept up to date by
            `fusion.texture_frame`).
    """

    surface: np.ndarray
    points: np.ndarray
    block_start: np.ndarray
    block_lo: np.ndarray
    block_hi: np.ndarray
    block_surface: np.ndarray
    normal: np.ndarray
    s_axis: np.ndarray
    t_axis: np.ndarray
    corner: np.ndarray
    size: np.ndarray
    worst: np.ndarray

    @classmethod
    def of(cls, surfaces: Sequence[SurfaceTexels], textures: Sequence[SurfaceTexture]) -> UnitTexels:
        """Stack `surfaces` (`fusion.SurfaceTexels`) with their `textures` (same order)."""
        n = [len(s.points) for s in surfaces]
        first = np.r_[0, np.cumsum(n)].astype(np.intp)
        starts = [s.block_start[:-1] + first[k] for k, s in enumerate(surfaces) if n[k]]
        nb = [len(s.block_start) - 1 if n[k] else 0 for k, s in enumerate(surfaces)]
        z3 = np.zeros((0, 3))
        g = [s.grid for s in surfaces]
        return cls(
            surface=np.repeat(np.arange(len(surfaces)), n),
            points=np.concatenate([s.points for s in surfaces]) if surfaces else z3,
            block_start=np.r_[np.concatenate(starts) if starts else np.zeros(0, np.intp), first[-1]],
            block_lo=np.concatenate([s.block_lo for k, s in enumerate(surfaces) if n[k]] or [z3]),
            block_hi=np.concatenate([s.block_hi for k, s in enumerate(surfaces) if n[k]] or [z3]),
            block_surface=np.repeat(np.arange(len(surfaces)), nb),
            normal=np.array([x.normal for x in g], np.float64).reshape(-1, 3),
            s_axis=np.array([x.s_axis for x in g], np.float64).reshape(-1, 3),
            t_axis=np.array([x.t_axis for x in g], np.float64).reshape(-1, 3),
            corner=np.array([x.corner for x in g], np.float64).reshape(-1, 3),
            size=np.array([x.size for x in g], np.float64),
            worst=np.concatenate(
                [t.worst[s.rows, s.cols] for s, t in zip(surfaces, textures, strict=True)]
                or [np.zeros(0, np.float32)]
            ).astype(np.float32),
        )

    def candidates(self, camera: Camera, pose: Pose, options: VisibilityOptions,
                   improve_factor: float) -> np.ndarray:  # fmt: skip
        """Indices `(M,)` (ascending) of the texels in the blocks that may appear in the frame,
        on a surface facing it, and may get a usable, better observation from it (the block's
        best possible local resolution — nearest point, head-on, at the image corner's
        magnification — finer than `max_texel_ratio` texel sizes and than every fused texel of
        the block × `improve_factor`)."""
        if len(self.block_surface) == 0:
            return np.zeros(0, np.intp)
        s = self.block_surface
        front = np.einsum("ij,ij->i", pose.center - self.corner, self.normal) > 0.0
        ok = front[s] & boxes_in_frustum(camera, pose, self.block_lo, self.block_hi, options)
        b = np.flatnonzero(ok)
        if len(b) == 0:
            return np.zeros(0, np.intp)
        a_lo, a_hi, b_lo, b_hi = frustum_extent(camera, 0.0)
        gain = max(camera.fx, camera.fy) * (1.0 + max(a_lo**2, a_hi**2) + max(b_lo**2, b_hi**2))
        near = np.clip(pose.center, self.block_lo[b], self.block_hi[b])
        nearest = np.linalg.norm(near - pose.center, axis=1)
        worst = np.maximum.reduceat(self.worst, self.block_start[:-1])[b]
        limit = np.minimum(options.max_texel_ratio * self.size[s[b]], worst * improve_factor)
        b = b[nearest / gain < limit]
        lengths = self.block_start[b + 1] - self.block_start[b]
        offsets = np.repeat(self.block_start[b] - np.r_[0, np.cumsum(lengths)[:-1]], lengths)
        return np.arange(int(lengths.sum())) + offsets


@dataclass(frozen=True, eq=False)
class FrameObservations:
    """A frame's winning observations `(M,)` before the occlusion test: flat texel index `idx`,
    pixel `uv (M, 2)`, distance (m), cosine of the viewing angle, local resolution (m/px)."""

    idx: np.ndarray
    uv: np.ndarray
    distance: np.ndarray
    cos_view: np.ndarray
    res: np.ndarray


def observe(camera: Camera, pose: Pose, stack: UnitTexels, idx: np.ndarray, options: VisibilityOptions,
            improve_factor: float) -> FrameObservations:  # fmt: skip
    """Project the texels `idx (M,)` of `stack` into the frame, apply the geometric tests of
    `visibility.project_texels` (grazing limit, depth, range, frustum, image margin) and keep
    those whose local resolution (the coarser of the surface axes, `fusion.local_resolution`)
    beats the fused `worst` × `improve_factor` and `max_texel_ratio` texel sizes."""
    R = pose.R_world_from_cam
    # einsum, not BLAS: an (M, 3) × (3, 3) product through BLAS cost 4× the CPU here (threads)
    xc = np.einsum("ij,jk->ik", np.take(stack.points, idx, axis=0) - pose.center, R)
    depth = xc[:, 2]
    dist = np.sqrt(np.einsum("ij,ij->i", xc, xc))
    surf = np.take(stack.surface, idx)
    # texels lie on their surface's plane: (centre - texel) · normal is the camera's height above
    # the plane, one number per surface (no per-texel normal gathered)
    height = np.einsum("ij,ij->i", pose.center - stack.corner, stack.normal)
    cos_view = np.take(height, surf) / np.maximum(dist, 1e-12)
    a_lo, a_hi, b_lo, b_hi = frustum_extent(camera, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = xc[:, 0] / depth
        b = xc[:, 1] / depth
    ok = (cos_view > math.cos(math.radians(options.max_view_angle_deg))) & (depth > options.min_depth_m)
    ok &= (dist < options.max_distance_m) & (a >= a_lo) & (a <= a_hi) & (b >= b_lo) & (b <= b_hi)
    k = np.flatnonzero(ok)
    z, s, ak, bk = depth[k], surf[k], a[k], b[k]
    inv = []
    for axes in (stack.s_axis, stack.t_axis):  # local resolution, pinhole Jacobian
        e = np.dot(axes, R)  # (S, 3) camera frame; gathered per texel column by column
        e0, e1, e2 = (np.take(np.ascontiguousarray(e[:, j]), s) for j in range(3))
        du = camera.fx * (e0 - ak * e2) / z
        dv = camera.fy * (e1 - bk * e2) / z
        inv.append(np.hypot(du, dv))
    res = (1.0 / np.maximum(np.minimum(inv[0], inv[1]), 1e-12)).astype(np.float32)
    win = res < np.take(stack.worst, idx[k]) * np.float32(improve_factor)
    win &= res <= options.max_texel_ratio * np.take(stack.size, s)
    k, res = k[win], res[win]
    uv = camera.pixel_from_normalized(np.stack([a[k], b[k]], axis=1))
    inside = camera.in_image(uv, margin=options.margin_px)
    k, uv, res = k[inside], uv[inside], res[inside]
    return FrameObservations(idx[k], uv, dist[k], cos_view[k], res)

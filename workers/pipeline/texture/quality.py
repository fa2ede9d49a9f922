"""Texture accuracy against a known temperature field (synthetic scenes: tests, demo, bench).

In: a surface's `TexelGrid`, its fused texture `(H, W)` float32 (NaN = not observed), a
ground-truth temperature function of world points (model CRS, metres -> kelvin), and optionally
the frames' true poses and a ray caster to find the texels the frames can see.
Out: per surface and overall: RMSE (all observed texels, near and away from sharp edges of the
field), misregistration (phase correlation of the texture against the truth on the same grid,
texels), coverage (observed share of the visible texels).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.texture.alignment import AlignOptions, align_partial
from workers.pipeline.texture.fusion import local_resolution
from workers.pipeline.texture.texel import TexelGrid
from workers.pipeline.texture.visibility import (
    VisibilityOptions,
    boxes_in_frustum,
    buried_texels,
    facing,
    project_texels,
)

#: world points (N, 3) -> temperature (N,) in kelvin, for one surface
TruthFn = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class EvalOptions:
    """Options of the evaluation.

    Attributes:
        edge_gradient_k: a truth gradient above this (kelvin per texel) marks an edge texel.
        edge_radius: texels within this many texels of an edge texel count as "near edges".
        min_texels_misregistration: smaller surfaces are left out of the misregistration figure.
    """

    edge_gradient_k: float = 0.5
    edge_radius: int = 2
    min_texels_misregistration: int = 400


@dataclass(frozen=True)
class SurfaceErrors:
    """Errors of one surface texture (K, texels); NaN where undefined."""

    polygon_id: str
    texels: int
    visible: int
    observed: int
    observed_visible: int
    sse: float
    sse_edge: float
    n_edge: int
    misregistration: float


def truth_raster(grid: TexelGrid, truth: TruthFn, supersample: int = 3) -> np.ndarray:
    """Ground-truth texture `(H, W)` float32 of a grid (NaN outside the polygon): the mean of the
    field over each texel's square, from `supersample × supersample` point samples (a texel
    stands for its area; 1 = the value at the texel centre)."""
    out = np.full(grid.shape, np.nan, np.float32)
    r, c = grid.masked_indices()
    if len(r) == 0:
        return out
    offs = (np.arange(supersample) + 0.5) / supersample
    acc = np.zeros(len(r))
    for dy in offs:
        for dx in offs:
            acc += truth(grid.points_at(np.stack([c + dx, r + dy], axis=1)))
    out[r, c] = acc / supersample**2
    return out


def visible_texels(
    grid: TexelGrid,
    camera: Camera,
    poses: Sequence[Pose],
    raycaster: RayCaster | None,
    options: VisibilityOptions = VisibilityOptions(),
    ground_z: float | None = None,
) -> np.ndarray:
    """`(H, W)` bool: texels (inside the polygon) that at least one of `poses` sees — inside the
    frame with the margin, in front, facing within the viewing-angle limit, at a local resolution
    within `max_texel_ratio` texel sizes, and unoccluded along the ray to the projection centre
    (point-wise test); never texels on a shared wall (inside
    another solid) or below `ground_z` (a synthetic scene's ground plane)."""
    rows, cols = grid.masked_indices()
    pts = grid.centres(rows, cols)
    seen = np.zeros(len(pts), dtype=bool)
    if len(pts) == 0:
        return np.zeros(grid.shape, dtype=bool)
    if raycaster is not None:
        seen |= buried_texels(raycaster, pts, grid.normal)
    if ground_z is not None:
        seen |= pts[:, 2] < ground_z
    never = seen.copy()
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    for pose in poses:
        if not boxes_in_frustum(camera, pose, lo[None], hi[None], options)[0]:
            continue
        if not facing(grid.normal, grid.corner, pose.center):
            continue
        todo = ~seen
        proj = project_texels(camera, pose, pts[todo], grid.normal, options)
        idx = np.nonzero(todo)[0][proj.ok]
        if len(idx) == 0:
            continue
        res_s, res_t = local_resolution(camera, pose, pts[idx], grid.s_axis, grid.t_axis)
        idx = idx[np.maximum(res_s, res_t) <= options.max_texel_ratio * grid.size]
        if len(idx) == 0:
            continue
        if raycaster is not None:
            idx = idx[raycaster.visible(pts[idx], pose.center, options.occlusion_tolerance_m)]
        seen[idx] = True
    out = np.zeros(grid.shape, dtype=bool)
    out[rows, cols] = seen & ~never
    return out


def edge_mask(truth: np.ndarray, options: EvalOptions) -> np.ndarray:
    """`(H, W)` bool: texels within `edge_radius` of a sharp gradient of the truth raster."""
    t = np.where(np.isfinite(truth), truth, np.nanmean(truth) if np.isfinite(truth).any() else 0.0)
    gx = np.abs(np.diff(t, axis=1, prepend=t[:, :1]))
    gy = np.abs(np.diff(t, axis=0, prepend=t[:1]))
    strong = (np.maximum(gx, gy) > options.edge_gradient_k).astype(np.uint8)
    k = 2 * options.edge_radius + 2
    return cv2.dilate(strong, np.ones((k, k), np.uint8)).astype(bool)


def surface_errors(
    grid: TexelGrid,
    value: np.ndarray,
    truth: np.ndarray,
    visible: np.ndarray | None = None,
    options: EvalOptions = EvalOptions(),
) -> SurfaceErrors:
    """Errors of one fused texture `value (H, W)` against `truth (H, W)` (both NaN-masked)."""
    inside = grid.mask
    obs = inside & np.isfinite(value)
    vis = inside if visible is None else (visible & inside)
    err = (value - truth)[obs].astype(np.float64)
    edges = edge_mask(truth, options)
    err_edge = (value - truth)[obs & edges].astype(np.float64)
    mis = float("nan")
    if obs.sum() >= options.min_texels_misregistration:
        got = align_partial(
            np.where(inside, truth, np.nan).astype(np.float32),
            np.where(obs, value, np.nan).astype(np.float32),
            AlignOptions(max_shift_texels=3.0, refine_iterations=5),
        )
        if got is not None:
            mis = math.hypot(got[0], got[1])
    return SurfaceErrors(
        polygon_id=grid.polygon_id,
        texels=int(inside.sum()),
        visible=int(vis.sum()),
        observed=int(obs.sum()),
        observed_visible=int((obs & vis).sum()),
        sse=float(np.sum(err**2)),
        sse_edge=float(np.sum(err_edge**2)),
        n_edge=len(err_edge),
        misregistration=mis,
    )


def summarize(errors: Sequence[SurfaceErrors]) -> dict[str, float]:
    """Overall figures: `rmse_k`, `rmse_edges_k`, `rmse_away_k`, `misregistration_median_texel`,
    `coverage` (observed share of visible texels), counts."""
    n = sum(e.observed for e in errors)
    n_edge = sum(e.n_edge for e in errors)
    sse = sum(e.sse for e in errors)
    sse_edge = sum(e.sse_edge for e in errors)
    vis = sum(e.visible for e in errors)
    mis = [e.misregistration for e in errors if math.isfinite(e.misregistration)]
    nan = float("nan")
    return {
        "rmse_k": math.sqrt(sse / n) if n else nan,
        "rmse_edges_k": math.sqrt(sse_edge / n_edge) if n_edge else nan,
        "rmse_away_k": math.sqrt((sse - sse_edge) / (n - n_edge)) if n > n_edge else nan,
        "misregistration_median_texel": float(np.median(mis)) if mis else nan,
        "misregistration_surfaces": len(mis),
        "coverage": sum(e.observed_visible for e in errors) / vis if vis else nan,
        "texels_observed": n,
        "texels_visible": vis,
        "surfaces": len(errors),
    }

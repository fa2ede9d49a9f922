"""Facades across polygons: coplanar, adjacent surfaces of one building analysed as one texture.

LoD2 models split a wall into several small coplanar polygons (NRW: often one per storey part or
per window axis), so that one polygon often holds a single window, a leak's surroundings lie on
its neighbour, and the polygon's outline runs through the middle of the facade. A **facade** is
a set of polygons of one building and one surface class that are coplanar (normals and texel
axes within `facade_angle_deg`, each one's texels within `facade_plane_m` of the other's plane),
have the same texel size and are adjacent (texel centres of the two within 1.5 texels: they share
an edge). `analyse_building` maps the members' texels onto one raster in the first member's
plane axes (each member shifted by a whole number of texels: its texels move by at most half a
texel), closes the seams of one texel between them (a seam texel copies its nearest member
texel), runs `analyse_surface` on that raster and hands each member its part:

- anomalies whose centre lies on the member's texels (outlines may reach onto a neighbour: they
  stay on the common plane), ids `<polygon id>-<kind>-<n>` numbered per member;
- the label raster at the member's texels;
- `typical` and `spread` of the facade; `hot_share`, `window_share` and `heat_loss_index` over
  the member's own texels (the heat-loss index with the excess over the facade's typical value,
  the linear bridges not removed).

A polygon without coplanar neighbours is analysed alone, exactly as `analyse_surface` does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from workers.pipeline.anomalies import figures
from workers.pipeline.anomalies.analysis import LEAK, WINDOW, SurfaceAnalysis, analyse_surface, with_ids
from workers.pipeline.anomalies.options import AnomalyOptions
from workers.pipeline.anomalies.typical import edge_band
from workers.pipeline.texture.fused import SurfaceTexture
from workers.pipeline.texture.texel import TexelGrid

_TEXTURE_FIELDS = ("value", "resolution", "view_angle", "frame", "count", "worst")
_OBS_FIELDS = ("obs_value", "obs_res", "obs_angle", "obs_frame")


def _coplanar(a: TexelGrid, b: TexelGrid, ca: np.ndarray, cb: np.ndarray, o: AnomalyOptions) -> bool:
    """Same class, texel size, plane (within `facade_plane_m`) and axes (within
    `facade_angle_deg`); `ca`, `cb` `(N, 3)` texel centres of each."""
    if a.building_id != b.building_id or a.surface_class != b.surface_class:
        return False
    if abs(a.size - b.size) > 1e-6 * max(a.size, b.size):
        return False
    cos = math.cos(math.radians(o.facade_angle_deg))
    if min(a.normal @ b.normal, a.s_axis @ b.s_axis, a.t_axis @ b.t_axis) < cos:
        return False
    return bool(
        np.max(np.abs((cb - a.plane_origin) @ a.normal)) <= o.facade_plane_m
        and np.max(np.abs((ca - b.plane_origin) @ b.normal)) <= o.facade_plane_m
    )


def facade_groups(grids: Sequence[TexelGrid], options: AnomalyOptions = AnomalyOptions()) -> list[list[int]]:
    """Indices of `grids` grouped into facades (module docstring), each group sorted, groups in
    the order of their first member; a polygon without coplanar neighbour is a group of one."""
    n = len(grids)
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    rims, boxes = [], []
    for g in grids:  # texel centres on the rim of each mask: where a neighbour can touch
        rows, cols = np.nonzero(edge_band(g.mask, 1))
        c = g.centres(rows, cols)
        rims.append(c)
        boxes.append((c.min(axis=0), c.max(axis=0)) if len(c) else None)
    for i in range(n):
        for j in range(i + 1, n):
            a, b = grids[i], grids[j]
            if boxes[i] is None or boxes[j] is None or find(i) == find(j):
                continue
            reach = 1.5 * a.size
            if np.any(boxes[i][0] - reach > boxes[j][1]) or np.any(boxes[j][0] - reach > boxes[i][1]):
                continue
            if not _coplanar(a, b, rims[i], rims[j], options):
                continue
            d, _ = cKDTree(rims[i]).query(rims[j], k=1, distance_upper_bound=reach)
            if np.isfinite(d).any():
                parent[find(i)] = find(j)
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(i)
    return sorted(groups.values(), key=lambda m: m[0])


def merge_facade(
    grids: Sequence[TexelGrid], textures: Sequence[SurfaceTexture]
) -> tuple[TexelGrid, SurfaceTexture, np.ndarray, list[tuple[int, int]]]:
    """One raster for the coplanar `grids` (a facade): its grid (the first member's id, plane and
    axes), its texture, `owner (H, W)` int (member index of each texel, −1 none) and each
    member's `(row, col)` offset in it (module docstring)."""
    ref = grids[0]
    offs = []
    for g in grids:
        xy = ref.raster_xy(g.centres(np.array([0]), np.array([0])))[0]
        offs.append((round(float(xy[1]) - 0.5), round(float(xy[0]) - 0.5)))
    r0 = min(r for r, _ in offs)
    c0 = min(c for _, c in offs)
    H = max(r + g.shape[0] for (r, _), g in zip(offs, grids, strict=True)) - r0
    W = max(c + g.shape[1] for (_, c), g in zip(offs, grids, strict=True)) - c0
    offs = [(r - r0, c - c0) for r, c in offs]
    tex = SurfaceTexture.empty((H, W), textures[0].options)
    owner = np.full((H, W), -1, np.int32)
    for k, (g, t, (r, c)) in enumerate(zip(grids, textures, offs, strict=True)):
        sub = (slice(r, r + g.shape[0]), slice(c, c + g.shape[1]))
        seen = np.isfinite(t.value)
        free = owner[sub] < 0
        free |= ~np.isfinite(tex.value[sub]) & seen  # an observed texel wins over an unobserved one
        put = g.mask & free
        owner[sub][put] = k
        for name in _TEXTURE_FIELDS:
            getattr(tex, name)[sub][put] = getattr(t, name)[put]
        for name in _OBS_FIELDS:
            getattr(tex, name)[(slice(None), *sub)][:, put] = getattr(t, name)[:, put]
    mask = owner >= 0
    seam = ndimage.binary_closing(mask, np.ones((3, 3), bool), border_value=0) & ~mask
    if seam.any():  # seams of a texel between members: copies of the nearest member texel
        _, (ii, jj) = ndimage.distance_transform_edt(~mask, return_indices=True)
        src = (ii[seam], jj[seam])
        for name in _TEXTURE_FIELDS:
            a = getattr(tex, name)
            a[seam] = a[src]
        for name in _OBS_FIELDS:
            a = getattr(tex, name)
            a[:, seam] = a[:, src[0], src[1]]
        mask = mask | seam
    size = ref.size
    s_min, t_max = ref.s_min + (c0 * size), ref.t_max - (r0 * size)
    grid = replace(
        ref,
        mask=mask,
        s_min=float(s_min),
        t_max=float(t_max),
        corner=ref.plane_origin + s_min * ref.s_axis + t_max * ref.t_axis,
    )
    return grid, tex, owner, offs


def _member(
    g: TexelGrid,
    t: SurfaceTexture,
    whole: SurfaceAnalysis,
    part: tuple[slice, slice],
    found: list,
    o: AnomalyOptions,
) -> SurfaceAnalysis:
    """A member's share of the facade's analysis (module docstring)."""
    observed = g.mask & np.isfinite(t.value)
    labels = np.where(observed, whole.labels[part], 0).astype(np.uint8)
    excess = np.where(observed, t.value - np.float32(whole.typical), np.nan)
    windows = labels == WINDOW
    nan = float("nan")
    analysed = math.isfinite(whole.typical) and observed.any()  # else every figure is NaN
    return SurfaceAnalysis(
        polygon_id=g.polygon_id,
        building_id=g.building_id,
        typical=whole.typical,
        spread=whole.spread,
        hot_share=figures.hot_share(excess, observed, windows, o.hot_delta_k) if analysed else nan,
        window_share=figures.window_share(observed, windows) if analysed else nan,
        heat_loss_index=figures.heat_loss_index(excess, observed, labels == LEAK) if analysed else nan,
        anomalies=with_ids(g, [(a.kind, replace(a, polygon_id=g.polygon_id)) for a in found]),
        labels=labels,
    )


def analyse_building(
    grids: Sequence[TexelGrid], textures: Sequence[SurfaceTexture], options: AnomalyOptions = AnomalyOptions()
) -> list[SurfaceAnalysis]:
    """`analyse_surface` over the facades of one building unit (module docstring): one
    `SurfaceAnalysis` per input surface, in the input order (`grids[k]`, `textures[k]`; every
    grid of one building, model CRS)."""
    if len(grids) != len(textures):
        raise ValueError(f"{len(grids)} grids but {len(textures)} textures")
    out: list[SurfaceAnalysis | None] = [None] * len(grids)
    groups = facade_groups(grids, options) if options.facade_grouping else [[k] for k in range(len(grids))]
    for members in groups:
        if len(members) == 1:
            k = members[0]
            out[k] = analyse_surface(grids[k], textures[k], options)
            continue
        gs = [grids[k] for k in members]
        grid, tex, owner, offs = merge_facade(gs, [textures[k] for k in members])
        whole = analyse_surface(grid, tex, options)
        # each anomaly to the member whose texel lies under its centre (or nearest to it)
        _, (ii, jj) = ndimage.distance_transform_edt(owner < 0, return_indices=True)
        found: list[list] = [[] for _ in members]
        for a in whole.anomalies:
            x, y = grid.raster_xy(a.centre[None])[0]
            i = min(max(math.floor(y), 0), owner.shape[0] - 1)
            j = min(max(math.floor(x), 0), owner.shape[1] - 1)
            found[int(owner[ii[i, j], jj[i, j]])].append(a)
        for m, (k, g, (r, c)) in enumerate(zip(members, gs, offs, strict=True)):
            part = (slice(r, r + g.shape[0]), slice(c, c + g.shape[1]))
            out[k] = _member(g, textures[k], whole, part, found[m], options)
    return [a for a in out if a is not None]

"""The per-texel occlusion and clean-pixel test of one frame, by ray casting through the scene.

In: a `RayCaster` over a unit's scene (its building and every building that can occlude it;
mesh in a local frame, `SceneMesh.origin`), the camera, a frame's pose (world = model CRS,
metres), and per surface the pixel positions `uv (N, 2)` of its texel samples (pixel centres at
integers), their distances to the projection centre `(N,)` (metres) and their plane group.
Out: per surface `(N,)` bool: the pixels bilinear sampling reads, grown by the blur margin (the
PSF radius), see the texel's own plane at the texel's distance over their whole area, corners
included (`OcclusionScene.visible`; the footprint as `VisibilityOptions.blur_margin_px` defines it).

Cost: one coarse cast of every `buffer_step_px`-th pixel (only around the samples), then full
resolution pixel rays and pixel-corner rays only near silhouettes. Every surface of the frame
goes through each step at once (one concatenated test, group per sample); the cast buffers are
kept per scene and only the entries cast are reset, so a frame's cost follows the rays it casts,
not the image size.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster, SceneMesh
from workers.pipeline.texture.footprint import FootprintEdges
from workers.pipeline.texture.visibility_options import VisibilityOptions


@functools.lru_cache(maxsize=4)
def pixel_rays(camera: Camera) -> np.ndarray:
    """Unit rays `(H, W, 3)` float32 through every pixel centre, camera frame (distortion removed).

    Cached per camera (read-only array); a frame's world rays are `rays @ R_world_from_camᵀ`.
    """
    uu, vv = np.meshgrid(
        np.arange(camera.width, dtype=np.float64), np.arange(camera.height, dtype=np.float64)
    )
    rays = camera.bearing(np.stack([uu.ravel(), vv.ravel()], axis=1))
    out = rays.reshape(camera.height, camera.width, 3).astype(np.float32)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=4)
def corner_rays(camera: Camera) -> np.ndarray:
    """Unit rays `(H + 1, W + 1, 3)` float32 through every pixel corner (pixel `(u - ½, v - ½)`
    at `[v, u]`), camera frame; cached per camera (read-only)."""
    uu, vv = np.meshgrid(np.arange(camera.width + 1.0) - 0.5, np.arange(camera.height + 1.0) - 0.5)
    rays = camera.bearing(np.stack([uu.ravel(), vv.ravel()], axis=1))
    out = rays.reshape(camera.height + 1, camera.width + 1, 3).astype(np.float32)
    out.flags.writeable = False
    return out


@dataclass(frozen=True, eq=False)
class HitBuffer:
    """What the pixels bilinear sampling reads see in one frame: first-hit distance and polygon,
    stored flat (pixel `(v, u)` at `v · width + u`).

    Attributes:
        width, height: size of the cast grid (the image's divided by `step`, rounded up).
        step: pixel step of the cast grid (grid element `(i, j)` is pixel `(i·step, j·step)`).
        t: `(H·W,)` float32 distance from the projection centre to the first hit (inf: nothing,
            or a pixel that was not cast).
        polygon: `(H·W,)` int32 index into the scene's `polygon_ids` (-1: nothing / not cast).
    """

    width: int
    height: int
    step: int
    t: np.ndarray
    polygon: np.ndarray


def _top_left(uv: np.ndarray, H: int, W: int, margin: int = 0) -> np.ndarray:
    """Flat index `(N,)` of the top-left pixel of the 2x2 bilinear neighbourhood of `uv (N, 2)`
    (clamped so that the neighbourhood, grown by `margin` pixels, lies inside the image)."""
    c0 = np.clip(np.floor(uv[:, 0]).astype(np.intp), margin, max(W - 2 - margin, margin))
    r0 = np.clip(np.floor(uv[:, 1]).astype(np.intp), margin, max(H - 2 - margin, margin))
    return r0 * W + c0


def _offsets(W: int, margin: int) -> np.ndarray:
    """Flat offsets of the `(2 + 2·margin)²` pixels around a top-left pixel."""
    k = np.arange(-margin, 2 + margin)
    return (k[:, None] * W + k[None, :]).ravel()


def consistent_samples(
    buffer: HitBuffer,
    uv: np.ndarray,
    distance: np.ndarray,
    group: int | np.ndarray,
    polygon_group: np.ndarray,
    options: VisibilityOptions,
    margin: int,
    require: str = "all",
) -> np.ndarray:
    """`(N,)` bool: the cast-grid elements around `uv (N, 2)` — the 2x2 around the sample grown by
    `margin` elements — all (`require="all"`; `"any"`: at least one) see the texel's own plane:
    their first hit is a polygon of the texel's plane `group` (one for all samples, or `(N,)`; see
    `plane_groups`) at the texel's `distance (N,)` within `depth_tolerance_m +
    depth_tolerance_rel · distance`. `polygon_group (P + 1,)` maps polygon index -> plane group,
    its last entry (index -1) is -1."""
    W = buffer.width
    lin = _top_left(uv / buffer.step, buffer.height, W, margin)
    return _own_plane(buffer.t, buffer.polygon, lin, _offsets(W, margin), distance, group, polygon_group,
                      options, every=require == "all")  # fmt: skip


def _own_plane(
    t: np.ndarray,
    polygon: np.ndarray,
    lin: np.ndarray,
    offsets: np.ndarray,
    distance: np.ndarray,
    group: int | np.ndarray,
    polygon_group: np.ndarray,
    options: VisibilityOptions,
    every: bool = True,
) -> np.ndarray:
    """`(N,)` bool: the cast rays at flat indices `lin (N,) + offsets (K,)` (first-hit distance `t`,
    polygon index `polygon`, flat) all (`every`; else at least one) hit the plane `group` (scalar
    or `(N,)`) at `distance (N,)` within the depth tolerance. One pass per offset over `(N,)`
    arrays (cache-resident; an `(N, K)` gather at once measured slower)."""
    d = np.asarray(distance, dtype=np.float32)
    tol = np.float32(options.depth_tolerance_m) + np.float32(options.depth_tolerance_rel) * d
    lo, hi = d - tol, d + tol
    ok = np.full(len(lin), every, dtype=bool)
    for off in offsets:
        j = lin + off
        tj = t[j]
        own = polygon_group[polygon[j]] == group
        own &= tj >= lo
        own &= tj <= hi
        if every:
            ok &= own
        else:
            ok |= own
    return ok


def plane_groups(mesh: SceneMesh, options: VisibilityOptions) -> np.ndarray:
    """`(P,)` int: a plane id per polygon of `mesh`; polygons of one building lying in one plane
    (normals within `coplanar_deg`, planes within `coplanar_m`) share it."""
    P = mesh.n_polygons
    group = np.arange(P)
    if P == 0 or len(mesh.triangles) == 0:
        return group
    # a vertex of each polygon (local frame) for the plane offset
    first = np.full(P, -1, np.int64)
    first[mesh.triangle_polygon[::-1]] = mesh.triangles[::-1, 0]
    has = first >= 0
    offset = np.zeros(P)
    offset[has] = np.einsum(
        "ij,ij->i", mesh.polygon_normals[has], mesh.vertices[first[has]].astype(np.float64)
    )
    cos_tol = math.cos(math.radians(options.coplanar_deg))
    by_building: dict[str, list[int]] = {}
    for i, b in enumerate(mesh.polygon_building):
        if has[i]:
            by_building.setdefault(b, []).append(i)
    for ids in by_building.values():
        idx = np.array(ids)
        n = mesh.polygon_normals[idx]
        same = (n @ n.T > cos_tol) & (
            np.abs(offset[idx][:, None] - offset[idx][None, :]) < options.coplanar_m
        )
        for a in range(len(idx)):  # smallest index of the connected set (planes are few per building)
            group[idx[a]] = group[idx[np.nonzero(same[a])[0]]].min()
    return group


#: `_CastGrid.needed` sorts up to this many window elements, marks and scans more
_SORT_MAX = 512


class _CastGrid:
    """A grid of camera-frame rays `(H, W, 3)` with flat first-hit buffers kept between frames:
    a cast fills the entries asked for and first resets the ones the previous cast filled."""

    def __init__(self, rays: np.ndarray) -> None:
        self.rays = rays
        self.height, self.width = rays.shape[:2]
        n = self.height * self.width
        self.t = np.full(n, np.inf, np.float32)
        self.polygon = np.full(n, -1, np.int32)
        self._filled = np.zeros(0, np.intp)
        self._mark = np.zeros(n, bool)  # all False between calls of `needed`

    def needed(self, lin: np.ndarray, size: int, anchor: int) -> np.ndarray:
        """Sorted flat indices of the pixels in the `size × size` windows whose element `(anchor,
        anchor)` is at `lin (N,)` (the pixels to cast): listed when the windows are few (sorted
        by `np.unique` for a handful, else marked in a kept flag array that is scanned and
        cleared: a third of the sort's cost from a few hundred elements on), else the window
        corners marked and grown by a dilation (no marking of every window element for many)."""
        n = len(lin) * size * size
        if n * 8 < self.height * self.width:  # few windows: list them
            k = np.arange(size) - anchor
            every = lin[:, None] + (k[:, None] * self.width + k[None, :]).ravel()[None, :]
            if n <= _SORT_MAX:
                return np.unique(every)
            mark = self._mark
            mark[every.ravel()] = True
            pix = np.flatnonzero(mark)
            mark[pix] = False
            return pix
        mark = np.zeros((self.height, self.width), np.uint8)
        mark.ravel()[lin] = 1
        if size > 1:
            k = np.ones((size, size), np.uint8)
            mark = cv2.dilate(mark, k, anchor=(size - 1 - anchor, size - 1 - anchor))
        return np.flatnonzero(mark)


class OcclusionScene:
    """Everything the per-texel occlusion test needs for one unit: the ray caster over the
    scene mesh (building and occluders), the camera's pixel rays, and the scene index and plane
    group of each polygon. Rays are built in float32 in the mesh's local frame (no float64
    round trip). Not picklable; build one per unit."""

    def __init__(self, raycaster: RayCaster, camera: Camera, options: VisibilityOptions,
                 buildings: Sequence[Building] | None = None) -> None:  # fmt: skip
        """`buildings`: those the ray caster's mesh was built from (`raycast.build_scene_mesh`,
        same order); their polygons' rings are the outlines of the exact edge test
        (`VisibilityOptions.boundary_edges`), which is off without them."""
        mesh = raycaster.mesh
        self.mesh = mesh
        self._raycaster = raycaster
        self.step = max(1, options.buffer_step_px)
        full = pixel_rays(camera)
        self._grids = {1: _CastGrid(full)}
        if self.step > 1:
            self._grids[self.step] = _CastGrid(np.ascontiguousarray(full[:: self.step, :: self.step]))
        self.options = options
        self._corners = _CastGrid(corner_rays(camera)) if options.pixel_area else None
        self.polygon_index = mesh.polygon_index()
        groups = plane_groups(mesh, options) if options.coplanar_clean else np.arange(mesh.n_polygons)
        self.polygon_group = np.append(groups, -1).astype(np.intp)
        self._edges: FootprintEdges | None = None
        if options.boundary_edges and buildings is not None:
            self._edges = FootprintEdges(buildings, mesh, camera, groups, options.occlusion_tolerance_m,
                                         options.coplanar_clean)  # fmt: skip

    def buffer(self, pose: Pose, uv: np.ndarray, step: int = 1, margin: int = 0) -> HitBuffer:
        """Cast the grid of every `step`-th pixel around `uv (N, 2)` (the 2x2 grid elements around
        each sample grown by `margin`) from the projection centre of `pose` through the scene.
        The buffer's arrays are the scene's own: valid until the next cast at this `step`."""
        grid = self._grids[step]
        H, W = grid.height, grid.width
        pix = grid.needed(_top_left(uv / step, H, W, margin), 2 + 2 * margin, margin)
        self._cast(pose, grid, pix)
        return HitBuffer(width=W, height=H, step=step, t=grid.t, polygon=grid.polygon)

    def _cast(self, pose: Pose, grid: _CastGrid, pix: np.ndarray) -> None:
        """Cast the rays of `grid` at flat indices `pix` from the projection centre of `pose` into
        its buffers (the previous cast's entries reset to inf / -1 first)."""
        grid.t[grid._filled] = np.inf
        grid.polygon[grid._filled] = -1
        grid._filled = pix
        if len(pix):
            rays = np.empty((len(pix), 6), np.float32)
            rays[:, :3] = (pose.center - self.mesh.origin).astype(np.float32)
            R = pose.R_world_from_cam.astype(np.float32)  # einsum, not BLAS (see frame_pass.observe)
            rays[:, 3:] = np.einsum("ij,kj->ik", np.take(grid.rays.reshape(-1, 3), pix, axis=0), R)
            grid.t[pix], grid.polygon[pix] = self._raycaster.cast_local(rays)

    def _corner_index(self, uv: np.ndarray, margin: int) -> tuple[np.ndarray, np.ndarray]:
        """Flat index `(N,)` of the top-left corner of each sample's footprint (the 2x2 bilinear
        pixels grown by `margin`) and the flat offsets of its `(3 + 2·margin)²` corners."""
        assert self._corners is not None
        H1, W1 = self._corners.height, self._corners.width
        n = 3 + 2 * margin
        c0 = np.clip(np.floor(uv[:, 0]).astype(np.intp) - margin, 0, max(W1 - n, 0))
        r0 = np.clip(np.floor(uv[:, 1]).astype(np.intp) - margin, 0, max(H1 - n, 0))
        k = np.arange(n)
        return r0 * W1 + c0, (k[:, None] * W1 + k[None, :]).ravel()

    def pure_footprint(self, pose: Pose, uv: np.ndarray, distance: np.ndarray,
                       group: int | np.ndarray, margin: int) -> np.ndarray:  # fmt: skip
        """`(N,)` bool: rays through every corner of the footprint pixels of the samples at
        `uv (N, 2)` (the 2x2 bilinear pixels grown by `margin`) see the texel's own plane
        `group` at its `distance (N,)` (all True without `pixel_area`)."""
        if self._corners is None or len(uv) == 0:
            return np.ones(len(uv), bool)
        lin, offs = self._corner_index(uv, margin)
        self._cast(pose, self._corners, self._corners.needed(lin, 3 + 2 * margin, 0))
        g = self._corners
        return _own_plane(g.t, g.polygon, lin, offs, distance, group, self.polygon_group, self.options)

    def visible(self, pose: Pose, samples: Sequence[tuple[np.ndarray, np.ndarray, int]]) -> list[np.ndarray]:
        """Occlusion and silhouette test of a frame's texel samples, per surface.

        Args:
            samples: per surface `(uv (N, 2), distance (N,), plane group)`.

        Returns per surface `(N,)` bool: the pixels bilinear sampling reads and `blur_margin_px`
        around them see the texel's own plane. With `buffer_step_px > 1` a coarse grid decides
        first: samples whose coarse neighbourhood (2x2 grown by one element) is all own plane
        pass, those whose coarse 2x2 shows no own plane at all fail, and those in between (near
        a silhouette) are tested at full resolution. All surfaces are tested together.
        """
        if not samples:
            return []
        uv = np.concatenate([s[0] for s in samples])
        dist = np.concatenate([s[1] for s in samples])
        group = np.repeat(np.array([s[2] for s in samples], np.intp), [len(s[0]) for s in samples])
        ok = self.visible_flat(pose, uv, dist, group)
        return np.split(ok, np.cumsum([len(s[0]) for s in samples])[:-1])

    def _coarse_all(self, buf: HitBuffer, uv: np.ndarray, dist: np.ndarray, group: np.ndarray) -> np.ndarray:
        """`(N,)` bool: the coarse 2x2 around each sample, grown by one element, all see its own
        plane (`consistent_samples` with margin 0, then 1, at once): from the window minimum and
        maximum of the plane group and the hit distance (`cv2.erode` / `cv2.dilate` of the cast
        grid), four gathers per sample and window instead of one per window element."""
        H, W = buf.height, buf.width
        g_img = self.polygon_group[buf.polygon].astype(np.float32).reshape(H, W)  # exact below 2**24
        t_img = buf.t.reshape(H, W)
        d = np.asarray(dist, dtype=np.float32)
        tol = np.float32(self.options.depth_tolerance_m) + np.float32(self.options.depth_tolerance_rel) * d
        g = np.asarray(group, dtype=np.float32)
        ok = np.ones(len(uv), bool)
        for margin in (0, 1):
            k = np.ones((2 + 2 * margin,) * 2, np.uint8)
            lin = _top_left(uv / buf.step, H, W, margin)
            for img, keep in ((g_img, lambda x: x == g), (t_img, lambda x: x <= d + tol)):
                hi = cv2.dilate(img, k, anchor=(margin, margin), borderType=cv2.BORDER_REPLICATE).ravel()
                ok &= keep(hi[lin])
            for img, keep in ((g_img, lambda x: x == g), (t_img, lambda x: x >= d - tol)):
                lo = cv2.erode(img, k, anchor=(margin, margin), borderType=cv2.BORDER_REPLICATE).ravel()
                ok &= keep(lo[lin])
        return ok

    def visible_flat(self, pose: Pose, uv: np.ndarray, dist: np.ndarray, group: np.ndarray) -> np.ndarray:
        """`visible` on the samples of all surfaces at once: `uv (N, 2)` pixels, `dist (N,)`
        metres to the projection centre, `group (N,)` each sample's plane group -> `(N,)` bool.
        The samples the rays pass then go through the exact edge test (`boundary_edges`)."""
        ok = self._rays_clean(pose, uv, dist, group)
        if self._edges is not None and ok.any():
            k = np.flatnonzero(ok)
            ok[k] = ~self._edges.crossed(pose, uv[k], group[k], self.options.blur_margin_px)
        return ok

    def _rays_clean(self, pose: Pose, uv: np.ndarray, dist: np.ndarray, group: np.ndarray) -> np.ndarray:
        """The ray half of `visible_flat`: `(N,)` bool, the cast rays around each sample see its
        own plane at its distance (coarse grid, then full resolution and pixel corners near a
        silhouette)."""
        o, pg = self.options, self.polygon_group
        m = o.blur_margin_px
        if self.step == 1:
            buf = self.buffer(pose, uv, 1, m)
            ok = consistent_samples(buf, uv, dist, group, pg, o, m)
            ok[ok] = self.pure_footprint(pose, uv[ok], dist[ok], group[ok], m)
            return ok
        coarse = self.buffer(pose, uv, self.step, 1)
        ok = self._coarse_all(coarse, uv, dist, group)
        rest = np.flatnonzero(~ok)
        some = np.zeros(len(uv), bool)
        some[rest] = consistent_samples(coarse, uv[rest], dist[rest], group[rest], pg, o, 0, require="any")
        near = np.flatnonzero(some & ~ok)
        if len(near):
            fine = self.buffer(pose, uv[near], 1, m)
            sub = consistent_samples(fine, uv[near], dist[near], group[near], pg, o, m)
            keep = near[sub]
            sub[sub] = self.pure_footprint(pose, uv[keep], dist[keep], group[keep], m)
            ok[near] = sub
        return ok

"""Visibility of buildings and texels in a frame.

In: a `Camera`, a `Pose` (world = model CRS, metres), axis-aligned boxes or texel centres
`(N, 3)` with their surface normal, and a `RayCaster` over the scene (the building and every
building that can occlude it). Out: cheap per-box frustum decisions, and per texel the pixel
position `(N, 2)` (pixel centres at integers), the depth and a visibility mask.

A texel is visible when it projects inside the frame (with a margin), lies in front of the
camera, its surface faces the camera within a maximum viewing angle, and the pixels bilinear
sampling reads (plus a blur margin) all see the texel's own plane at the texel's distance: the
occlusion test by ray casting through the whole scene, which also keeps samples from mixing the
surface with the sky or other surfaces at silhouettes (`OcclusionScene`). Texels on a wall
shared with a touching building are never visible (`buried_texels`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster, SceneMesh


@dataclass(frozen=True)
class VisibilityOptions:
    """Options of the visibility stage.

    Attributes:
        margin_px: texels projecting closer than this to the frame border are not used.
        min_depth_m: texels closer to the camera than this (along the optical axis) are not used.
        max_distance_m: texels farther than this from the projection centre are not used.
        max_view_angle_deg: largest angle between the surface normal and the ray to the camera
            (the grazing limit). Oblique observations lose out to better ones in the fusion
            (ranked by local resolution, which grows as 1/cos of the angle); a surface seen only
            obliquely (a flat roof from the street) still gets a texture, its mean viewing angle
            in the statistics tells the user (real emissivity falls beyond ~60°).
        max_texel_ratio: an observation whose local resolution (metres on the surface per pixel)
            exceeds this many texel sizes is not used: it resolves nothing at the texel scale
            (inf: no limit).
        occlusion_tolerance_m: rays stop this far short of the texel (its own surface); used by
            `unoccluded` (point-wise test).
        depth_tolerance_m, depth_tolerance_rel: a pixel read for a texel belongs to the texel's
            surface when it sees the texel's plane (its polygon or a coplanar polygon of the same
            building) at the texel's distance within `depth_tolerance_m + depth_tolerance_rel ·
            distance`.
        blur_margin_px: that must also hold for the pixels this far around the 2x2 pixels that
            bilinear sampling reads: the optics blur a silhouette (sky, roof edge, occluder) into
            its neighbours.
        buffer_step_px: the occlusion test casts every `buffer_step_px`-th pixel in both
            directions (3: a ninth of the rays); a texel's test then reads the 2x2 cast pixels
            around it, and near a silhouette every pixel of its footprint (`visible`). 3 against
            2: the same textures on the NRW bench drive and flight, a close-range drive past
            Berlin facades 41 against 33 frames/s.
        pixel_area: near a silhouette, the footprint's pixels must see the texel's plane over
            their whole area, tested by rays through their corners as well as their centres (a
            pixel half on a neighbour is a mixed pixel even when its centre is not).
        coplanar_deg, coplanar_m: polygons of one building whose normals differ by less than
            `coplanar_deg` and whose planes are less than `coplanar_m` apart form one plane (a
            facade split into several polygons).
    """

    margin_px: float = 2.0
    min_depth_m: float = 0.5
    max_distance_m: float = 800.0
    max_view_angle_deg: float = 80.0
    max_texel_ratio: float = 3.0
    occlusion_tolerance_m: float = 0.05
    depth_tolerance_m: float = 0.3
    depth_tolerance_rel: float = 0.02
    blur_margin_px: int = 1
    buffer_step_px: int = 3
    pixel_area: bool = True
    coplanar_deg: float = 1.0
    coplanar_m: float = 0.05


@functools.lru_cache(maxsize=64)
def frustum_extent(camera: Camera, margin_px: float) -> tuple[float, float, float, float]:
    """Normalised image-plane extent `(a_lo, a_hi, b_lo, b_hi)` of a camera's frame grown by
    `margin_px`, from the rays of the four corners and edge midpoints (distortion included)."""
    w, h = camera.width - 1.0, camera.height - 1.0
    m = -margin_px
    # corners plus edge midpoints: with barrel distortion the edge midpoints bulge outward
    border = np.array(
        [
            [m, m],
            [w / 2, m],
            [w - m, m],
            [w - m, h / 2],
            [w - m, h - m],
            [w / 2, h - m],
            [m, h - m],
            [m, h / 2],
        ]
    )
    rays_c = camera.bearing(border)
    ab = rays_c[:, :2] / rays_c[:, 2:]
    return float(ab[:, 0].min()), float(ab[:, 0].max()), float(ab[:, 1].min()), float(ab[:, 1].max())


def frustum_planes(camera: Camera, pose: Pose, margin_px: float = 0.0) -> np.ndarray:
    """Side planes of the viewing frustum in world coordinates, `(4, 4)` rows `[n, d]` with
    `n · X + d >= 0` inside. Built through the projection centre and the widest normalised extent
    of the image border (distortion included), so that it slightly over-covers the frame.
    """
    a_lo, a_hi, b_lo, b_hi = frustum_extent(camera, float(margin_px))
    # planes in camera frame through the origin: a >= a_lo  <=>  x - a_lo z >= 0, etc.
    n_c = np.array([[1.0, 0.0, -a_lo], [-1.0, 0.0, a_hi], [0.0, 1.0, -b_lo], [0.0, -1.0, b_hi]])
    n_w = n_c @ pose.R_world_from_cam.T
    d = -n_w @ pose.center
    return np.concatenate([n_w, d[:, None]], axis=1)


def boxes_in_frustum(
    camera: Camera,
    pose: Pose,
    lo: np.ndarray,
    hi: np.ndarray,
    options: VisibilityOptions = VisibilityOptions(),
) -> np.ndarray:
    """Conservative test of axis-aligned boxes `lo, hi (B, 3)` against a frame's frustum -> `(B,)` bool.

    False only when the box surely cannot appear: entirely behind the near plane, beyond
    `max_distance_m`, or entirely outside one side plane.
    """
    lo = np.atleast_2d(np.asarray(lo, dtype=np.float64))
    hi = np.atleast_2d(np.asarray(hi, dtype=np.float64))
    corners = np.stack(
        [np.where(np.array([i & 1, i & 2, i & 4], dtype=bool), hi, lo) for i in range(8)], axis=1
    )  # (B, 8, 3)
    planes = frustum_planes(camera, pose, margin_px=2.0)
    rel = corners - pose.center  # planes pass through the centre: no large offsets
    side = rel @ planes[:, :3].T  # (B, 8, 4)
    outside_side = np.any(np.all(side < 0, axis=1), axis=1)
    z = rel @ pose.R_world_from_cam[:, 2]  # depth along the optical axis
    behind = np.all(z < options.min_depth_m, axis=1)
    nearest = np.linalg.norm(np.clip(pose.center, lo, hi) - pose.center, axis=1)
    too_far = nearest > options.max_distance_m
    return ~(outside_side | behind | too_far)


def facing(normal: np.ndarray, point: np.ndarray, center: np.ndarray) -> bool:
    """True when `center (3,)` lies on the front side of the plane with unit `normal (3,)`
    through `point (3,)`: a cheap per-surface reject before any texel is projected."""
    return float(np.dot(np.asarray(center) - np.asarray(point), normal)) > 0.0


def unoccluded(
    raycaster: RayCaster | None, points: np.ndarray, center: np.ndarray, options: VisibilityOptions
) -> np.ndarray:
    """`(N,)` bool: nothing in the ray caster's scene lies between `center (3,)` and `points (N, 3)`
    (all True without a ray caster)."""
    if raycaster is None or len(points) == 0:
        return np.ones(len(points), dtype=bool)
    return raycaster.visible(points, center, tolerance_m=options.occlusion_tolerance_m)


@dataclass(frozen=True, eq=False)
class TexelProjection:
    """Where texels land in one frame.

    Attributes:
        uv: `(N, 2)` float64 pixels (NaN where behind the camera).
        depth: `(N,)` depth along the optical axis, metres.
        distance: `(N,)` distance to the projection centre, metres.
        cos_view: `(N,)` cosine of the angle between the surface normal and the ray to the camera.
        ok: `(N,)` bool, geometric tests passed (inside the frame, in front, facing, in range);
            occlusion is not yet tested.
    """

    uv: np.ndarray
    depth: np.ndarray
    distance: np.ndarray
    cos_view: np.ndarray
    ok: np.ndarray


def project_texels(
    camera: Camera, pose: Pose, points: np.ndarray, normal: np.ndarray, options: VisibilityOptions
) -> TexelProjection:
    """Project texel centres `points (N, 3)` of one surface (unit `normal (3,)`) into a frame and
    apply the geometric visibility tests (not occlusion).

    Points outside the frustum of the undistorted image border are rejected before the
    distortion is applied (the polynomial can fold points far outside the field of view back
    into the image)."""
    xc = (np.asarray(points, dtype=np.float64) - pose.center) @ pose.R_world_from_cam
    depth = xc[:, 2]
    distance = np.sqrt(np.einsum("ij,ij->i", xc, xc))
    n_c = pose.R_world_from_cam.T @ np.asarray(normal, dtype=np.float64)
    cos_view = -(xc @ n_c) / np.maximum(distance, 1e-12)
    a_lo, a_hi, b_lo, b_hi = frustum_extent(camera, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = xc[:, 0] / depth
        b = xc[:, 1] / depth
    ok = (
        (cos_view > math.cos(math.radians(options.max_view_angle_deg)))
        & (depth > options.min_depth_m)
        & (distance < options.max_distance_m)
        & (a >= a_lo)
        & (a <= a_hi)
        & (b >= b_lo)
        & (b <= b_hi)
    )
    uv = np.full((len(xc), 2), np.nan)
    idx = np.nonzero(ok)[0]
    if len(idx):
        uv[idx] = camera.pixel_from_normalized(np.stack([a[idx], b[idx]], axis=1))
        ok[idx] = camera.in_image(uv[idx], margin=options.margin_px)
    return TexelProjection(uv=uv, depth=depth, distance=distance, cos_view=cos_view, ok=ok)


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
    group: int,
    polygon_group: np.ndarray,
    options: VisibilityOptions,
    margin: int,
    require: str = "all",
) -> np.ndarray:
    """`(N,)` bool: the cast-grid elements around `uv (N, 2)` — the 2x2 around the sample grown by
    `margin` elements — all (`require="all"`; `"any"`: at least one) see the texel's own plane:
    their first hit is a polygon of the
    texel's plane `group` (see `plane_groups`) at the texel's `distance (N,)` within
    `depth_tolerance_m + depth_tolerance_rel · distance`. `polygon_group (P + 1,)` maps polygon
    index -> plane group, its last entry (index -1) is -1."""
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
    group: int,
    polygon_group: np.ndarray,
    options: VisibilityOptions,
    every: bool = True,
) -> np.ndarray:
    """`(N,)` bool: the cast rays at flat indices `lin (N,) + offsets` (first-hit distance `t`,
    polygon index `polygon`, flat) all (`every`; else at least one) hit the plane `group` at
    `distance (N,)` within the depth tolerance."""
    tol = options.depth_tolerance_m + options.depth_tolerance_rel * distance
    ok = np.full(len(lin), every, dtype=bool)
    for off in offsets:
        j = lin + off
        own = (polygon_group[polygon[j]] == group) & (np.abs(t[j] - distance) <= tol)
        ok = (ok & own) if every else (ok | own)
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


def buried_texels(
    raycaster: RayCaster, points: np.ndarray, normal: np.ndarray, offset_m: float = 0.02
) -> np.ndarray:
    """`(N,)` bool: texels `points (N, 3)` of a surface with unit `normal (3,)` that lie inside or on
    the wall of another solid (a shared wall of touching buildings, modelled twice): a ray from
    just in front of the texel along the normal first meets a surface from behind (its normal
    points along the ray). Such texels are never seen from outside."""
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    n = np.asarray(normal, dtype=np.float64)
    hits = raycaster.cast(
        np.asarray(points, dtype=np.float64) + offset_m * n, np.broadcast_to(n, points.shape)
    )
    return hits.hit & (hits.normal @ n > 0.0)


class OcclusionScene:
    """Everything the per-texel occlusion test needs for one unit: the ray caster over the
    scene mesh (building and occluders), the camera's pixel rays, and the scene index and plane
    group of each polygon. Rays are built in float32 in the mesh's local frame (no float64
    round trip). Not picklable; build one per unit."""

    def __init__(
        self, raycaster: RayCaster, camera: Camera, options: VisibilityOptions = VisibilityOptions()
    ) -> None:
        mesh = raycaster.mesh
        self.mesh = mesh
        self._raycaster = raycaster
        self.step = max(1, options.buffer_step_px)
        full = pixel_rays(camera)
        self._rays = {1: full, self.step: np.ascontiguousarray(full[:: self.step, :: self.step])}
        self.options = options
        self._corners = corner_rays(camera) if options.pixel_area else None
        self.polygon_index = mesh.polygon_index()
        self.polygon_group = np.append(plane_groups(mesh, options), -1).astype(np.intp)

    def buffer(self, pose: Pose, uv: np.ndarray, step: int = 1, margin: int = 0) -> HitBuffer:
        """Cast the grid of every `step`-th pixel around `uv (N, 2)` (the 2x2 grid elements around
        each sample grown by `margin`) from the projection centre of `pose` through the scene."""
        grid = self._rays[step]
        H, W = grid.shape[:2]
        if len(uv) * (2 + 2 * margin) ** 2 >= H * W // 2:  # most of the grid: cast it all
            pix = np.arange(H * W)
        else:
            need = np.zeros(H * W, dtype=np.uint8)
            lin = _top_left(uv / step, H, W, margin)
            for off in (0, 1, W, W + 1):
                need[lin + off] = 1
            if margin > 0:
                k = 2 * margin + 1
                need = cv2.dilate(need.reshape(H, W), np.ones((k, k), np.uint8)).ravel()
            pix = np.flatnonzero(need)
        t, poly = self._cast(pose, grid, pix)
        return HitBuffer(width=W, height=H, step=step, t=t, polygon=poly)

    def _cast(self, pose: Pose, grid: np.ndarray, pix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cast the rays of `grid (H, W, 3)` (camera frame) at flat indices `pix` from the projection
        centre of `pose` -> `(t (H·W,) float32, polygon (H·W,) int32)`, inf / -1 where not cast."""
        n = grid.shape[0] * grid.shape[1]
        t = np.full(n, np.inf, np.float32)
        poly = np.full(n, -1, np.int32)
        if len(pix):
            rays = np.empty((len(pix), 6), np.float32)
            rays[:, :3] = (pose.center - self.mesh.origin).astype(np.float32)
            rays[:, 3:] = grid.reshape(-1, 3)[pix] @ pose.R_world_from_cam.T.astype(np.float32)
            t[pix], poly[pix] = self._raycaster.cast_local(rays)
        return t, poly

    def _corner_index(self, uv: np.ndarray, margin: int) -> tuple[np.ndarray, np.ndarray]:
        """Flat index `(N,)` of the top-left corner of each sample's footprint (the 2x2 bilinear
        pixels grown by `margin`) and the flat offsets of its `(3 + 2·margin)²` corners."""
        assert self._corners is not None
        H1, W1 = self._corners.shape[:2]
        n = 3 + 2 * margin
        c0 = np.clip(np.floor(uv[:, 0]).astype(np.intp) - margin, 0, max(W1 - n, 0))
        r0 = np.clip(np.floor(uv[:, 1]).astype(np.intp) - margin, 0, max(H1 - n, 0))
        k = np.arange(n)
        return r0 * W1 + c0, (k[:, None] * W1 + k[None, :]).ravel()

    def pure_footprint(self, pose: Pose, samples: Sequence[tuple[np.ndarray, np.ndarray, int]],
                       margin: int) -> list[np.ndarray]:
        """Per surface `(N,)` bool: rays through every corner of the samples' footprint pixels
        (the 2x2 bilinear pixels grown by `margin`) see the texel's own plane at its distance
        (all True without `pixel_area`)."""
        if self._corners is None or not samples:
            return [np.ones(len(uv), bool) for uv, _, _ in samples]
        H1, W1 = self._corners.shape[:2]
        need = np.zeros(H1 * W1, np.bool_)
        for uv, _, _ in samples:
            lin, offs = self._corner_index(uv, margin)
            for off in offs:
                need[lin + off] = True
        t, poly = self._cast(pose, self._corners, np.flatnonzero(need))
        return [
            _own_plane(t, poly, *self._corner_index(uv, margin), d, g, self.polygon_group, self.options)
            for uv, d, g in samples
        ]

    def visible(self, pose: Pose, samples: Sequence[tuple[np.ndarray, np.ndarray, int]]) -> list[np.ndarray]:
        """Occlusion and silhouette test of a frame's texel samples, per surface.

        Args:
            samples: per surface `(uv (N, 2), distance (N,), plane group)`.

        Returns per surface `(N,)` bool: the pixels bilinear sampling reads and `blur_margin_px`
        around them see the texel's own plane. With `buffer_step_px > 1` a coarse grid decides
        first: samples whose coarse neighbourhood (2x2 grown by one element) is all own plane
        pass, those whose coarse 2x2 shows no own plane at all fail, and those in between (near
        a silhouette) are tested at full resolution.
        """
        o = self.options
        if not samples:
            return []
        all_uv = np.concatenate([uv for uv, _, _ in samples])
        if self.step == 1:
            buf = self.buffer(pose, all_uv, 1, o.blur_margin_px)
            pure = self.pure_footprint(pose, samples, o.blur_margin_px)
            return [
                consistent_samples(buf, uv, d, g, self.polygon_group, o, o.blur_margin_px) & p
                for (uv, d, g), p in zip(samples, pure, strict=True)
            ]
        coarse = self.buffer(pose, all_uv, self.step, 1)
        out, near = [], []
        for uv, d, g in samples:
            core = consistent_samples(coarse, uv, d, g, self.polygon_group, o, 0)
            ring = core.copy()
            ring[core] = consistent_samples(coarse, uv[core], d[core], g, self.polygon_group, o, 1)
            some = consistent_samples(coarse, uv, d, g, self.polygon_group, o, 0, require="any")
            out.append(ring)
            near.append(np.nonzero(some & ~ring)[0])
        if sum(len(n) for n in near):
            fine = self.buffer(
                pose,
                np.concatenate([uv[n] for (uv, _, _), n in zip(samples, near, strict=True)]),
                1,
                o.blur_margin_px,
            )
            subs = [(uv[n], d[n], g) for (uv, d, g), n in zip(samples, near, strict=True)]
            pure = self.pure_footprint(pose, subs, o.blur_margin_px)
            for k, (uv, d, g) in enumerate(subs):
                if len(uv):
                    out[k][near[k]] = consistent_samples(
                        fine, uv, d, g, self.polygon_group, o, o.blur_margin_px
                    ) & pure[k]
        return out

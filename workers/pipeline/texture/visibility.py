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
shared with a touching building are never visible (`buried_texels`). The occlusion test itself
is `occlusion.OcclusionScene` (re-exported here).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.texture.occlusion import (
    HitBuffer,
    OcclusionScene,
    consistent_samples,
    corner_rays,
    pixel_rays,
    plane_groups,
)
from workers.pipeline.texture.visibility_options import VisibilityOptions

__all__ = [  # the occlusion test (`occlusion`) is re-exported
    "HitBuffer",
    "OcclusionScene",
    "TexelProjection",
    "VisibilityOptions",
    "boxes_in_frustum",
    "buried_texels",
    "consistent_samples",
    "corner_rays",
    "facing",
    "frustum_extent",
    "frustum_planes",
    "pixel_rays",
    "plane_groups",
    "project_texels",
    "unoccluded",
]


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
    mesh = raycaster.mesh
    rays = np.empty((len(points), 6), np.float32)  # in the mesh's local frame, float32 (cast_local)
    rays[:, :3] = np.asarray(points, dtype=np.float64) + (offset_m * n - mesh.origin)
    rays[:, 3:] = n
    _, polygon = raycaster.cast_local(rays)
    hit = polygon >= 0
    # a triangle's normal is its polygon's (triangles are wound like their polygon's ring)
    behind = np.zeros(len(points), dtype=bool)
    behind[hit] = mesh.polygon_normals[polygon[hit]] @ n > 0.0
    return behind

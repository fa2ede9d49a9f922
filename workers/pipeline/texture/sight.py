"""How the frames see each surface, before any texel exists: the best ground resolution they
offer (so that a surface seen only coarsely still gets a texture, at the resolution the frames
support) and why a surface may get none.

In: polygons (model CRS, metres), the camera, the poses of the frames that may see them (world =
model CRS), a `RayCaster` over the scene (or None), `VisibilityOptions`.
Out: per polygon a `SurfaceSight`: the best local resolution (metres on the surface per image
pixel, the coarser of the two surface axes, as `fusion.local_resolution`) over the frames that
see one of its sample points unoccluded within the grazing limit, and counts of the frames that
had it in view, facing them, within the grazing limit, and unoccluded. `surface_resolution`
turns that into the texels per metre of the surface's grid.

Sample points: the centroid and the exterior vertices pulled 20 % towards it (up to 16), so a
surface half hidden behind a neighbour still counts as seen, and the resolution reflects its
nearest visible part.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Polygon
from workers.pipeline.geometry.polygons import fit_plane, open_ring, surface_axes
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.texture.fusion import local_resolution
from workers.pipeline.texture.visibility import VisibilityOptions, project_texels

#: largest number of exterior vertices sampled per polygon
MAX_SAMPLES = 16


@dataclass(frozen=True)
class SurfaceSight:
    """How the frames see one polygon (see the module docstring).

    Attributes:
        best_resolution_m: finest local resolution any frame gives one of its sample points
            (m/px; inf when no frame sees one unoccluded within the grazing limit).
        frames_in_view: frames with a sample point inside the image, in front of the camera and
            in range.
        frames_facing: of those, frames on the polygon's front side.
        frames_in_angle: of those, frames within `max_view_angle_deg` of its normal.
        frames_visible: of those, frames that see a sample point unoccluded.
    """

    best_resolution_m: float = math.inf
    frames_in_view: int = 0
    frames_facing: int = 0
    frames_in_angle: int = 0
    frames_visible: int = 0

    @property
    def seen(self) -> bool:
        """True when some frame sees the polygon (a sample point, unoccluded, within the limit)."""
        return self.frames_visible > 0

    def reason_unseen(self, max_view_angle_deg: float) -> str:
        """Why no frame sees the polygon; "" when one does or when it faces no frame at all."""
        if self.seen or self.frames_facing == 0:
            return ""
        if self.frames_in_angle == 0:
            return f"seen only at grazing angles beyond {max_view_angle_deg:g}° ({self.frames_facing} frames)"
        return f"hidden by other surfaces in every frame that looks at it ({self.frames_in_angle} frames)"


def sample_points(polygon: Polygon) -> tuple[np.ndarray, np.ndarray] | None:
    """Sample points `(S, 3)` of a polygon and its unit normal `(3,)`; None when degenerate."""
    plane = fit_plane(polygon)
    if plane is None:
        return None
    ext = open_ring(polygon.exterior.coords)
    if len(ext) > MAX_SAMPLES:
        ext = ext[np.linspace(0, len(ext) - 1, MAX_SAMPLES).astype(int)]
    c = plane.centroid
    # project onto the plane (slightly non-planar rings), pull towards the centroid
    pts = np.vstack([c, c + 0.8 * (ext - c)])
    pts -= np.outer((pts - c) @ plane.normal, plane.normal)
    return pts, plane.normal


def surface_sight(
    polygons: Sequence[Polygon],
    camera: Camera,
    poses: Sequence[Pose],
    raycaster: RayCaster | None,
    options: VisibilityOptions,
) -> list[SurfaceSight]:
    """`SurfaceSight` of every polygon over the frames at `poses` (see the module docstring)."""
    samples = [sample_points(p) for p in polygons]
    wide = VisibilityOptions(
        margin_px=options.margin_px, min_depth_m=options.min_depth_m, max_distance_m=options.max_distance_m,
        max_view_angle_deg=90.0,
    )  # fmt: skip
    cos_limit = math.cos(math.radians(options.max_view_angle_deg))
    counts = np.zeros((len(polygons), 4), np.int64)
    best = np.full(len(polygons), np.inf)
    for pose in poses:
        found: list[tuple[int, np.ndarray, np.ndarray]] = []
        for k, s in enumerate(samples):
            if s is None:
                continue
            pts, normal = s
            if not _in_view(camera, pose, pts, wide).any():
                continue
            counts[k, 0] += 1
            proj = project_texels(camera, pose, pts, normal, wide)
            if not proj.ok.any():
                continue
            counts[k, 1] += 1
            ok = proj.ok & (proj.cos_view > cos_limit)
            if ok.any():
                counts[k, 2] += 1
                found.append((k, pts[ok], normal))
        if not found:
            continue
        pts_all = np.concatenate([p for _, p, _ in found])
        vis = np.ones(len(pts_all), bool) if raycaster is None else raycaster.visible(
            pts_all, pose.center, tolerance_m=options.occlusion_tolerance_m
        )
        start = 0
        for k, pts, normal in found:
            v = vis[start : start + len(pts)]
            start += len(pts)
            if not v.any():
                continue
            counts[k, 3] += 1
            s_axis, t_axis = surface_axes(normal)
            rs, rt = local_resolution(camera, pose, pts[v], s_axis, t_axis)
            best[k] = min(best[k], float(np.min(np.maximum(rs, rt))))
    return [
        SurfaceSight(float(best[k]), *(int(x) for x in counts[k])) for k in range(len(polygons))
    ]


def _in_view(camera: Camera, pose: Pose, points: np.ndarray, options: VisibilityOptions) -> np.ndarray:
    """`(N,)` bool: points inside the image, in front of the camera and in range, whichever side
    of their surface the camera is on."""
    uv, depth = pose.project(camera, points)
    dist = np.linalg.norm(points - pose.center, axis=1)
    ok = (depth > options.min_depth_m) & (dist < options.max_distance_m)
    ok[ok] = camera.in_image(uv[ok], margin=0.0)
    return ok


def surface_resolution(requested_px_per_m: float, best_resolution_m: float, oversample: float) -> float:
    """Texels per metre of a surface's grid: the requested resolution, halved until one texel is
    no finer than `1 / oversample` of the best pixel footprint the frames give the surface
    (`best_resolution_m`, m/px). The halving ladder keeps the values exact in JSON and alike
    across surfaces.

    >>> surface_resolution(10.0, 0.05, 1.5), surface_resolution(10.0, 0.42, 1.5)
    (10.0, 2.5)
    """
    r = float(requested_px_per_m)
    if not math.isfinite(best_resolution_m) or best_resolution_m <= 0:
        return r
    while 1.0 / r < best_resolution_m / oversample and r > 1e-3:
        r /= 2.0
    return r

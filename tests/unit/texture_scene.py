"""Tiny analytic scenes for the texture tests: box buildings, a temperature field defined on
world points, and frames rendered by intersecting every pixel's ray with the polygons (no
renderer needed; the ground truth of every texel is the field at its centre)."""

from __future__ import annotations

import numpy as np
import shapely

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building, Polygon, Ring
from workers.pipeline.geometry.polygons import fit_plane, open_ring, surface_axes, to_plane_2d
from workers.pipeline.geometry.pose import Pose

SKY_K = 250.0


def ring(rid: str, pts: list[list[float]]) -> Ring:
    a = np.array(pts, dtype=float)
    return Ring(rid, np.vstack([a, a[:1]]))


def box_building(
    bid: str, x0: float, y0: float, x1: float, y1: float, h: float, holes: bool = False
) -> Building:
    """An axis-aligned box building with outward-facing walls and a flat roof (ids `<bid>_w0`...).

    With `holes`, the south wall (y = y0) gets two rectangular window holes.
    """
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    polys = []
    for k in range(4):
        (ax, ay), (bx, by) = corners[k], corners[(k + 1) % 4]
        ext = ring(f"{bid}_w{k}_r", [[ax, ay, 0], [bx, by, 0], [bx, by, h], [ax, ay, h]])
        interiors: tuple[Ring, ...] = ()
        if holes and k == 0:
            w = x1 - x0
            interiors = tuple(
                ring(
                    f"{bid}_w0_h{i}",
                    [[x0 + c, y0, 1.0], [x0 + c, y0, 2.5], [x0 + c + 1.5, y0, 2.5], [x0 + c + 1.5, y0, 1.0]],
                )
                for i, c in enumerate((0.2 * w, 0.6 * w))
            )
        polys.append(Polygon(f"{bid}_w{k}", ext, interiors, surface_class="WallSurface"))
    roof = ring(f"{bid}_roof_r", [[x, y, h] for x, y in corners])
    polys.append(Polygon(f"{bid}_roof", roof, surface_class="RoofSurface"))
    ground = ring(f"{bid}_ground_r", [[x, y, 0] for x, y in reversed(corners)])
    polys.append(Polygon(f"{bid}_ground", ground, surface_class="GroundSurface"))
    return Building(bid, tuple(polys))


def field(points: np.ndarray, edge_m: float = 0.15) -> np.ndarray:
    """Temperature field (K) at world points `(N, 3)`: smooth variation plus window-like warm
    rectangles with soft edges of width ~`edge_m` (sharp for small values)."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    base = 285.0 + 2.0 * np.sin(0.7 * x + 0.5 * y) + 1.5 * np.cos(0.9 * z) + 0.3 * np.sin(2.1 * (x - y))
    u = np.mod(x + y, 2.0) - 1.0  # windows every 2 m along the wall
    v = np.mod(z, 2.5) - 1.25
    e = max(edge_m, 1e-3)
    win = 0.25 * (1 + np.tanh((0.5 - np.abs(u)) / e)) * (1 + np.tanh((0.6 - np.abs(v)) / e))
    return (base + 4.0 * win).astype(np.float64)


def look_at(center: np.ndarray, target: np.ndarray) -> Pose:
    """A level camera at `center` looking at `target` (OpenCV axes: y down)."""
    c = np.asarray(center, float)
    zc = np.asarray(target, float) - c
    zc /= np.linalg.norm(zc)
    xc = np.cross(zc, [0.0, 0.0, 1.0])
    xc /= np.linalg.norm(xc)
    yc = np.cross(zc, xc)
    return Pose(np.stack([xc, yc, zc], axis=1), c)


def render(camera: Camera, pose: Pose, buildings: list[Building], edge_m: float = 0.15) -> np.ndarray:
    """Float32 frame `(H, W)`: per pixel the field at the nearest polygon hit, `SKY_K` elsewhere."""
    H, W = camera.height, camera.width
    uu, vv = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
    d = camera.bearing(uv) @ pose.R_world_from_cam.T
    best = np.full(len(d), np.inf)
    for b in buildings:
        for p in b.iter_polygons():
            pl = fit_plane(p)
            denom = d @ pl.normal
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (pl.offset - pose.center @ pl.normal) / denom
            cand = (t > 0) & (t < best)
            if not cand.any():
                continue
            X = pose.center + t[cand, None] * d[cand]
            s, tt = surface_axes(pl.normal, p.exterior.coords)
            st = to_plane_2d(X, pl.centroid, s, tt)
            shape = shapely.Polygon(
                to_plane_2d(open_ring(p.exterior.coords), pl.centroid, s, tt),
                [to_plane_2d(open_ring(r.coords), pl.centroid, s, tt) for r in p.interiors],
            )
            inside = shapely.contains_xy(shape, st[:, 0], st[:, 1])
            ci = np.nonzero(cand)[0][inside]
            best[ci] = t[ci]
    img = np.full(len(d), SKY_K)
    hit = np.isfinite(best)
    img[hit] = field(pose.center + best[hit, None] * d[hit], edge_m)
    return img.reshape(H, W).astype(np.float32)

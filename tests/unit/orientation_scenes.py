"""Small synthetic scenes for the orientation tests: box and gable buildings, a ray-cast TIR
renderer with constant temperatures per surface (plus window grids), and drive poses.

Independent of the project's synthesiser so that the orientation tests pin down their own
ground truth; coordinates in a local metric CRS (x east, y north, z up).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building, Polygon, Ring
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
from workers.pipeline.orientation.quality import edge_points
from workers.pipeline.orientation.quality import reprojection_rms as quality_rms

CAMERA = Camera(width=640, height=512, fx=780.0, fy=780.0, cx=319.5, cy=255.5, k1=-0.08, k2=0.02)


def _poly(pid: str, pts: list[tuple[float, float, float]], cls: str) -> Polygon:
    c = np.array([*pts, pts[0]], dtype=np.float64)
    return Polygon(id=pid, exterior=Ring(id=pid + "_r", coords=c), surface_class=cls)


def box_building(bid: str, x0: float, y0: float, w: float, d: float, h: float,
                 ridge: float = 0.0) -> Building:
    """A box `w` (x) by `d` (y) by `h` from `(x0, y0, 0)`; a gable roof along x when `ridge` > 0."""
    x1, y1 = x0 + w, y0 + d
    ym = 0.5 * (y0 + y1)
    P = [
        _poly(f"{bid}_g", [(x0, y0, 0), (x0, y1, 0), (x1, y1, 0), (x1, y0, 0)], "GroundSurface"),
        _poly(f"{bid}_ws", [(x0, y0, 0), (x1, y0, 0), (x1, y0, h), (x0, y0, h)], "WallSurface"),
        _poly(f"{bid}_wn", [(x1, y1, 0), (x0, y1, 0), (x0, y1, h), (x1, y1, h)], "WallSurface"),
    ]
    if ridge > 0:
        P += [
            _poly(f"{bid}_we", [(x1, y0, 0), (x1, y1, 0), (x1, y1, h), (x1, ym, h + ridge), (x1, y0, h)],
                  "WallSurface"),
            _poly(f"{bid}_ww", [(x0, y1, 0), (x0, y0, 0), (x0, y0, h), (x0, ym, h + ridge), (x0, y1, h)],
                  "WallSurface"),
            _poly(f"{bid}_rs", [(x0, y0, h), (x1, y0, h), (x1, ym, h + ridge), (x0, ym, h + ridge)],
                  "RoofSurface"),
            _poly(f"{bid}_rn", [(x1, y1, h), (x0, y1, h), (x0, ym, h + ridge), (x1, ym, h + ridge)],
                  "RoofSurface"),
        ]
    else:
        P += [
            _poly(f"{bid}_we", [(x1, y0, 0), (x1, y1, 0), (x1, y1, h), (x1, y0, h)], "WallSurface"),
            _poly(f"{bid}_ww", [(x0, y1, 0), (x0, y0, 0), (x0, y0, h), (x0, y1, h)], "WallSurface"),
            _poly(f"{bid}_r", [(x0, y0, h), (x1, y0, h), (x1, y1, h), (x0, y1, h)], "RoofSurface"),
        ]
    return Building(id=bid, polygons=tuple(P))


def look_at(center: np.ndarray, target: np.ndarray) -> Pose:
    """Pose at `center` looking at `target` with image `v` pointing down (world z up)."""
    z = np.asarray(target, float) - np.asarray(center, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose(np.stack([x, y, z], axis=1), np.asarray(center, float))


def rot(axis: np.ndarray, deg: float) -> np.ndarray:
    """Rotation matrix about a unit `axis` by `deg` degrees (Rodrigues)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def perturb(pose: Pose, d_center: np.ndarray, d_rot_deg: np.ndarray) -> Pose:
    """Pose with its centre moved by `d_center` (world) and rotated by small angles about camera x, y, z."""
    R = pose.R_world_from_cam
    for i, ang in enumerate(d_rot_deg):
        if ang:
            R = R @ rot(np.eye(3)[i], ang)
    return Pose(R, pose.center + np.asarray(d_center, float))


@dataclass
class Renderer:
    """Ray-cast TIR renderer: a temperature per polygon, window grids on walls, ground and sky."""

    buildings: list[Building]
    camera: Camera = CAMERA
    sky_k: float = 262.0
    ground_k: float = 272.5
    windows: bool = True
    blur_sigma: float = 0.7
    noise_k: float = 0.05
    seed: int = 0

    def __post_init__(self) -> None:
        self.mesh = build_scene_mesh(self.buildings)
        self.caster = RayCaster(self.mesh)
        rng = np.random.default_rng(self.seed)
        temps = []
        for pid in self.mesh.polygon_ids:
            if pid.endswith("_r") or pid.endswith("_rs") or pid.endswith("_rn"):
                temps.append(271.0 + rng.uniform(-0.5, 0.5))
            else:
                temps.append(276.0 + rng.uniform(-1, 1))
        self.temps = np.array(temps)
        H, W = self.camera.height, self.camera.width
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        self.bearings = self.camera.bearing(np.stack([u.ravel(), v.ravel()], axis=1))

    def render(self, pose: Pose, frame_seed: int = 0) -> np.ndarray:
        """`(H, W)` float32 kelvin seen from `pose`."""
        d = self.bearings @ pose.R_world_from_cam.T
        hits = self.caster.cast(np.broadcast_to(pose.center, d.shape), d)
        out = np.full(len(d), self.sky_k)
        ground = (~hits.hit) & (d[:, 2] < 0)
        tg = -pose.center[2] / np.where(ground, d[:, 2], -1.0)
        gp = pose.center + tg[:, None] * d
        out[ground] = self.ground_k + 0.5 * np.sin(0.7 * gp[ground, 0]) * np.cos(0.5 * gp[ground, 1])
        h = hits.hit
        out[h] = self.temps[hits.polygon[h]]
        if self.windows:
            X = pose.center + hits.t[h, None] * d[h]
            n = hits.normal[h]
            wall = np.abs(n[:, 2]) < 0.3
            s = np.where(np.abs(n[:, 0]) > np.abs(n[:, 1]), X[:, 1], X[:, 0])
            z = X[:, 2]
            win = wall & (np.mod(s, 3.0) > 1.0) & (np.mod(s, 3.0) < 2.2) & (np.mod(z, 3.0) > 1.0) & (
                np.mod(z, 3.0) < 2.4) & (z < 8.0)
            vals = out[h]
            vals[win] -= 2.5
            out[h] = vals
        img = out.reshape(self.camera.height, self.camera.width).astype(np.float32)
        if self.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.blur_sigma)
        rng = np.random.default_rng(1000 + frame_seed)
        return (img + rng.normal(0, self.noise_k, img.shape)).astype(np.float32)


def drive_poses(start: np.ndarray, heading: np.ndarray, n: int, step_m: float = 0.8,
                forward_deg: float = 25.0, up_deg: float = 12.0) -> list[Pose]:
    """Side-looking drive: camera at `start` moving along the horizontal `heading`, looking right,
    turned `forward_deg` toward the front and tilted `up_deg` up."""
    f = np.asarray(heading, float)
    f /= np.linalg.norm(f)
    right = np.array([f[1], -f[0], 0.0])
    a, e = np.radians(forward_deg), np.radians(up_deg)
    view = np.cos(e) * (np.cos(a) * right + np.sin(a) * f) + np.array([0, 0, np.sin(e)])
    return [look_at(np.asarray(start, float) + k * step_m * f,
                    np.asarray(start, float) + k * step_m * f + view) for k in range(n)]


def reprojection_rms(camera: Camera, building: Building, pose: Pose, truth: Pose) -> float:
    """RMS pixel distance, `pose` vs `truth`, of points along the building's edges that the true
    pose sees inside the frame and in front (NaN when there are none)."""
    return quality_rms(camera, edge_points(building), pose, truth)

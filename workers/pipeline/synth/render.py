"""TIR frame renderer: ray casting through the city model, one ray per pixel (or sub-pixel).

In: a `SceneMesh` (model CRS, metres), a `ThermalScene`, a `Camera` (spec conventions: OpenCV
distortion, pixel centres at integers), the ground plane height and a camera `Pose`
(`R_world_from_cam`, centre). Out: `(H, W)` float32 temperature images in kelvin: the ideal
scene (`radiance`) or with sensor effects (`frame`): Gaussian PSF blur, vignetting, fixed-pattern
column noise and temporal noise (NETD); `dn` quantises to uint16 with the radiometry
`DN · 0.01 + 0 = K`.

Rays: `Camera.bearing` of each pixel centre, rotated into the world by `R_wc` and cast from `C`
with Open3D on the `raycast.SceneMesh`. A microbolometer integrates the radiance over its pixel's
area, so a pixel is the mean of `supersample²` sub-pixel rays (default 3 × 3): one ray per pixel
centre with a blur afterwards would put every edge on the pixel grid (edges jumping by whole
pixels from frame to frame, an aliasing no real sensor has). With `adaptive` (default), the
sub-pixel rays are cast only for pixels whose 4-neighbour differs by more than
`adaptive_threshold_k` or sees another surface: inside a smooth patch the mean over the pixel
equals the centre value to second order, and the edges (10–20 % of a drive's pixels, most of
a flight's) cost the extra rays. The ground is an analytic plane `z = ground_z` (not in the
mesh) or a `Ground` terrain (`synth.ground`: a TIN cast as a second geometry of the model's scene,
the plane beyond it); a ray that hits neither the model nor the ground sees the sky. Optional `Occluders`
(`synth.occluders`: trees, cars the model lacks) are a second triangle mesh with a temperature
per triangle; a ray that meets one before the model and the ground sees it (label `OCCLUDER`).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.manifest import Radiometry
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import SceneMesh, open3d_scene
from workers.pipeline.synth.common import SynthError, rng_for
from workers.pipeline.synth.ground import Ground
from workers.pipeline.synth.occluders import Occluders
from workers.pipeline.synth.thermal import ThermalScene

#: Pixel labels of `Renderer.labels` for what a ray saw besides a polygon index.
SKY, GROUND, OCCLUDER = -1, -2, -3

RADIOMETRY = Radiometry(unit="K", scale=0.01, offset=0.0)


_POOL: tuple[int, ThreadPoolExecutor] | None = None  # (pid, pool): a forked child builds its own


def _parallel_temperature(
    thermal: ThermalScene, x: np.ndarray, y: np.ndarray, z: np.ndarray, p: np.ndarray
) -> np.ndarray:
    """`thermal.temperature_xyz_unchecked` split over the CPU cores (numpy releases the GIL in
    its loops); `p` are valid polygon indices (ray-cast labels)."""
    global _POOL
    n_threads = min(os.cpu_count() or 1, 4)
    n = len(p)
    if n_threads < 2 or n < 50_000:
        return thermal.temperature_xyz_unchecked(x, y, z, p)
    if _POOL is None or _POOL[0] != os.getpid():
        _POOL = (os.getpid(), ThreadPoolExecutor(max_workers=n_threads, thread_name_prefix="synth-render"))
    pool = _POOL[1]
    edges = np.linspace(0, n, n_threads + 1).astype(int)
    parts = [(edges[i], edges[i + 1]) for i in range(n_threads)]
    ev = thermal.temperature_xyz_unchecked
    futures = [pool.submit(ev, x[a:b], y[a:b], z[a:b], p[a:b]) for a, b in parts[1:]]
    a, b = parts[0]
    first = ev(x[a:b], y[a:b], z[a:b], p[a:b])
    return np.concatenate([first, *(f.result() for f in futures)])


def default_camera(width: int = 640, height: int = 512, hfov_deg: float = 45.0) -> Camera:
    """The default TIR camera: `width × height`, `hfov_deg` horizontal field of view (pinhole),
    square pixels, principal point at the image centre, mild barrel distortion."""
    fx = 0.5 * width / np.tan(np.radians(0.5 * hfov_deg))
    return Camera(
        width=width,
        height=height,
        fx=float(fx),
        fy=float(fx),
        cx=0.5 * (width - 1),
        cy=0.5 * (height - 1),
        k1=-0.1,
        k2=0.03,
    )


@dataclass(frozen=True)
class SensorOptions:
    """Sensor effects, each switched off by setting it to 0."""

    psf_sigma_px: float = 0.6  # Gaussian optical blur, pixels
    netd_k: float = 0.05  # temporal noise (noise-equivalent temperature difference), K
    column_noise_k: float = 0.03  # fixed-pattern column offsets (same in every frame), K
    vignetting_k: float = -0.2  # offset at the image corners, quadratic in the radius, K
    supersample: int = 3  # area sampling: rays per pixel = supersample²
    adaptive: bool = True  # sub-pixel rays only at edges (see the module docstring)
    adaptive_threshold_k: float = 0.25  # a 4-neighbour this much warmer or colder marks an edge, K


class Renderer:
    """Renders one camera over one scene (see the module docstring).

    Picklable: the Open3D scene is rebuilt in the receiving process.

    Args:
        mesh: the triangulated scene.
        thermal: its temperature field (polygon order = `mesh.polygon_ids`).
        camera: interior orientation.
        ground_z: the ground: a plane's height (world metres) or a `Ground` (a terrain TIN inside
            the plane `ground.z`, `synth.ground`).
        sensor: sensor effects.
        seed: seed of the fixed-pattern and temporal noise.
        occluders: trees, cars the model lacks (None: none).
    """

    def __init__(
        self,
        mesh: SceneMesh,
        thermal: ThermalScene,
        camera: Camera,
        ground_z: float | Ground,
        sensor: SensorOptions | None = None,
        seed: int = 0,
        occluders: Occluders | None = None,
    ) -> None:
        if tuple(thermal.polygon_ids) != tuple(mesh.polygon_ids):
            raise SynthError("thermal scene and mesh disagree on the polygon order")
        self.mesh, self.thermal, self.camera = mesh, thermal, camera
        self.ground = ground_z if isinstance(ground_z, Ground) else Ground(float(ground_z))
        self.ground_z = float(self.ground.z)
        self.sensor = sensor or SensorOptions()
        if self.sensor.supersample < 1:
            raise SynthError(f"supersample must be >= 1, got {self.sensor.supersample}")
        self.seed = int(seed)
        self.occluders = occluders if occluders is not None and len(occluders.triangles) else None
        self._scene: tuple | None = None
        # polygon label per triangle, plus SKY for Open3D's invalid id (clipped to the last entry)
        self._tri_label = np.append(mesh.triangle_polygon.astype(np.int32), np.int32(SKY))
        self._rays: tuple[np.ndarray, np.ndarray] | None = None  # `_bearings`, made on first use
        H, W = camera.height, camera.width
        fpn = rng_for(seed, "fpn").standard_normal(W)
        self._columns = (self.sensor.column_noise_k * fpn).astype(np.float32)
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        r2 = ((u - camera.cx) ** 2 + (v - camera.cy) ** 2) / (camera.cx**2 + camera.cy**2)
        self._vignette = (self.sensor.vignetting_k * r2).astype(np.float32)

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_scene"] = None
        state["_rays"] = None  # rebuilt on demand (tens of MB)
        return state

    def _raycasting_scene(self) -> object:
        """Open3D `RaycastingScene` of `mesh` (local frame `mesh.origin`), built once per process.

        The same triangles `raycast.RayCaster` casts against; rays are built here directly in
        float32 in the mesh's local frame, which saves RayCaster's float64 round trip (~25 ms
        per 640×512 frame).
        """
        if self._scene is None:
            import open3d as o3d  # heavy: only processes that render import it

            scene = open3d_scene(self.mesh)
            occ = None
            if self.occluders is not None:
                occ = o3d.t.geometry.RaycastingScene()
                local = (self.occluders.vertices - self.mesh.origin).astype(np.float32)
                occ.add_triangles(
                    o3d.core.Tensor.from_numpy(local),
                    o3d.core.Tensor.from_numpy(np.ascontiguousarray(self.occluders.triangles, np.uint32)),
                )
            ground_id = None
            if not self.ground.flat:  # the terrain: a second geometry of the same scene
                local = (self.ground.vertices - self.mesh.origin).astype(np.float32)
                ground_id = scene.add_triangles(
                    o3d.core.Tensor.from_numpy(np.ascontiguousarray(local)),
                    o3d.core.Tensor.from_numpy(np.ascontiguousarray(self.ground.triangles, np.uint32)),
                )
            self._scene = (o3d, scene, occ, ground_id)
        return self._scene

    def _bearings(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit rays in the camera frame, float32, made on first use: through every pixel centre
        `(H·W, 3)`, and through the centres of the `ss × ss` sub-pixels of every pixel
        `(ss², H·W, 3)` (empty when `supersample` is 1). The sub-pixel rays are interpolated
        bilinearly between the pixel-centre rays (the ray field is smooth: far below 1e-3 px of
        error), which spares the iterative undistortion of `ss²` times as many points."""
        if self._rays is None:
            cam, ss = self.camera, self.sensor.supersample
            H, W = cam.height, cam.width
            v, u = np.mgrid[-1 : H + 1, -1 : W + 1].astype(np.float64)  # one pixel beyond the frame
            grid = cam.bearing(np.stack([u, v], axis=-1).reshape(-1, 2)).reshape(H + 2, W + 2, 3)
            centres = np.ascontiguousarray(grid[1:-1, 1:-1].reshape(-1, 3), dtype=np.float32)
            offs = (np.arange(ss) + 0.5) / ss - 0.5 if ss > 1 else np.zeros(0)
            sub = np.empty((len(offs) ** 2, H * W, 3), np.float32)
            k = 0
            for dv in offs:
                for du in offs:
                    # the same bilinear weights for every pixel: its cell's corners are shifted slices
                    su, sv = int(np.sign(du)), int(np.sign(dv))
                    a, b = abs(du), abs(dv)

                    def part(di: int, dj: int) -> np.ndarray:
                        return grid[1 + di : H + 1 + di, 1 + dj : W + 1 + dj]

                    r = ((1 - a) * (1 - b) * part(0, 0) + a * (1 - b) * part(0, su)
                         + (1 - a) * b * part(sv, 0) + a * b * part(sv, su))
                    sub[k] = (r / np.linalg.norm(r, axis=-1, keepdims=True)).reshape(-1, 3)
                    k += 1
            self._rays = (centres, sub)
        return self._rays

    # -- ideal images ----------------------------------------------------------------------------
    def hits(self, C: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """What rays from the projection centre `C` `(3,)` (world, m) along world directions `d`
        `(N, 3)` float32 (unit) meet first: (ray length `(N,)` float32 m, inf for the sky; label
        `(N,)` int32: polygon index, `SKY`, `GROUND` or `OCCLUDER`; the occluder triangle hit `(N,)`
        where the label is `OCCLUDER`, None without occluders). The ground is the terrain's
        triangles (cast with the model) and, where a ray meets nothing, the plane `ground.z`."""
        f32 = np.float32
        n = len(d)
        label = np.full(n, SKY, np.int32)
        o3d, scene, occ, ground_id = self._raycasting_scene()
        rays = np.empty((n, 6), f32)
        rays[:, :3] = (np.asarray(C, np.float64) - self.mesh.origin).astype(f32)
        rays[:, 3:] = d
        if len(self.mesh.triangles) or ground_id is not None:
            ans = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))
            t = ans["t_hit"].numpy()
            prim = ans["primitive_ids"].numpy()
            label = self._tri_label[np.minimum(prim, len(self._tri_label) - 1)]
            if ground_id is not None:
                label[ans["geometry_ids"].numpy() == ground_id] = GROUND
        else:
            t = np.full(n, np.inf, f32)
        occ_prim = None
        if occ is not None:
            ans = occ.cast_rays(o3d.core.Tensor.from_numpy(rays))
            t_occ = ans["t_hit"].numpy()
            hit = np.flatnonzero(t_occ < t)
            occ_prim = ans["primitive_ids"].numpy()
            if len(hit):
                t = t.copy()
                t[hit] = t_occ[hit]
                label[hit] = OCCLUDER
        dz = np.ascontiguousarray(d[:, 2])
        with np.errstate(divide="ignore", invalid="ignore"):
            tg = f32(self.ground_z - C[2]) / dz
        # with a terrain, the plane lies beyond its outer square: only a ray that met nothing
        plane = (dz < 0) & (tg > 0) & ((tg < t) if ground_id is None else np.isinf(t))
        t = np.where(plane, tg, t)
        label[plane] = GROUND
        return t, label, occ_prim

    def _trace(self, pose: Pose, bearings: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Cast rays `(N, 3)` (camera frame) -> (temperature `(N,)` float32 K, label `(N,)` int32,
        ray length `(N,)` float32 m, inf for the sky)."""
        f32 = np.float32
        R = np.asarray(pose.R_world_from_cam, dtype=np.float64)
        C = np.asarray(pose.center, dtype=np.float64)
        b = np.ascontiguousarray(bearings, dtype=f32)
        n = len(b)
        d = cv2.transform(b.reshape(n, 1, 3), R.astype(f32)).reshape(n, 3)  # world directions
        t, label, occ_prim = self.hits(C, d)
        T = np.empty(n, f32)
        if occ_prim is not None:
            io = np.flatnonzero(label == OCCLUDER)
            T[io] = self.occluders.temperature[occ_prim[io]]
        dx, dy, dz = (np.ascontiguousarray(c) for c in d.T)
        cx, cy, cz = (C - self.thermal.origin).astype(f32)
        on = np.flatnonzero(label >= 0)
        if len(on):
            ton = t[on]
            x, y, z = cx + ton * dx[on], cy + ton * dy[on], cz + ton * dz[on]
            T[on] = _parallel_temperature(self.thermal, x, y, z, label[on])
        ig = np.flatnonzero(label == GROUND)
        if len(ig):
            tgr = t[ig]
            T[ig] = self.thermal.ground_temperature_local(
                np.stack([cx + tgr * dx[ig], cy + tgr * dy[ig], cz + tgr * dz[ig]], axis=-1)
            )
        sky = np.flatnonzero(label == SKY)
        if len(sky):
            T[sky] = self.thermal.sky_temperature(d[sky])
        return T, label, t

    def radiance(self, pose: Pose) -> np.ndarray:
        """Ideal temperature image `(H, W)` float32 K: the mean over each pixel's area
        (`supersample²` sub-pixel rays, only at edges when `adaptive`), no sensor effects."""
        H, W = self.camera.height, self.camera.width
        s = self.sensor
        centres, sub = self._bearings()
        if s.supersample == 1:
            return self._trace(pose, centres)[0].reshape(H, W)
        if not s.adaptive:
            acc = np.zeros(H * W, np.float64)
            for b in sub:
                acc += self._trace(pose, b)[0]
            return (acc / len(sub)).astype(np.float32).reshape(H, W)
        T, label, _ = self._trace(pose, centres)
        idx = np.flatnonzero(_edge_pixels(T.reshape(H, W), label.reshape(H, W), s.adaptive_threshold_k))
        if len(idx):
            # with an odd `supersample` the middle sub-pixel is the pixel centre, already cast
            mid = len(sub) // 2 if s.supersample % 2 else -1
            acc = T[idx].astype(np.float64) if mid >= 0 else np.zeros(len(idx), np.float64)
            for k, b in enumerate(sub):
                if k != mid:
                    acc += self._trace(pose, b[idx])[0]
            T[idx] = (acc / len(sub)).astype(np.float32)
        return T.reshape(H, W)

    def labels(self, pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """What each pixel centre sees: label `(H, W)` int32 (polygon index, `SKY` or `GROUND`)
        and ray length `(H, W)` float64 metres (inf for sky)."""
        cam = self.camera
        _, label, t = self._trace(pose, self._bearings()[0])
        return label.reshape(cam.height, cam.width), t.astype(np.float64).reshape(cam.height, cam.width)

    # -- sensor ---------------------------------------------------------------------------------
    def apply_sensor(self, image: np.ndarray, index: int) -> np.ndarray:
        """Sensor effects on an ideal image `(H, W)` K -> `(H, W)` float32 K; the temporal noise
        is drawn from `(seed, index)`, so a frame renders identically every time."""
        s = self.sensor
        img = np.asarray(image, dtype=np.float32)
        if s.psf_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), s.psf_sigma_px, borderType=cv2.BORDER_REFLECT)
        if s.vignetting_k:
            img = img + self._vignette
        if s.column_noise_k:
            img = img + self._columns[None, :]
        if s.netd_k > 0:
            noise = rng_for(self.seed, "netd", index).standard_normal(img.shape, dtype=np.float32)
            img = img + np.float32(s.netd_k) * noise
        return img.astype(np.float32)

    def frame(self, pose: Pose, index: int) -> np.ndarray:
        """Frame `index` seen from `pose`: `(H, W)` float32 K with sensor effects."""
        return self.apply_sensor(self.radiance(pose), index)

    def frame_dn(self, pose: Pose, index: int) -> np.ndarray:
        """Frame `index` as `(H, W)` uint16 DN (`K = DN · 0.01`)."""
        return RADIOMETRY.dn(self.frame(pose, index))


def _edge_pixels(T: np.ndarray, label: np.ndarray, threshold_k: float) -> np.ndarray:
    """`(H, W)` bool: pixels of the centre-sampled image `T` `(H, W)` K with a 4-neighbour more
    than `threshold_k` warmer or colder, or labelled differently (`label` `(H, W)`): the pixels an
    edge may cross (both pixels of every such pair are marked)."""
    out = np.zeros(T.shape, bool)
    for axis in (0, 1):
        a = [slice(None)] * 2
        b = [slice(None)] * 2
        a[axis], b[axis] = slice(1, None), slice(None, -1)
        jump = (np.abs(T[tuple(a)] - T[tuple(b)]) > threshold_k) | (label[tuple(a)] != label[tuple(b)])
        out[tuple(a)] |= jump
        out[tuple(b)] |= jump
    return out

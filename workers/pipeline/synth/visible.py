"""Visible-band (RGB) camera of the synthetic generator: albedo textures and 8-bit rendering.

In: the TIR `Renderer` of a scene (its `SceneMesh`, `ThermalScene` and ground plane; world =
model CRS, metres), an RGB `Camera` and camera `Pose`s (`R_world_from_cam`, centre).
Out: `(H, W, 3)` uint8 RGB frames of the same scene as the TIR frames.

Surfaces get procedural albedo textures with real structure, so that stereo matching works:
walls are brick (courses 8.5 cm, bricks 25 cm, mortar joints, a shade per brick) or plaster
(multi-octave value noise), with the thermal scene's window grid as dark panes in light frames;
roofs are tiles (a shade per tile); the ground is asphalt (value noise at 4 cm … 60 cm); the sky
a smooth gradient. Shading is Lambertian under a sun plus ambient light. Texture coordinates are
the thermal scene's wall-local `s` (horizontal along the polygon) and `v` (height above the
building's base on walls, the slope coordinate on roofs), so textures are fixed to the surfaces.
One ray per pixel centre, then a Gaussian PSF and sensor noise (seeded by frame index).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.georef import body_from_cam, ins_from_camera
from workers.pipeline.geometry.manifest import Accuracy, FrameRecord, Mounting, SecondCamera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.synth.common import SynthError, rng_for
from workers.pipeline.synth.render import GROUND, OCCLUDER, Renderer
from workers.pipeline.synth.thermal import _gather_rows

F32 = np.float32


@dataclass(frozen=True)
class RgbOptions:
    """The RGB camera of `SynthOptions.rgb`: interior orientation, mounting relative to the TIR
    camera, pose errors and rendering. Metres, degrees, pixels, 8-bit digital numbers."""

    width: int = 1280
    height: int = 1024
    hfov_deg: float = 50.0  # a little wider than the TIR camera's 45°: it covers the TIR view
    offset_m: tuple[float, float, float] = (0.12, -0.05, 0.0)  # centre in TIR camera axes
    rotation_deg: tuple[float, float, float] = (0.3, -0.4, 0.2)  # about TIR camera x, y, z
    pose_source: str = "photogrammetric"  # what the manifest states
    position_sigma_m: float = 0.005  # per-frame pose errors (a block adjusted with GCPs)
    attitude_sigma_deg: float = 0.003
    psf_sigma_px: float = 0.5
    noise_dn: float = 1.5
    sun_azimuth_deg: float = 135.0  # clockwise from grid north
    sun_elevation_deg: float = 35.0


def rgb_camera(o: RgbOptions) -> Camera:
    """The RGB camera: `width × height`, `hfov_deg`, principal point at the centre, mild barrel."""
    fx = 0.5 * o.width / np.tan(np.radians(0.5 * o.hfov_deg))
    return Camera(width=o.width, height=o.height, fx=float(fx), fy=float(fx), cx=0.5 * (o.width - 1),
                  cy=0.5 * (o.height - 1), k1=-0.05, k2=0.01)  # fmt: skip


def _rot(angles_deg: np.ndarray) -> np.ndarray:
    """`Rz(c) · Ry(b) · Rx(a)` for `[a, b, c]` degrees -> `(3, 3)`."""
    a, b, c = np.radians(np.asarray(angles_deg, dtype=np.float64))
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    Rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def tir_from_rgb(o: RgbOptions) -> tuple[np.ndarray, np.ndarray]:
    """The RGB camera in the TIR camera's frame: (`R_tir_from_rgb` `(3, 3)`, centre `(3,)` m)."""
    return _rot(np.asarray(o.rotation_deg)), np.asarray(o.offset_m, dtype=np.float64)


def rgb_poses(tir_poses: list[Pose], o: RgbOptions) -> list[Pose]:
    """True RGB poses from true TIR poses (rigid mount, same exposure)."""
    R_tr, c = tir_from_rgb(o)
    return [Pose(p.R_world_from_cam @ R_tr, p.center + p.R_world_from_cam @ c) for p in tir_poses]


def perturbed(poses: list[Pose], o: RgbOptions, seed: int) -> list[Pose]:
    """`poses` with the RGB block's per-frame errors (Gaussian position and small rotations)."""
    rng = rng_for(seed, "rgb-pose-errors")
    out = []
    for p in poses:
        dR = _rot(o.attitude_sigma_deg * rng.standard_normal(3))
        out.append(Pose(dR @ p.R_world_from_cam, p.center + o.position_sigma_m * rng.standard_normal(3)))
    return out


# -- procedural textures -------------------------------------------------------------------------
def _hash(i: np.ndarray, j: np.ndarray, k: np.ndarray | int) -> np.ndarray:
    """Integer lattice `(i, j, k)` -> uniform float32 in [0, 1) (a 32-bit integer mix)."""
    i64 = np.int64
    h = (np.asarray(i, i64) * 73856093) ^ (np.asarray(j, i64) * 19349663) ^ (np.asarray(k, i64) * 83492791)
    h = (h & 0xFFFFFFFF).astype(np.uint64)
    h = ((h >> np.uint64(16)) ^ h) * np.uint64(0x45D9F3B) & np.uint64(0xFFFFFFFF)
    h = ((h >> np.uint64(16)) ^ h) * np.uint64(0x45D9F3B) & np.uint64(0xFFFFFFFF)
    h = (h >> np.uint64(16)) ^ h
    return ((h & np.uint64(0xFFFFFF)).astype(F32)) / F32(1 << 24)


def _value_noise(a: np.ndarray, b: np.ndarray, cell: float, key: int) -> np.ndarray:
    """Smooth value noise in [0, 1) at `(a, b)` metres with lattice spacing `cell` metres."""
    fa, fb = a / F32(cell), b / F32(cell)
    ia, ib = np.floor(fa), np.floor(fb)
    ta, tb = fa - ia, fb - ib
    ta, tb = ta * ta * (3 - 2 * ta), tb * tb * (3 - 2 * tb)
    ia, ib = ia.astype(np.int64), ib.astype(np.int64)
    v00, v10 = _hash(ia, ib, key), _hash(ia + 1, ib, key)
    v01, v11 = _hash(ia, ib + 1, key), _hash(ia + 1, ib + 1, key)
    return (v00 * (1 - ta) + v10 * ta) * (1 - tb) + (v01 * (1 - ta) + v11 * ta) * tb


def _fbm(a: np.ndarray, b: np.ndarray, cells: tuple[float, ...], key: int) -> np.ndarray:
    """Sum of value-noise octaves (spacings `cells`, equal weights), zero mean, about ±0.5."""
    return sum(_value_noise(a, b, c, key + 7 * n) for n, c in enumerate(cells)) / F32(len(cells)) - F32(0.5)


def _bricks(s: np.ndarray, v: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Brick bond albedo factor `(N,)`: bricks 25 × 8.5 cm (running bond), 1 cm mortar joints."""
    L, H, joint = F32(0.25), F32(0.085), F32(0.01)
    row = np.floor(v / H)
    su = s + F32(0.5) * L * np.mod(row, 2)
    col = np.floor(su / L)
    mortar = ((su - col * L) < joint) | ((v - row * H) < joint)
    shade = F32(0.7) + F32(0.6) * _hash(col.astype(np.int64), row.astype(np.int64), poly)
    return np.where(mortar, F32(1.55), shade) + F32(0.15) * _fbm(s, v, (0.02,), 11)


def _tiles(s: np.ndarray, v: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Roof tile albedo factor `(N,)`: tiles 25 × 33 cm with dark joints, a shade per tile."""
    row, col = np.floor(v / F32(0.33)), np.floor(s / F32(0.25))
    joint = ((v - row * F32(0.33)) < F32(0.03)) | ((s - col * F32(0.25)) < F32(0.015))
    shade = F32(0.75) + F32(0.5) * _hash(col.astype(np.int64), row.astype(np.int64), poly + 99991)
    return np.where(joint, F32(0.45), shade)


#: base colours (linear RGB albedo): brick, plasters, roofs (red tiles, anthracite)
BRICK = np.array([0.42, 0.17, 0.10], F32)
PLASTERS = np.array([[0.75, 0.70, 0.58], [0.62, 0.66, 0.70], [0.78, 0.62, 0.50]], F32)
ROOFS = np.array([[0.40, 0.13, 0.08], [0.16, 0.16, 0.18]], F32)
GLASS, FRAME, ASPHALT = np.array([0.05, 0.07, 0.09], F32), np.array([0.85, 0.85, 0.82], F32), F32(0.22)


class RgbRenderer:
    """Renders the RGB camera over the TIR renderer's scene (see the module docstring).

    Args:
        tir: the scene's TIR renderer (mesh, thermal scene with the window grid, ground plane).
        camera: the RGB interior orientation.
        options: rendering options (sun, PSF, noise).
        seed: seed of the sensor noise.
    """

    def __init__(self, tir: Renderer, camera: Camera, options: RgbOptions, seed: int = 0) -> None:
        self.tir, self.camera, self.options, self.seed = tir, camera, options, int(seed)
        th = tir.thermal
        n = np.cross(th.p_s, th.p_t)
        self._normals = (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)).astype(F32)
        self._material = _hash(np.asarray(th.p_building), 0, seed + 5)  # (P,) per building in [0, 1)
        el, az = np.radians(options.sun_elevation_deg), np.radians(options.sun_azimuth_deg)
        self._sun = np.array([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], F32)
        self._bearings: np.ndarray | None = None

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_bearings"] = None
        return state

    def _rays(self) -> np.ndarray:
        if self._bearings is None:
            cam = self.camera
            v, u = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
            b = cam.bearing(np.stack([u, v], axis=-1).reshape(-1, 2))
            self._bearings = np.ascontiguousarray(b, dtype=F32)
        return self._bearings

    def albedo(self, pose: Pose) -> np.ndarray:
        """Ideal shaded image `(H, W, 3)` float32 in [0, 1] (linear), no sensor effects."""
        cam, tir = self.camera, self.tir
        R = pose.R_world_from_cam.astype(F32)
        d = self._rays() @ R.T  # (N, 3) world directions
        n = len(d)
        t, label, _ = tir.hits(pose.center, d)
        occluded = label == OCCLUDER
        ground = label == GROUND
        X = (pose.center - tir.thermal.origin).astype(F32) + t[:, None] * d  # thermal-local metres
        out = np.empty((n, 3), F32)
        sky = ~ground & (label < 0)
        out[sky] = np.array([0.55, 0.70, 0.92], F32) * (F32(0.8) + F32(0.2) * d[sky, 2:3])
        ig = np.flatnonzero(ground)
        a = ASPHALT + F32(0.25) * _fbm(X[ig, 0], X[ig, 1], (0.04, 0.15, 0.6), 3)
        out[ig] = a[:, None] * (F32(0.45) + F32(0.55) * max(float(self._sun[2]), 0.0))
        on = np.flatnonzero(~ground & (label >= 0))
        if len(on):
            out[on] = self._surfaces(X[on], label[on])
        io = np.flatnonzero(~ground & occluded)
        if len(io):
            leaf = F32(0.8) + F32(0.4) * _fbm(X[io, 0], X[io, 2], (0.5, 1.5), 11)
            out[io] = np.array([0.18, 0.32, 0.12], F32) * leaf[:, None]
        return np.clip(out, 0, 1).reshape(cam.height, cam.width, 3)

    def _surfaces(self, X: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Shaded albedo `(N, 3)` of thermal-local points `X` `(N, 3)` on polygons `p` `(N,)`."""
        th = self.tir.thermal
        g = _gather_rows(th._tab, p)
        x, y, z = X[:, 0], X[:, 1], X[:, 2]
        s = x * g[0] + y * g[1] + z * g[2] - g[3]
        v = x * g[4] + y * g[5] + z * g[6] - g[7]
        wt = g[9 + 3 * th._n_sin :]
        wall = wt[11] > 0
        mat = self._material[p]
        col = np.empty((len(p), 3), F32)
        brick = wall & (mat < 0.5)
        col[brick] = BRICK * _bricks(s[brick], v[brick], p[brick])[:, None]
        pl = wall & ~brick
        k = np.minimum((mat[pl] - 0.5) * 6, 2).astype(int)
        col[pl] = PLASTERS[k] * (F32(1) + F32(0.35) * _fbm(s[pl], v[pl], (0.015, 0.05, 0.3), 5))[:, None]
        roof = ~wall
        col[roof] = ROOFS[(mat[roof] * 2).astype(int) % 2] * _tiles(s[roof], v[roof], p[roof])[:, None]
        pane, frame = self._windows(s, v, wt)
        col[frame] = FRAME
        col[pane] = GLASS * (F32(1) + F32(0.5) * _fbm(s[pane], v[pane], (0.3,), 9))[:, None]
        cos = np.abs(self._normals[p] @ self._sun)
        return col * (F32(0.4) + F32(0.6) * cos)[:, None]

    def _windows(self, s: np.ndarray, v: np.ndarray, wt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Masks `(N,)` of window panes and frames: the thermal scene's window grid."""
        o, th = self.tir.thermal.options, self.tir.thermal
        storey, pitch, s0, cols, rows, off, wall = wt[0], wt[1], wt[7], wt[8], wt[9], wt[10], wt[11]
        row = np.floor(v / storey)
        sr = s - s0
        c = np.floor(sr / pitch)
        u = sr - c * pitch - F32(0.5) * (pitch - F32(o.window_width_m))
        w = v - row * storey - F32(o.window_sill_m)
        cand = np.flatnonzero(
            (wall > 0) & (u >= 0) & (u <= o.window_width_m) & (w >= 0) & (w <= o.window_height_m)
            & (c >= 0) & (c < cols) & (row >= 0) & (row < rows)
        )  # fmt: skip
        pane, frame = np.zeros(len(s), bool), np.zeros(len(s), bool)
        if len(cand):
            idx = (off[cand] + row[cand] * cols[cand] + c[cand]).astype(np.int64)
            cand = cand[th.win_mask[idx]]
            uc, wc = u[cand], w[cand]
            edge = np.minimum(np.minimum(uc, o.window_width_m - uc), np.minimum(wc, o.window_height_m - wc))
            fr = edge < max(o.frame_width_m, 0.06)
            frame[cand[fr]] = True
            pane[cand[~fr]] = True
        return pane, frame

    def frame(self, pose: Pose, index: int) -> np.ndarray:
        """Frame `index` seen from `pose`: `(H, W, 3)` uint8 RGB (sRGB-like gamma, PSF, noise)."""
        o = self.options
        img = np.power(self.albedo(pose), F32(1 / 2.2)) * F32(255)
        if o.psf_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), o.psf_sigma_px, borderType=cv2.BORDER_REFLECT)
        if o.noise_dn > 0:
            rng = rng_for(self.seed, "rgb-noise", index)
            img = img + F32(o.noise_dn) * rng.standard_normal(img.shape, F32)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)


class RgbSynthFrames:
    """Lazy RGB frames: `frames[i]` / `load(i)` -> `(H, W, 3)` uint8, rendered on demand from the
    true RGB poses, deterministic; picklable."""

    def __init__(self, renderer: RgbRenderer, poses: list[Pose]) -> None:
        self.renderer, self.poses = renderer, tuple(poses)

    def __len__(self) -> int:
        return len(self.poses)

    def __getitem__(self, index: int) -> np.ndarray:
        i = int(index)
        if not -len(self) <= i < len(self):
            raise IndexError(f"rgb frame {index} out of range (0..{len(self) - 1})")
        i %= len(self)
        return self.renderer.frame(self.poses[i], i)

    def __iter__(self) -> Iterator[np.ndarray]:
        for i in range(len(self)):
            yield self[i]

    def load(self, index: int) -> np.ndarray:
        """Frame `index` `(H, W, 3)` uint8 RGB (what a package reader returns)."""
        return self[index]


@dataclass(frozen=True, eq=False)
class SynthRgb:
    """The RGB camera of a synthetic sequence: `frames` (lazy), `true_poses` (world), the poses
    the manifest records (`recorded_poses`, with the block's errors) and the `SecondCamera`."""

    frames: RgbSynthFrames
    true_poses: tuple[Pose, ...]
    recorded_poses: tuple[Pose, ...]
    second_camera: SecondCamera


def synth_rgb(
    tir: Renderer, true_tir_poses: list[Pose], true_mounting: Mounting, exposure_times: np.ndarray,
    o: RgbOptions, seed: int,
) -> SynthRgb:  # fmt: skip
    """The RGB camera of a sequence: its true poses on the rigid mount (exposed with the TIR
    frames, at `exposure_times` `(F,)` s on the INS clock), recorded poses with the block's
    errors, the manifest section (mounting = true TIR mounting composed with `tir_from_rgb`; frame
    positions / attitudes = the INS solution that gives the recorded poses) and lazy frames."""
    if o.width < 16 or o.height < 16 or not 1.0 < o.hfov_deg < 170.0:
        raise SynthError(f"rgb: bad image size {o.width}x{o.height} or hfov {o.hfov_deg}")
    if o.pose_source not in ("ins", "photogrammetric"):
        raise SynthError(f"rgb.pose_source must be 'ins' or 'photogrammetric', got {o.pose_source!r}")
    cam = rgb_camera(o)
    true = rgb_poses(list(true_tir_poses), o)
    recorded = perturbed(true, o, seed)
    B = body_from_cam(true_mounting)
    R_tr, c = tir_from_rgb(o)
    mounting = Mounting(
        camera_to_body=B @ R_tr, lever_arm_m=np.asarray(true_mounting.lever_arm_m, float) + B @ c
    )
    frames = []
    for i, pose in enumerate(recorded):
        pos, att = ins_from_camera(pose, mounting)
        frames.append(FrameRecord(index=i, file=f"rgb/{i:06d}.png", time=float(exposure_times[i]),
                                  position=pos, attitude_deg=att))  # fmt: skip
    sig_p, sig_a = o.position_sigma_m, o.attitude_sigma_deg
    acc = Accuracy(np.full(3, sig_p), np.full(3, sig_a)) if sig_p > 0 and sig_a > 0 else None
    second = SecondCamera(camera=cam, mounting=mounting, frames=tuple(frames), channels=3,
                          pose_source=o.pose_source, accuracy=acc)  # fmt: skip
    renderer = RgbRenderer(tir, cam, o, seed)
    return SynthRgb(RgbSynthFrames(renderer, true), tuple(true), tuple(recorded), second)

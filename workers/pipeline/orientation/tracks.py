"""Feature tracks through a frame sequence, on the model's surfaces (tie points for the bundle).

In: a `Camera`, frames in recording order with their images `(H, W)` float32 (physical values),
a pose per frame (the calibrated GNSS/INS priors: tens of pixels off frame by frame), a
`RayCaster` over the building model. Out: `Tracks`: every track's image observations
`(frame, u, v)` and the model plane its point lies on (of the polygon its first view's ray meets).

Why: consecutive TIR frames of a drive overlap by 90 %; a facade point seen in ten frames ties
their poses together far more precisely than GNSS does (0.2 m of white noise is 15 px at 11 m),
and its lying on a model plane ties the block to the model (Hoegner & Stilla, method 2).

Detection: the smaller eigenvalue of the structure tensor of the float frame (gradients in
physical units, Gaussian window) must reach `min_texture_ratio` × the frame's median, a
unit-free floor of noise and fixed-pattern stripes: weaker points drift on the pattern, which
moves with the sensor, not with the scene. Points whose rays and the rays `boundary_px` around
them do not all meet one model polygon (occlusion boundaries, sky, ground) are not tracked.

Tracking, frame k−1 to k:
1. prediction: each track's model point projected with pose k;
2. coarse: pyramidal Lucas-Kanade (OpenCV) on an 8-bit high-pass copy of the frames (the image
   minus its Gaussian blur, one gain for the sequence: translation-invariant, unlike CLAHE tiles
   or a stretch whose range the cold sky takes), from the prediction, with a forward-backward
   check;
3. fine: Lucas-Kanade on the float frames against the track's FIRST view (no drift along the
   track), the template warped by the plane-induced affine map from the first view to frame k
   (perspective changes by degrees between views at close range); the patch means are removed
   (a brightness offset); accepted when the zero-mean normalised correlation reaches `min_ncc`;
4. RANSAC of the essential matrix between frames k−1 and k removes what moved otherwise.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.track_frames import (
    TrackerFrames,
    TrackOptions,
    in_free_cells,
    texture_strength,
)

__all__ = ["TrackOptions", "TrackerFrames", "Tracks", "plane_affine", "texture_strength", "track_sequence"]


@dataclass(frozen=True, eq=False)
class Tracks:
    """Feature tracks (see the module docstring).

    Attributes:
        track: `(M,)` int track index of each observation.
        frame: `(M,)` int frame index of each observation.
        uv: `(M, 2)` float64 pixel coordinates (pixel centres at integers).
        point: `(T, 3)` world point of each track: its first view's ray on the model, or where an
            adjustment put it.
        normal: `(T, 3)` unit normal of the model plane the point lies on (world).
        offset: `(T,)` the model plane: `normal · X = offset` (metres); None: through `point`.
    """

    track: np.ndarray
    frame: np.ndarray
    uv: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    offset: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.offset is None:
            object.__setattr__(self, "offset", np.sum(self.normal * self.point, axis=1))

    @classmethod
    def empty(cls) -> Tracks:
        """No tracks."""
        z3 = np.zeros((0, 3))
        return cls(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 2)), z3, z3, np.zeros(0))

    def subset(self, keep: np.ndarray) -> Tracks:
        """The observations `keep` `(M,)` bool; tracks left with fewer than 2 observations (which
        tie nothing) are dropped and the rest renumbered."""
        t = self.track[keep]
        alive = np.bincount(t, minlength=self.n_tracks) >= 2
        m = alive[t]
        new_id = np.cumsum(alive) - 1
        return Tracks(new_id[t[m]], self.frame[keep][m], self.uv[keep][m], self.point[alive],
                      self.normal[alive], np.asarray(self.offset)[alive])

    def with_points(self, points: np.ndarray) -> Tracks:
        """The same tracks with their points at `points` `(T, 3)` (the model planes stay)."""
        return Tracks(self.track, self.frame, self.uv, np.asarray(points), self.normal, self.offset)

    @staticmethod
    def concat(parts: Sequence[Tracks]) -> Tracks:
        """One `Tracks` of several, track ids made unique."""
        if not parts:
            return Tracks.empty()
        offs = np.cumsum([0] + [p.n_tracks for p in parts[:-1]])
        return Tracks(
            track=np.concatenate([p.track + o for p, o in zip(parts, offs, strict=True)]),
            frame=np.concatenate([p.frame for p in parts]),
            uv=np.concatenate([p.uv for p in parts]),
            point=np.concatenate([p.point for p in parts]),
            normal=np.concatenate([p.normal for p in parts]),
            offset=np.concatenate([np.asarray(p.offset) for p in parts]),
        )

    @property
    def n_tracks(self) -> int:
        """Number of tracks."""
        return len(self.point)

    def lengths(self) -> np.ndarray:
        """`(T,)` observations per track."""
        return np.bincount(self.track, minlength=self.n_tracks)


def _ray_points(camera: Camera, raycaster: RayCaster, pose: Pose, uv: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays of pixels `uv` `(N, 2)` from `pose` on the model -> (points `(N, 3)`, polygon `(N,)`
    (-1: miss), unit normals `(N, 3)` facing the camera)."""
    d = camera.bearing(uv) @ pose.R_world_from_cam.T
    hits = raycaster.cast(np.broadcast_to(pose.center, d.shape).copy(), d)
    t = np.where(hits.hit, hits.t, 0.0)
    n = hits.normal * np.where(np.sum(hits.normal * d, axis=1) > 0, -1.0, 1.0)[:, None]
    return pose.center + t[:, None] * d, hits.polygon, n


def _on_surface(camera: Camera, raycaster: RayCaster, pose: Pose, uv: np.ndarray,
                options: TrackOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Which pixels `uv` `(N, 2)` lie inside one model polygon (their ray and the four rays
    `boundary_px` around it meet the same polygon, not at grazing incidence) -> (ok `(N,)`,
    points, polygons, normals). The four boundary rays are cast, in one call, only for the
    pixels whose own ray passed."""
    d = camera.bearing(uv) @ pose.R_world_from_cam.T
    hits = raycaster.cast(np.broadcast_to(pose.center, d.shape).copy(), d)
    t = np.where(hits.hit, hits.t, 0.0)
    n = hits.normal * np.where(np.sum(hits.normal * d, axis=1) > 0, -1.0, 1.0)[:, None]
    X, poly = pose.center + t[:, None] * d, hits.polygon
    ok = (poly >= 0) & (np.abs(np.sum(n * d, axis=1)) >= options.min_incidence)
    idx = np.flatnonzero(ok)
    if len(idx):
        b = options.boundary_px
        offs = np.array([[b, 0.0], [-b, 0.0], [0.0, b], [0.0, -b]])
        _, p2, _ = _ray_points(camera, raycaster, pose, (uv[idx][None] + offs[:, None]).reshape(-1, 2))
        ok[idx] = np.all(p2.reshape(4, -1) == poly[idx], axis=0)
    return ok, X, poly, n


def _plane_rays(camera: Camera, pose: Pose, uv: np.ndarray, step: float = 1.0) -> np.ndarray:
    """World directions `(N, 5, 3)` of the rays of view `pose` through pixels `uv` `(N, 2)` and
    through `uv ± step` along u and v (order: centre, +u, −u, +v, −v)."""
    offs = np.array([[0.0, 0.0], [step, 0.0], [-step, 0.0], [0.0, step], [0.0, -step]])
    px = (uv[:, None, :] + offs[None]).reshape(-1, 2)
    return (camera.bearing(px) @ pose.R_world_from_cam.T).reshape(len(uv), 5, 3)


def _plane_map(camera: Camera, origin: np.ndarray, rays: np.ndarray, X0: np.ndarray, normal: np.ndarray,
               pose: Pose) -> np.ndarray:
    """Rays `(N, K, 3)` (world) from `origin` `(N, 3)` meet the planes through `X0` `(N, 3)` with
    `normal` `(N, 3)`; the points projected with `pose` -> pixels `(N, K, 2)` (NaN behind it)."""
    den = np.einsum("nj,nkj->nk", normal, rays)
    s = np.sum(normal * (X0 - origin), axis=1)[:, None] / np.where(np.abs(den) > 1e-9, den, np.nan)
    X = origin[:, None, :] + s[..., None] * rays
    uv, z = pose.project(camera, X.reshape(-1, 3))
    uv[~(z > 0)] = np.nan
    return uv.reshape(*rays.shape[:2], 2)


def plane_affine(camera: Camera, pa: Pose, pb: Pose, uv: np.ndarray, X0: np.ndarray,
                 normal: np.ndarray, step: float = 1.0) -> np.ndarray:
    """Local affine maps `(N, 2, 2)` (columns ∂uv_b/∂u_a, ∂uv_b/∂v_a) of the plane-induced
    mapping from view a to view b at pixels `uv` `(N, 2)` of view a (central differences of
    `step` px)."""
    rays = _plane_rays(camera, pa, uv, step)
    return _affine(_plane_map(camera, np.broadcast_to(pa.center, X0.shape), rays, X0, normal, pb), step)


def _affine(mapped: np.ndarray, step: float) -> np.ndarray:
    """Affine maps `(N, 2, 2)` from the mapped `(N, 5, 2)` centre, +u, −u, +v, −v pixels."""
    return np.stack([(mapped[:, 1] - mapped[:, 2]) / (2 * step), (mapped[:, 3] - mapped[:, 4]) / (2 * step)],
                    axis=2)


def _window(options: TrackOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Offsets `du`, `dv` `(K,)` of the fine window and its Gaussian weights `(K,)` (sum 1)."""
    h = options.fine_half_window_px
    k = np.arange(-h, h + 1, dtype=np.float64)
    du, dv = (g.ravel() for g in np.meshgrid(k, k))
    w = np.exp(-0.5 * (du * du + dv * dv) / (h / 2.0) ** 2)
    return du, dv, w / w.sum()


def _templates(image: np.ndarray, uv: np.ndarray, options: TrackOptions) -> np.ndarray:
    """Zero-mean (Gaussian-weighted) templates `(N, K)` of `image` around pixels `uv` `(N, 2)`."""
    du, dv, w = _window(options)
    T = cv2.remap(image, (uv[:, 0:1] + du).astype(np.float32), (uv[:, 1:2] + dv).astype(np.float32),
                  cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
    return T - (T * w).sum(axis=1, keepdims=True)


def _fine(T: np.ndarray, stack: np.ndarray, uv0: np.ndarray, A: np.ndarray,
          options: TrackOptions) -> tuple[np.ndarray, np.ndarray]:
    """Lucas-Kanade of the translation of zero-mean templates `T` `(N, K)` (`_templates`), mapped
    by the affine maps `A` `(N, 2, 2)`, into the frame whose values and gradients are `stack`
    `(H, W, 3)` float32, from `uv0` `(N, 2)`; the patch means are removed (brightness offset).
    Returns (positions `(N, 2)`, zero-mean normalised correlation `(N,)`)."""
    du, dv, w = _window(options)
    ou = A[:, 0, 0:1] * du + A[:, 0, 1:2] * dv
    ov = A[:, 1, 0:1] * du + A[:, 1, 1:2] * dv
    p = uv0.astype(np.float64).copy()
    for _ in range(options.fine_iterations):
        ub = (p[:, 0:1] + ou).astype(np.float32)
        vb = (p[:, 1:2] + ov).astype(np.float32)
        s = cv2.remap(stack, ub, vb, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float64)
        val, Gx, Gy = s[..., 0], s[..., 1], s[..., 2]
        e = val - (val * w).sum(axis=1, keepdims=True) - T
        Gx = Gx - (Gx * w).sum(axis=1, keepdims=True)
        Gy = Gy - (Gy * w).sum(axis=1, keepdims=True)
        a, b, c = (w * Gx * Gx).sum(1), (w * Gx * Gy).sum(1), (w * Gy * Gy).sum(1)
        r1, r2 = -(w * Gx * e).sum(1), -(w * Gy * e).sum(1)
        det = np.maximum(a * c - b * b, 1e-20)
        step = np.stack([(c * r1 - b * r2) / det, (a * r2 - b * r1) / det], axis=1)
        step = np.clip(step, -1.0, 1.0)
        p += step
        if np.max(np.abs(step)) < 0.005:
            break
    ub = (p[:, 0:1] + ou).astype(np.float32)
    vb = (p[:, 1:2] + ov).astype(np.float32)
    val = cv2.remap(stack[..., 0], ub, vb, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    val = val.astype(np.float64)
    val -= (val * w).sum(axis=1, keepdims=True)
    ncc = (w * val * T).sum(1) / np.sqrt(np.maximum((w * val * val).sum(1) * (w * T * T).sum(1), 1e-30))
    return p, ncc


@dataclass(eq=False)
class _Active:
    """The tracks being followed: ids `(N,)`, last positions `(N, 2)`, views so far `(N,)`, their
    first view's centre `(N, 3)` and rays `(N, 5, 3)` (`_plane_rays`), model point and plane
    normal `(N, 3)`, template `(N, K)`."""

    ids: np.ndarray
    last_uv: np.ndarray
    n_obs: np.ndarray
    origin: np.ndarray
    rays: np.ndarray
    X0: np.ndarray
    normal: np.ndarray
    template: np.ndarray

    @classmethod
    def empty(cls, options: TrackOptions) -> _Active:
        k = (2 * options.fine_half_window_px + 1) ** 2
        z3 = np.zeros((0, 3))
        return cls(np.zeros(0, int), np.zeros((0, 2)), np.zeros(0, int), z3, np.zeros((0, 5, 3)), z3, z3,
                   np.zeros((0, k)))

    def select(self, m: np.ndarray) -> _Active:
        return _Active(self.ids[m], self.last_uv[m], self.n_obs[m], self.origin[m], self.rays[m], self.X0[m],
                       self.normal[m], self.template[m])

    def add(self, ids: np.ndarray, uv: np.ndarray, center: np.ndarray, rays: np.ndarray, X0: np.ndarray,
            normal: np.ndarray, template: np.ndarray) -> _Active:
        n = len(ids)
        return _Active(np.concatenate([self.ids, ids]), np.concatenate([self.last_uv, uv]),
                       np.concatenate([self.n_obs, np.ones(n, int)]),
                       np.concatenate([self.origin, np.broadcast_to(center, (n, 3))]),
                       np.concatenate([self.rays, rays]), np.concatenate([self.X0, X0]),
                       np.concatenate([self.normal, normal]), np.concatenate([self.template, template]))


def track_sequence(
    camera: Camera,
    frames: Sequence[int],
    images: Mapping[int, np.ndarray],
    poses: Mapping[int, Pose],
    raycaster: RayCaster,
    options: TrackOptions = TrackOptions(),
    prepared: TrackerFrames | None = None,
) -> Tracks:
    """Tracks through `frames` (recording order) on the model's surfaces (module docstring).

    Args:
        camera: interior orientation.
        frames: frame indices in recording order (consecutive entries are tracked against each other).
        images: `(H, W)` float32 physical values per frame.
        poses: camera pose per frame (world = model CRS): the relative motion of consecutive
            frames predicted to within the coarse tracker's reach (about `lk_window_px` ×
            2^`lk_levels` / 2 px), the model planes found by the rays.
        raycaster: the model the points lie on.
        options: parameters.
        prepared: the frames' high-pass copies and texture peaks (`TrackerFrames` of these
            `frames`, `images` and `options`), kept from an earlier tracking of the block; None:
            made here.
    """
    frames = list(frames)
    H, W = camera.height, camera.width
    rows, cols = (H + options.cell_px - 1) // options.cell_px, (W + options.cell_px - 1) // options.cell_px
    obs_t: list[np.ndarray] = []
    obs_f: list[np.ndarray] = []
    obs_uv: list[np.ndarray] = []
    pts: list[np.ndarray] = []
    nrms: list[np.ndarray] = []
    # one gain for the high-pass copies (translation-invariant tracking input), set by `prepared`
    prep = prepared if prepared is not None else TrackerFrames(frames, images, options)
    act = _Active.empty(options)
    prev8 = None
    prev = None
    for f in frames:
        img = prep.image(f)
        img8 = prep.highpass8(f)
        if len(act.ids) and prev is not None and prev8 is not None:
            new_uv = _follow(camera, act, poses[prev], poses[f], prev8, img8, img, options)
            _drop_essential_outliers(camera, act.last_uv, new_uv, options)
            cont = np.isfinite(new_uv).all(axis=1)
            if cont.any():
                obs_t.append(act.ids[cont])
                obs_f.append(np.full(int(cont.sum()), f))
                obs_uv.append(new_uv[cont])
            act.last_uv = new_uv
            act.n_obs = act.n_obs + 1
            act = act.select(cont & (act.n_obs < options.max_length))
        # new tracks in free cells
        cand, X, nrm = _new_points(camera, raycaster, poses[f], prep.peaks(f), act, (rows, cols), options)
        if len(cand):
            ids = np.arange(len(pts), len(pts) + len(cand))
            pts.extend(X)
            nrms.extend(nrm)
            obs_t.append(ids)
            obs_f.append(np.full(len(ids), f))
            obs_uv.append(cand)
            act = act.add(ids, cand, poses[f].center, _plane_rays(camera, poses[f], cand), X, nrm,
                          _templates(img, cand, options))
        prev8, prev = img8, f
    if not pts:
        return Tracks.empty()
    every = Tracks(np.concatenate(obs_t), np.concatenate(obs_f), np.concatenate(obs_uv), np.array(pts),
                   np.array(nrms))
    return every.subset(np.ones(len(every.track), bool))


def _follow(camera: Camera, act: _Active, pose_prev: Pose, pose: Pose, prev8: np.ndarray, img8: np.ndarray,
            img: np.ndarray, options: TrackOptions) -> np.ndarray:
    """The active tracks followed from the previous frame into this one (`pose`, high-pass copy
    `img8`, float frame `img`): prediction from the model points, coarse pyramidal LK with a
    forward-backward check, fine LK against each track's first view warped by its plane's affine
    map, accepted by correlation (module docstring, steps 1-3). -> `(N, 2)` positions, NaN where a
    track was lost."""
    lk = {"winSize": (options.lk_window_px, options.lk_window_px), "maxLevel": options.lk_levels}
    mapped = _plane_map(camera, act.origin, act.rays, act.X0, act.normal, pose)
    pred = mapped[:, 0]
    pred_prev, _ = pose_prev.project(camera, act.X0)
    ok = np.isfinite(mapped).all(axis=(1, 2)) & camera.in_image(pred, options.border_px / 2)
    ok &= np.isfinite(pred_prev).all(axis=1)
    new_uv = np.full((len(act.ids), 2), np.nan)
    if ok.any():
        p0 = act.last_uv[ok].astype(np.float32)[:, None]
        guess = (act.last_uv[ok] + (pred[ok] - pred_prev[ok])).astype(np.float32)[:, None]
        p1, st, _ = cv2.calcOpticalFlowPyrLK(prev8, img8, p0, guess.copy(),
                                             flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        pb, st2, _ = cv2.calcOpticalFlowPyrLK(img8, prev8, p1, p0.copy(),
                                              flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        good = (st[:, 0] == 1) & (st2[:, 0] == 1) & \
            (np.linalg.norm(pb[:, 0] - p0[:, 0], axis=1) < options.fb_tolerance_px)
        idx = np.flatnonzero(ok)[good]
        if len(idx):
            coarse = p1[good, 0].astype(np.float64)
            A = _affine(mapped[idx], 1.0)
            stack = cv2.merge([img, cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=1, scale=0.5),
                               cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=1, scale=0.5)])
            fine, ncc = _fine(act.template[idx], stack, coarse, A, options)
            keep = (ncc >= options.min_ncc) & \
                (np.linalg.norm(fine - coarse, axis=1) <= options.fine_max_shift_px) & \
                camera.in_image(fine, 2.0)
            new_uv[idx[keep]] = fine[keep]
    return new_uv


def _drop_essential_outliers(camera: Camera, last_uv: np.ndarray, new_uv: np.ndarray,
                             options: TrackOptions) -> None:
    """RANSAC of the essential matrix between the previous frame (`last_uv` `(N, 2)`) and this one
    (`new_uv` `(N, 2)`, NaN where lost): outliers set to NaN in `new_uv` (module docstring, step 4)."""
    m = np.isfinite(new_uv).all(axis=1)
    if m.sum() >= 8:
        xa = camera.normalized_from_pixel(last_uv[m])
        xb = camera.normalized_from_pixel(new_uv[m])
        _, inl = cv2.findEssentialMat(xa, xb, np.eye(3), cv2.RANSAC, 0.999,
                                      options.ransac_px / camera.fx)
        if inl is not None:
            new_uv[np.flatnonzero(m)[inl.ravel() == 0]] = np.nan


def _new_points(camera: Camera, raycaster: RayCaster, pose: Pose, peaks: np.ndarray, act: _Active,
                grid: tuple[int, int], options: TrackOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """New tracks for the frame: its texture peaks `peaks` `(K, 2)` (`TrackerFrames.peaks`) in the
    cells of `grid` (rows, cols) no active track occupies (`in_free_cells`), kept where they lie on
    one model polygon (`_on_surface`) -> image points `(K, 2)`, their model points `(K, 3)` and
    plane normals `(K, 3)`."""
    rows, cols = grid
    occupied = np.zeros((rows, cols), bool)
    if len(act.ids):
        c = np.clip((act.last_uv // options.cell_px).astype(int), 0, [cols - 1, rows - 1])
        occupied[c[:, 1], c[:, 0]] = True
    cand = in_free_cells(peaks, occupied, options.cell_px, options.max_tracks - len(act.ids))
    X = nrm = np.zeros((0, 3))
    if len(cand):
        ok, X, _, nrm = _on_surface(camera, raycaster, pose, cand, options)
        cand, X, nrm = cand[ok], X[ok], nrm[ok]
    return cand, X, nrm

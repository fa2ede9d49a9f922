"""Image-to-image tie points of consecutive frames and their epipolar residuals.

In: a `Camera`, frames `(H, W)` float32 (physical values), optional pixel boxes of the building in
each frame. Out: `TiePair`s (matched points of two frames as undistorted normalised coordinates),
and the Sampson distance of each tie point for two poses (pixels) with its Jacobian with respect
to the two pose corrections `δ = (ω_cam, dC_world)` (`coregister_geometry`); and the transfer
of a tie point through the building model: the ray of frame a meets the model surface (a plane
per point, found by ray casting), the point is projected into frame b (pixels).

Why: the true trajectory is smooth and consecutive frames overlap strongly, so image-to-image tie
points fix the relative orientation of neighbouring frames far better than GNSS white noise does
(Hoegner & Stilla: relative orientation inside the adjustment against the model). The epipolar
constraint has no scale, and with a close planar facade and a short baseline the relative rotation
and the translation direction are nearly ambiguous (bas-relief); transferring the tie points over
the model's planes (a plane-induced homography: the model inside the adjustment) fixes both.

Detection: Shi-Tomasi corners on a contrast-stretched 8-bit copy (percentiles over the building's
box, CLAHE), pyramidal Lucas-Kanade tracking with a forward-backward check, RANSAC of the
essential matrix on normalised coordinates; at most `max_points` per pair.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from workers.pipeline.camera import Camera
from workers.pipeline.coregister_geometry import apply_delta
from workers.pipeline.pose import Pose
from workers.pipeline.raycast import RayCaster

__all__ = [
    "TiePair", "TiePointOptions", "model_points", "sampson_jacobian", "sampson_px", "stretch8", "tie_pairs",
    "transfer_jacobian", "transfer_px",
]


@dataclass(frozen=True)
class TiePointOptions:
    """Parameters of tie-point detection and matching (pixels)."""

    # frame pairs (k, k + gap) of the ordered frame list for each gap
    gaps: tuple[int, ...] = (1, 2)
    # Shi-Tomasi corners: at most this many, quality level, minimum distance, block size
    max_corners: int = 200
    quality: float = 0.01
    min_distance_px: float = 8.0
    block_size: int = 7
    # pyramidal LK: window, pyramid levels, forward-backward tolerance
    window_px: int = 21
    levels: int = 3
    fb_tolerance_px: float = 0.5
    # RANSAC of the essential matrix: threshold (pixels), minimum inliers, at most this many kept
    ransac_px: float = 1.0
    min_points: int = 20
    max_points: int = 100
    # contrast stretch: percentiles over the building box, CLAHE clip limit
    percentiles: tuple[float, float] = (1.0, 99.0)
    clahe_clip: float = 2.0


@dataclass(frozen=True, eq=False)
class TiePair:
    """Tie points of frames `a` and `b`: `xa`, `xb` `(N, 2)` undistorted normalised coordinates."""

    a: int
    b: int
    xa: np.ndarray
    xb: np.ndarray


def stretch8(image: np.ndarray, box: tuple[int, int, int, int] | None = None,
             options: TiePointOptions = TiePointOptions()) -> np.ndarray:
    """Frame `(H, W)` float -> `(H, W)` uint8, stretched over the percentiles of the pixels in `box`
    `(u0, v0, u1, v1)` (the building, not the sky; whole frame when None), then CLAHE."""
    img = np.nan_to_num(np.asarray(image, dtype=np.float32))
    ref = img if box is None else img[box[1]:box[3], box[0]:box[2]]
    if ref.size == 0:
        ref = img
    lo, hi = np.percentile(ref, options.percentiles)
    u8 = np.clip((img - lo) * (255.0 / max(float(hi - lo), 1e-6)), 0, 255).astype(np.uint8)
    return cv2.createCLAHE(options.clahe_clip, (8, 8)).apply(u8)


def _predict(camera: Camera, raycaster: RayCaster, pa: Pose, pb: Pose, uv: np.ndarray) -> np.ndarray:
    """Pixels `(N, 2)` of frame a predicted in frame b: rays from `pa` onto the model (misses: far
    away), projected with `pb`; points behind b keep their position."""
    x = camera.normalized_from_pixel(uv)
    X, _, ok = model_points(raycaster, pa, x, min_cos=0.0)
    d = np.c_[x, np.ones(len(x))] @ pa.R_world_from_cam.T
    X = np.where(ok[:, None], X, pa.center + 1e4 * d / np.linalg.norm(d, axis=1, keepdims=True))
    out, z = pb.project(camera, X)
    bad = ~(np.isfinite(out).all(axis=1) & (z > 0))
    out[bad] = uv[bad]
    return out


def _match(camera: Camera, a8: np.ndarray, b8: np.ndarray, mask: np.ndarray | None,
           o: TiePointOptions, guess: tuple[RayCaster, Pose, Pose] | None = None,
           ) -> tuple[np.ndarray, np.ndarray] | None:
    """Tracked and RANSAC-filtered points of two 8-bit frames -> (xa, xb) normalised, or None.
    `guess` `(raycaster, pose a, pose b)`: the tracking starts from the positions predicted over
    the model (large image motion between frames: turns, vibration)."""
    p0 = cv2.goodFeaturesToTrack(a8, o.max_corners, o.quality, o.min_distance_px, mask=mask,
                                 blockSize=o.block_size)
    if p0 is None or len(p0) < o.min_points:
        return None
    lk = {"winSize": (o.window_px, o.window_px), "maxLevel": o.levels}
    if guess is not None:
        init = _predict(camera, *guess, p0[:, 0].astype(np.float64)).astype(np.float32)[:, None]
        p1, st, _ = cv2.calcOpticalFlowPyrLK(a8, b8, p0, init.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
                                             **lk)
    else:
        p1, st, _ = cv2.calcOpticalFlowPyrLK(a8, b8, p0, None, **lk)
    pb, st2, _ = cv2.calcOpticalFlowPyrLK(b8, a8, p1, None, **lk)
    ok = (st[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm(pb - p0, axis=2)[:, 0] < o.fb_tolerance_px)
    if ok.sum() < o.min_points:
        return None
    xa = camera.normalized_from_pixel(p0[ok, 0].astype(np.float64))
    xb = camera.normalized_from_pixel(p1[ok, 0].astype(np.float64))
    E, m = cv2.findEssentialMat(xa, xb, np.eye(3), cv2.RANSAC, 0.999, o.ransac_px / camera.fx)
    if E is None or m is None:
        return None
    m = m.ravel().astype(bool)
    if m.sum() < o.min_points:
        return None
    xa, xb = xa[m], xb[m]
    if len(xa) > o.max_points:
        k = np.linspace(0, len(xa) - 1, o.max_points).round().astype(int)
        xa, xb = xa[k], xb[k]
    return xa, xb


def tie_pairs(
    camera: Camera,
    images: Mapping[int, np.ndarray],
    frames: Sequence[int],
    boxes: Mapping[int, tuple[int, int, int, int]] | None = None,
    options: TiePointOptions = TiePointOptions(),
    raycaster: RayCaster | None = None,
    poses: Mapping[int, Pose] | None = None,
) -> list[TiePair]:
    """Tie points between frames `k` and `k + gap` of the ordered `frames` for each gap of
    `options.gaps`; pairs with too few consistent points are left out. `boxes`: pixel boxes of the
    building per frame (stretch and detection region); `raycaster` and `poses` (priors): tracking
    starts from the positions predicted over the model."""
    boxes = boxes or {}
    u8 = {i: stretch8(images[i], boxes.get(i), options) for i in frames}
    masks = {}
    for i in frames:
        box = boxes.get(i)
        if box is not None:
            m = np.zeros(u8[i].shape, np.uint8)
            m[box[1]:box[3], box[0]:box[2]] = 255
            masks[i] = m
    out = []
    for gap in options.gaps:
        for k in range(len(frames) - gap):
            a, b = frames[k], frames[k + gap]
            guess = None if raycaster is None or poses is None else (raycaster, poses[a], poses[b])
            got = _match(camera, u8[a], u8[b], masks.get(a), options, guess)
            if got is not None:
                out.append(TiePair(a, b, *got))
    return out


def _essential(pa: Pose, pb: Pose) -> np.ndarray:
    """`(3, 3)` essential matrix with `x_bᵀ E x_a = 0` for normalised coordinates of the two poses."""
    R = pb.R_world_from_cam.T @ pa.R_world_from_cam
    t = pb.R_world_from_cam.T @ (pa.center - pb.center)
    n = max(float(np.linalg.norm(t)), 1e-9)
    t = t / n
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return tx @ R


def sampson_px(camera: Camera, pa: Pose, pb: Pose, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Sampson distances `(N,)` (pixels, signed) of tie points `xa`, `xb` `(N, 2)` (normalised) for
    poses `pa`, `pb` (the baseline's length does not matter)."""
    E = _essential(pa, pb)
    ha = np.c_[xa, np.ones(len(xa))]
    hb = np.c_[xb, np.ones(len(xb))]
    Ex = ha @ E.T
    Etx = hb @ E
    num = np.sum(hb * Ex, axis=1)
    den = np.sqrt(Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2)
    return num / np.maximum(den, 1e-12) * camera.fx


def sampson_jacobian(camera: Camera, pa: Pose, pb: Pose, xa: np.ndarray,
                     xb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sampson distances `(N,)` px and their Jacobian `(N, 12)` with respect to the corrections of
    `pa` then `pb` (`(ω, dC)` each; central differences)."""
    r = sampson_px(camera, pa, pb, xa, xb)
    J = np.empty((len(xa), 12))
    steps = np.array([1e-5] * 3 + [1e-3] * 3)
    for k in range(12):
        d = np.zeros(6)
        d[k % 6] = steps[k % 6]
        if k < 6:
            rp = sampson_px(camera, apply_delta(pa, d), pb, xa, xb)
            rm = sampson_px(camera, apply_delta(pa, -d), pb, xa, xb)
        else:
            rp = sampson_px(camera, pa, apply_delta(pb, d), xa, xb)
            rm = sampson_px(camera, pa, apply_delta(pb, -d), xa, xb)
        J[:, k] = (rp - rm) / (2 * steps[k % 6])
    return r, J


def model_points(raycaster: RayCaster, pose: Pose, x: np.ndarray,
                 min_cos: float = 0.2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays of normalised points `x` `(N, 2)` of a frame at `pose` cast onto the model -> (points
    `(N, 3)` world, unit plane normals `(N, 3)`, hit `(N,)` bool; misses and grazing rays, with
    |cos| of ray and normal below `min_cos`, are False)."""
    d = np.c_[x, np.ones(len(x))] @ pose.R_world_from_cam.T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hits = raycaster.cast(np.broadcast_to(pose.center, d.shape).copy(), d)
    ok = np.isfinite(hits.t) & (np.abs(np.sum(hits.normal * d, axis=1)) >= min_cos)
    X = pose.center + np.where(ok, hits.t, 0.0)[:, None] * d
    return X, hits.normal, ok


def _transfer_batch(camera: Camera, Ra: np.ndarray, Ca: np.ndarray, Rb: np.ndarray, Cb: np.ndarray,
                    xa: np.ndarray, xb: np.ndarray, X0: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """`transfer_px` for K pose pairs at once: rotations `(K, 3, 3)`, centres `(K, 3)` -> `(K, N, 2)`."""
    h = np.c_[xa, np.ones(len(xa))]
    d = np.einsum("kij,nj->kni", Ra, h)
    s = np.sum(normal[None] * (X0[None] - Ca[:, None]), axis=2) / np.sum(normal[None] * d, axis=2)
    X = Ca[:, None] + s[..., None] * d
    xc = np.einsum("kni,kij->knj", X - Cb[:, None], Rb)
    z = np.maximum(xc[..., 2:], 1e-6)
    return (xc[..., :2] / z - xb[None]) * camera.fx


def transfer_px(camera: Camera, pa: Pose, pb: Pose, xa: np.ndarray, xb: np.ndarray, X0: np.ndarray,
                normal: np.ndarray) -> np.ndarray:
    """Residuals `(N, 2)` (pixels, normalised × fx) of the tie points `xb` `(N, 2)` and the rays of
    `xa` from `pa` intersected with the planes through `X0` `(N, 3)` with `normal` `(N, 3)` and
    projected into `pb`."""
    return _transfer_batch(camera, pa.R_world_from_cam[None], pa.center[None], pb.R_world_from_cam[None],
                           pb.center[None], xa, xb, X0, normal)[0]


def transfer_jacobian(camera: Camera, pa: Pose, pb: Pose, xa: np.ndarray, xb: np.ndarray, X0: np.ndarray,
                      normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`transfer_px` `(N, 2)` and its Jacobian `(N, 2, 12)` with respect to the corrections of `pa`
    then `pb` (central differences, all 25 evaluations in one batch)."""
    steps = np.array([1e-5] * 3 + [1e-3] * 3)
    Ra, Ca, Rb, Cb = [pa.R_world_from_cam], [pa.center], [pb.R_world_from_cam], [pb.center]
    for k in range(12):
        for sign in (1.0, -1.0):
            d = np.zeros(6)
            d[k % 6] = sign * steps[k % 6]
            qa = apply_delta(pa, d) if k < 6 else pa
            qb = apply_delta(pb, d) if k >= 6 else pb
            Ra.append(qa.R_world_from_cam)
            Ca.append(qa.center)
            Rb.append(qb.R_world_from_cam)
            Cb.append(qb.center)
    out = _transfer_batch(camera, np.array(Ra), np.array(Ca), np.array(Rb), np.array(Cb), xa, xb, X0, normal)
    J = (out[1::2] - out[2::2]) / (2 * np.tile(steps, 2)[:, None, None])
    return out[0], np.transpose(J, (1, 2, 0))

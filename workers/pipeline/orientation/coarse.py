"""Coarse, correspondence-free search of orientation: edge-distance scores over image shifts.

In: a `Camera`, a pose (or the poses of several frames), the visible wireframe, the frame's
`ImageFeatures` (truncated distance transforms of a strong-edge map) and `FrameFitOptions`
(`fit_options`). Out: score maps over candidate poses (depth offsets along the optical axis,
rolls about it) and image shifts (`cv2.matchTemplate` on a pyramid level), and the corrected
pose: an image shift becomes a camera rotation plus a translation across the optical axis, split
by their a-priori standard deviations.

- one frame (`coarse_search`, the first stage of `frame_fit.fit_frame`): the minimum of its own
  score map;
- several frames of a building at once (`joint_coarse`, `apply_coarse`; `building` step 2): the
  GNSS/INS errors of consecutive frames share a constant boresight misalignment and a slowly
  drifting position bias, so the score maps of all frames are averaged and the minimum is the
  common correction, found where single frames are ambiguous (a neighbour's outline, a window
  row).
"""

from __future__ import annotations

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import so3_exp
from workers.pipeline.orientation.features import ImageFeatures
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.wireframe import VisibleWireframe

__all__ = [
    "apply_coarse",
    "candidate_pose",
    "coarse_scores",
    "coarse_search",
    "joint_coarse",
    "shift_penalty",
    "shift_pose",
    "shift_rotation",
]


def candidate_pose(pose: Pose, depth_m: float, roll_rad: float = 0.0) -> Pose:
    """`pose` moved `depth_m` along its optical axis and rolled by `roll_rad` about it."""
    R = pose.R_world_from_cam
    return Pose(R @ so3_exp(np.array([0.0, 0.0, roll_rad])), pose.center + depth_m * R[:, 2])


def coarse_scores(
    camera: Camera, pose: Pose, vis: VisibleWireframe, feats: ImageFeatures, depths_m: np.ndarray,
    options: FrameFitOptions, rolls_rad: np.ndarray | None = None,
) -> np.ndarray:
    """Mean truncated edge distance (level pixels) of the projected samples for every candidate
    (depth offset along the optical axis `depths_m` `(D,)` × roll about it `rolls_rad` `(Q,)`,
    default 0) and image shift -> `(D·Q, 2r+1, 2r+1)` (depth-major), r = coarse radius in level
    pixels, shift `(j - r, i - r)` level pixels at `[c, i, j]`; the truncation value where a
    candidate cannot be scored. Computed with `cv2.matchTemplate` on level `coarse_level`."""
    s = options.coarse_level
    R_lev = int(np.ceil(options.coarse_radius_px / s))
    dt = feats.dt.get(s)
    trunc = float(dt.max()) if dt is not None else 1.0
    rolls = np.zeros(1) if rolls_rad is None else np.asarray(rolls_rad, dtype=np.float64)
    cands = [(d, q) for d in depths_m for q in rolls]
    out = np.full((len(cands), 2 * R_lev + 1, 2 * R_lev + 1), trunc, np.float32)
    if dt is None or len(vis.points) == 0:
        return out
    u0, v0 = feats.roi[0], feats.roi[1]
    padded = cv2.copyMakeBorder(dt, R_lev, R_lev, R_lev, R_lev, cv2.BORDER_CONSTANT, value=trunc)
    for k, (d, q) in enumerate(cands):
        uv, z = candidate_pose(pose, d, q).project(camera, vis.points)
        ok = np.isfinite(uv).all(axis=1) & (z > 0.5)
        if ok.sum() < options.min_samples:
            continue
        ij = np.rint((uv[ok] - [u0, v0] - (s - 1) / 2) / s).astype(int)
        lo = ij.min(axis=0)
        size = ij.max(axis=0) - lo + 1
        if np.any(size > np.array(dt.shape[::-1]) + 2 * R_lev - 1):
            continue
        T = np.zeros((size[1], size[0]), np.float32)
        np.add.at(T, (ij[:, 1] - lo[1], ij[:, 0] - lo[0]), vis.weight[ok].astype(np.float32))
        # window of the padded DT: the template's top-left at (lo + R_lev) ± R_lev
        x0, y0 = lo[0], lo[1]
        x1, y1 = lo[0] + size[0] + 2 * R_lev, lo[1] + size[1] + 2 * R_lev
        px, py = max(-x0, 0), max(-y0, 0)
        pw = cv2.copyMakeBorder(padded, py, max(y1 - padded.shape[0], 0), px, max(x1 - padded.shape[1], 0),
                                cv2.BORDER_CONSTANT, value=trunc)
        win = pw[y0 + py: y1 + py, x0 + px: x1 + px]
        out[k] = cv2.matchTemplate(win, T, cv2.TM_CCORR) / max(float(T.sum()), 1e-9)
    return out


def shift_rotation(camera: Camera, ref_uv: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """Rotation vector ω `(3,)` (camera frame) with `R' = R exp(ω)` moving the image point `ref_uv`
    `(2,)` by `shift` `(2,)` pixels (exact: the rotation between the two bearings)."""
    b0 = camera.bearing(np.asarray(ref_uv, dtype=np.float64)[None])[0]
    b1 = camera.bearing((np.asarray(ref_uv) + shift)[None])[0]
    axis_q = np.cross(b1, b0)
    sin_q = np.linalg.norm(axis_q)
    ang = np.arctan2(sin_q, float(b0 @ b1))
    return axis_q / sin_q * ang if sin_q > 1e-12 else np.zeros(3)


def shift_pose(camera: Camera, pose: Pose, ref_uv: np.ndarray, shift: np.ndarray, depth: float,
               options: FrameFitOptions) -> Pose:
    """`pose` changed so that image point `ref_uv` `(2,)` of a surface at `depth` metres moves by
    `shift` `(2,)` px, by a rotation and a translation across the optical axis (see
    `coarse_rotation_sigma_deg`)."""
    sr = np.radians(options.coarse_rotation_sigma_deg)
    st = options.coarse_translation_sigma_m / max(depth, 1e-3)
    a = sr**2 / (sr**2 + st**2)
    shift = np.asarray(shift, dtype=np.float64)
    w = shift_rotation(camera, ref_uv, a * shift)
    # moving the camera by -t (camera frame) moves the image by f t / Z
    t_cam = -np.array([(1 - a) * shift[0] * depth / camera.fx, (1 - a) * shift[1] * depth / camera.fy, 0.0])
    R = pose.R_world_from_cam
    return Pose(R @ so3_exp(w), pose.center + R @ t_cam)


def shift_penalty(shape: tuple[int, ...], options: FrameFitOptions) -> np.ndarray:
    """`(2r+1, 2r+1)` penalty favouring small shifts (level pixels of mean distance)."""
    r = shape[-1] // 2
    sy, sx = np.mgrid[-r:r + 1, -r:r + 1]
    return (options.coarse_shift_penalty * np.hypot(sx, sy)).astype(np.float32)


def coarse_search(
    camera: Camera, pose: Pose, vis: VisibleWireframe, feats: ImageFeatures, options: FrameFitOptions
) -> Pose:
    """Minimise the mean truncated edge distance of the projected samples over depth offsets and
    image shifts (level `coarse_level`); the shift is turned into an exact camera rotation."""
    if len(vis.points) == 0:
        return pose
    _, depth = pose.project(camera, vis.points)
    dmed = float(np.median(depth))
    depths = np.clip(np.asarray(options.coarse_depth_steps) * dmed, -options.coarse_max_depth_m,
                     options.coarse_max_depth_m)
    scores = coarse_scores(camera, pose, vis, feats, depths, options)
    scores = scores + shift_penalty(scores.shape, options)[None]
    k, iy, ix = np.unravel_index(int(np.argmin(scores)), scores.shape)
    r = scores.shape[-1] // 2
    # keep the pose unless the minimum is inside the window and clearly below the typical score
    typical = float(np.median(scores))
    inside = min(ix, iy) > 0 and max(ix, iy) < 2 * r
    if not inside or scores[k, iy, ix] > (1.0 - options.coarse_min_gain) * typical:
        return pose
    shift = np.array([ix - r, iy - r], dtype=np.float64) * options.coarse_level
    moved = Pose(pose.R_world_from_cam, pose.center + depths[k] * pose.R_world_from_cam[:, 2])
    uv, z = moved.project(camera, vis.points)
    ref = np.nanmean(uv, axis=0)
    return shift_pose(camera, moved, ref, shift, float(np.median(z)), options)


def joint_coarse(
    camera: Camera,
    poses: list[Pose],
    visible: list[VisibleWireframe],
    features: list[ImageFeatures],
    options: FrameFitOptions,
    rolls_deg: tuple[float, ...] = (0.0,),
    min_gain: float = 0.35,
    candidates: int = 1,
) -> list[tuple[np.ndarray, float, float, float]]:
    """Common coarse corrections of several frames, best first: each (image shift `(2,)` px at
    the principal point, depth offset along the optical axis (m), roll about it (rad), median
    depth (m)); empty without usable frames or without a distinct minimum.

    The score maps of all frames over the same depth offsets (steps × the median sample depth)
    and shifts are averaged; `apply_coarse` turns a result into each frame's pose. A candidate
    is a local minimum inside the search window that lowers the typical score by `min_gain`; up
    to `candidates` of them, at least 3 level pixels apart in shift (for verification by the
    caller: repetitive scenes have several similar minima).
    """
    depths = []
    for pose, vis in zip(poses, visible, strict=True):
        _, z = pose.project(camera, vis.points)
        depths.append(float(np.median(z)))
    if not depths:
        return []
    dmed = float(np.median(depths))
    steps = np.clip(np.asarray(options.coarse_depth_steps) * dmed, -options.coarse_max_depth_m,
                    options.coarse_max_depth_m)
    total = None
    for pose, vis, feats in zip(poses, visible, features, strict=True):
        sc = coarse_scores(camera, pose, vis, feats, steps, options, np.radians(rolls_deg))
        total = sc if total is None else total + sc
    if total is None:
        return []
    total = total / len(poses) + shift_penalty(total.shape, options)[None]
    r = total.shape[-1] // 2
    typical = float(np.median(total))
    # best over depth and roll per shift, then minima with suppression of their neighbourhood
    flat = total.min(axis=0)
    which = total.argmin(axis=0)
    work = flat.copy()
    out = []
    for _ in range(max(candidates, 1)):
        iy, ix = np.unravel_index(int(np.argmin(work)), work.shape)
        best = float(work[iy, ix])
        # inside the window and clearly below the typical score; else no usable common signal
        # (e.g. close-range drives that see facade interiors and hardly any model edge)
        inside = min(ix, iy) > 0 and max(ix, iy) < 2 * r
        if not np.isfinite(best) or not inside or best > (1.0 - min_gain) * typical:
            break
        k = int(which[iy, ix])
        kd, kq = divmod(k, len(rolls_deg))
        shift = np.array([ix - r, iy - r], dtype=np.float64) * options.coarse_level
        out.append((shift, float(steps[kd]), float(np.radians(rolls_deg[kq])), dmed))
        work[max(iy - 3, 0): iy + 4, max(ix - 3, 0): ix + 4] = np.inf
    return out


def apply_coarse(camera: Camera, pose: Pose, common: tuple[np.ndarray, float, float, float],
                 options: FrameFitOptions) -> Pose:
    """`pose` moved along its optical axis by the common depth offset, then shifted in the image by
    the common shift (rotation and translation, `shift_pose`)."""
    shift, depth_m, roll, dmed = common
    moved = candidate_pose(pose, depth_m, roll)
    centre = np.array([camera.cx, camera.cy])
    return shift_pose(camera, moved, centre, shift, max(dmed - depth_m, 1.0), options)

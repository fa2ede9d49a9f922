"""Sequence level of per-building orientation: what consecutive frames share.

In: per-frame data of one building (visible wireframes, edge-distance score maps, frame fits with
their data information matrices, times). Out: a common coarse correction of all frames, and
per-frame predictions of the correction from the neighbours in time.

The GNSS/INS errors of consecutive frames are strongly correlated: a constant boresight
misalignment (a rotation fixed in the camera frame), a position bias drifting slowly, plus
per-frame white noise and vibration. Hence:

- **joint coarse search**: the edge-distance score maps (depth offset × image shift) of all
  frames are summed; the minimum is the common correction, found where single frames are
  ambiguous (a neighbour's outline, a window row);
- **prediction**: for each frame, the information-weighted mean of the converged corrections of
  its neighbours within a time window (Gaussian time weights; each frame's information inflated
  by the per-frame noise `Σ_frame`, outliers removed by a Mahalanobis gate), with its covariance.

Corrections are `δ = (ω_cam, dC_world)` relative to each frame's prior (`coregister_frame`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.orientation.coarse import candidate_pose, coarse_scores, shift_penalty, shift_pose
from workers.pipeline.orientation.features import ImageFeatures
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.frame_fit import FrameFit
from workers.pipeline.orientation.wireframe import VisibleWireframe


@dataclass(frozen=True, eq=False)
class Prediction:
    """Neighbour prediction of one frame's correction.

    Attributes:
        delta: `(6,)` predicted correction `(ω_cam, dC_world)`.
        covariance: `(6, 6)` covariance of the predicted mean (without the per-frame noise).
        neighbours: converged neighbours used (after the outlier gate).
        both_sides: neighbours before and after the frame in time.
    """

    delta: np.ndarray
    covariance: np.ndarray
    neighbours: int
    both_sides: bool


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
    the common shift (rotation and translation, `coregister_frame.shift_pose`)."""
    shift, depth_m, roll, dmed = common
    moved = candidate_pose(pose, depth_m, roll)
    centre = np.array([camera.cx, camera.cy])
    return shift_pose(camera, moved, centre, shift, max(dmed - depth_m, 1.0), options)


def predict(
    j: int,
    times: np.ndarray,
    deltas: np.ndarray,
    fits: list[FrameFit],
    usable: np.ndarray,
    frame_cov: np.ndarray,
    regulariser: np.ndarray,
    reg_delta: np.ndarray,
    window_s: float,
    time_sigma_s: float,
    gate: float,
) -> Prediction | None:
    """Prediction of frame `j`'s correction from the usable frames around it (`j` left out).

    Args:
        times: `(F,)` seconds; deltas: `(F, 6)` corrections; usable: `(F,)` bool (converged).
        frame_cov: `(6, 6)` per-frame noise `Σ_frame`.
        regulariser: `(6, 6)` weak information pulling the mean towards `reg_delta` `(6,)` (keeps
            directions no frame observes defined).
        gate: Mahalanobis distance (per degree of freedom, squared) beyond which a neighbour is an
            outlier of the first estimate.
    """
    dt = times - times[j]
    nb = usable & (np.abs(dt) <= window_s)
    nb[j] = False
    k = np.nonzero(nb)[0]
    if len(k) == 0:
        return None
    w = np.exp(-0.5 * (dt[k] / time_sigma_s) ** 2)
    # information of each neighbour's correction as an observation of the shared one:
    # (H⁻¹ + Σ_frame)⁻¹ = H (I + Σ_frame H)⁻¹ (valid for singular H)
    H = np.array([fits[i].information for i in k])
    M = H @ np.linalg.inv(np.eye(6)[None] + frame_cov[None] @ H)
    M = 0.5 * (M + np.transpose(M, (0, 2, 1)))
    keep = np.ones(len(k), bool)
    mean = reg_delta
    cov = np.linalg.inv(regulariser)
    for _ in range(2):
        A = regulariser + np.einsum("k,kij->ij", w[keep], M[keep])
        b = regulariser @ reg_delta + np.einsum("k,kij,kj->i", w[keep], M[keep], deltas[k][keep])
        cov = np.linalg.inv(A)
        mean = cov @ b
        r = deltas[k] - mean
        maha = np.einsum("ki,kij,kj->k", r, M, r) / 6.0
        new_keep = maha <= gate
        if new_keep.sum() == 0 or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    used = k[keep]
    both = bool(np.any(dt[used] < 0) and np.any(dt[used] > 0))
    return Prediction(delta=mean, covariance=cov, neighbours=len(used), both_sides=both)

"""Start poses for tracking from noisy priors: the GNSS/INS poses smoothed over time.

In: a pose per frame (world = model CRS) and the frames' times (seconds). Out: the priors'
frame-to-frame white noise measured from the priors themselves (`prior_noise`: robust standard
deviations of their second differences), and the poses with that noise smoothed out
(`smooth_poses`), each frame's pose the intercept of a Gaussian-weighted local linear fit of its
neighbours' poses against time.

Why: the tracker predicts each track's position in the next frame from the poses of the two
frames (`tracks`, step 1). Uncalibrated priors of a hand-held or terrestrial sequence carry the
GNSS/INS white noise of decimetres and a degree from frame to frame (0.5 m at 10 m is 40 px,
1° another 14 px): predictions that far off lock the coarse tracker onto the next window of a
regular facade. The camera's true path is smooth over a second; the smoothed priors predict the
motion between consecutive frames to a few pixels, and their common error is what the block's
common correction absorbs anyway. The priors as observations of the adjustment stay unsmoothed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import apply_delta, pose_delta

__all__ = ["prior_noise", "smooth_poses"]


def prior_noise(poses: Mapping[int, Pose], frames: Sequence[int]) -> tuple[float, float]:
    """The white noise of consecutive poses of `frames` (recording order): robust standard
    deviations (1.4826 × median absolute value, largest of the three axes) of the second
    differences `pose_delta(p_k, p_k−1) + pose_delta(p_k, p_k+1)` divided by √6 (their σ for
    independent errors of σ per frame; a steady or slowly turning motion leaves ~0 at 10 Hz).
    Returns (rotation σ in degrees about the camera axes, position σ in metres); (0, 0) for
    fewer than 3 frames.

    >>> p = {k: Pose(np.eye(3), np.array([float(k), 0.3 * (k % 2), 0.0])) for k in range(9)}
    >>> deg, m = prior_noise(p, range(9))
    >>> round(deg, 3), round(m, 3)  # 0.3 m up and down: second differences of 0.6 m
    (0.0, 0.363)
    """
    frames = [int(f) for f in frames]
    if len(frames) < 3:
        return 0.0, 0.0
    d2 = np.array(
        [
            pose_delta(poses[b], poses[a]) + pose_delta(poses[b], poses[c])
            for a, b, c in zip(frames, frames[1:], frames[2:], strict=False)
        ]
    )
    sd = 1.4826 * np.median(np.abs(d2), axis=0) / np.sqrt(6.0)
    return float(np.degrees(np.max(sd[:3]))), float(np.max(sd[3:]))


def smooth_poses(
    poses: Mapping[int, Pose], frames: Sequence[int], times: Mapping[int, float], sigma_s: float
) -> dict[int, Pose]:
    """The poses of `frames` smoothed over time (module docstring).

    For each frame `i`, the increments `δ_j = (ω_cam [rad], dC_world [m])` of the frames `j`
    within 3 σ (`pose_delta(poses[i], poses[j])`) are fitted by `a + b (t_j − t_i)` with Gaussian
    weights of σ `sigma_s` (seconds); the frame's smoothed pose is `poses[i]` moved by `a`. A
    local linear fit keeps a steady motion (a walk, a drive) unbiased, also at the ends of the
    sequence. With `sigma_s <= 0` or fewer than 3 frames the poses are returned as they are.

    >>> p = {k: Pose(np.eye(3), np.array([float(k), 0.0, 0.0])) for k in range(5)}
    >>> s = smooth_poses(p, range(5), {k: float(k) for k in range(5)}, 1.0)
    >>> bool(np.allclose([s[k].center[0] for k in range(5)], range(5)))
    True
    """
    frames = [int(f) for f in frames]
    if sigma_s <= 0 or len(frames) < 3:
        return {f: poses[f] for f in frames}
    t = np.array([float(times[f]) for f in frames])
    out: dict[int, Pose] = {}
    for k, f in enumerate(frames):
        dt = t - t[k]
        near = np.flatnonzero(np.abs(dt) <= 3.0 * sigma_s)
        if len(near) < 3:
            out[f] = poses[f]
            continue
        w = np.exp(-0.5 * (dt[near] / sigma_s) ** 2)
        d = np.array([pose_delta(poses[f], poses[frames[j]]) for j in near])  # (K, 6)
        A = np.stack([np.ones(len(near)), dt[near]], axis=1) * np.sqrt(w)[:, None]
        coef, *_ = np.linalg.lstsq(A, d * np.sqrt(w)[:, None], rcond=None)
        out[f] = apply_delta(poses[f], coef[0])
    return out

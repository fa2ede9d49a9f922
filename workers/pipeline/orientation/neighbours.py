"""Neighbour prediction of per-building orientation: a frame's correction from its neighbours in time.

In: the frame fits of one building's frames (`frame_fit.FrameFit`, with their data information
matrices), their corrections `δ = (ω_cam, dC_world)` relative to each frame's prior
(`geometry.pose_increments.pose_delta`), their times, the per-frame deviation `Σ_frame`
(`priors.frame_noise_covariance`). Out: per frame a `Prediction` of its correction with its
covariance (`predict`), used by the second pass and the inheritance rule of `building`.

The GNSS/INS errors of consecutive frames are strongly correlated: a constant boresight
misalignment (a rotation fixed in the camera frame), a position bias drifting slowly, plus
per-frame white noise and vibration. Hence the **prediction**: for each frame, the
information-weighted mean of the converged corrections of its neighbours within a time window
(Gaussian time weights; each frame's information inflated by the per-frame noise `Σ_frame`,
outliers removed by a Mahalanobis gate), with its covariance. (What all frames share at once, the
joint coarse search, is in `coarse`.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workers.pipeline.orientation.frame_fit import FrameFit

__all__ = ["Prediction", "predict"]


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

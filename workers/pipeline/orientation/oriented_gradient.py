"""Oriented-gradient edge score: how well projected wireframe samples lie on image edges of their
direction, without correspondences.

In: a frame `(H, W)` float32, candidate positions of the projected edge samples `(K, N, 2)`
(full-resolution pixels, one row per candidate correction), the samples' image normals `(N, 2)`
and weights `(N,)`. Out: one score per candidate in [−1, 1].

The frame is downsampled and smoothed (`downsampled_gradient`); a sample scores the image
gradient component along its projected edge's normal minus the one across it, divided by the
frame's robust gradient scale and clipped to ±1 (`oriented_gradient_score`). Insensitive to the
window rows the model does not contain (a plain distance transform is not). Used by the coarse
stage of the common correction (`common_correction`: common image shifts and world translations)
and by the time-delay search of the sequence calibration (`calibration`).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["downsampled_gradient", "oriented_gradient_score"]


def downsampled_gradient(img: np.ndarray, ds: int, sigma: float) -> tuple[np.ndarray, float]:
    """Image `(H, W)` downsampled by `ds` and smoothed by `sigma` (downsampled pixels) ->
    gradients `(h, w, 2)` and their robust scale (95th percentile of the magnitude)."""
    small = cv2.resize(img, (img.shape[1] // ds, img.shape[0] // ds), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small.astype(np.float32), (0, 0), sigma)
    gx = cv2.Sobel(small, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(small, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return np.dstack([gx, gy]), float(np.percentile(np.hypot(gx, gy), 95)) or 1e-6


def oriented_gradient_score(
    grad: tuple[np.ndarray, float], ds: int, uv: np.ndarray, nrm: np.ndarray, w: np.ndarray
) -> np.ndarray:
    """Oriented-gradient score `(K,)` of candidate sample positions `uv` `(K, N, 2)` (full-resolution
    pixels) with edge normals `nrm` `(N, 2)` and weights `w` `(N,)` on the gradients `grad` of
    `downsampled_gradient` (downsampled by `ds`): weighted mean over samples of (gradient along
    the normal − across it) / scale, clipped to ±1; 0 outside the frame."""
    g, ref = grad
    pu = np.nan_to_num((uv[..., 0] + 0.5) / ds - 0.5, nan=-1e4).astype(np.float32)
    pv = np.nan_to_num((uv[..., 1] + 0.5) / ds - 0.5, nan=-1e4).astype(np.float32)
    gg = cv2.remap(g, pu, pv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    along = np.abs(gg[..., 0] * nrm[None, :, 0] + gg[..., 1] * nrm[None, :, 1])
    across = np.abs(gg[..., 0] * nrm[None, :, 1] - gg[..., 1] * nrm[None, :, 0])
    sc = np.clip((along - across) / ref, -1.0, 1.0)
    return (sc * w[None]).sum(axis=1) / max(float(w.sum()), 1e-9)

"""Typical temperature of a surface and the per-texel masks every later step needs.

In: a surface's fused values `(H, W)` (NaN: not observed), its texel mask, its kept observations'
frames `(K, H, W)`. Out: robust typical value and spread (median, 1.4826 · MAD), the edge band
of the observed region, the number of frames that saw each texel, NaN-aware smoothing.
"""

from __future__ import annotations

import cv2
import numpy as np

MAD_TO_SIGMA = 1.4826


def robust_stats(values: np.ndarray) -> tuple[float, float]:
    """Median and 1.4826 · MAD of the finite entries of `values` (NaN, NaN when empty).

    >>> robust_stats(np.array([1.0, 2.0, 3.0, 4.0, 100.0]))
    (3.0, 1.4826)
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return float("nan"), float("nan")
    med = float(np.median(v))
    return med, float(MAD_TO_SIGMA * np.median(np.abs(v - med)))


def edge_band(observed: np.ndarray, band_px: int) -> np.ndarray:
    """`(H, W)` bool: observed texels within `band_px` texels (Chebyshev) of an unobserved texel
    or of the raster border (the polygon outline is where `observed` ends)."""
    if band_px <= 0:
        return np.zeros_like(observed)
    padded = np.pad(observed.astype(np.uint8), band_px)
    kernel = np.ones((2 * band_px + 1, 2 * band_px + 1), np.uint8)
    inner = cv2.erode(padded, kernel)[band_px:-band_px, band_px:-band_px].astype(bool)
    return observed & ~inner


def frames_per_texel(obs_frame: np.ndarray) -> np.ndarray:
    """`(H, W)` int: frames among a texel's kept observations `(K, H, W)` (-1: empty slot); a
    frame is merged into a texel at most once (`SurfaceTexture.merge`), so the kept observations
    of a texel come from distinct frames."""
    f = np.asarray(obs_frame)
    if f.ndim != 3 or f.shape[0] == 0:
        return np.zeros(f.shape[-2:], np.int32)
    return np.count_nonzero(f >= 0, axis=0).astype(np.int32)


def smooth(values: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing (`sigma` texels) of `values` over `valid` texels only (normalised
    convolution); NaN outside `valid`."""
    v = np.where(valid, values, 0.0).astype(np.float32)
    if sigma <= 0:
        return np.where(valid, v, np.nan).astype(np.float32)
    w = valid.astype(np.float32)
    ks = 2 * int(np.ceil(3 * sigma)) + 1
    num = cv2.GaussianBlur(v, (ks, ks), sigma, borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(w, (ks, ks), sigma, borderType=cv2.BORDER_CONSTANT)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den
    return np.where(valid & (den > 1e-6), out, np.nan).astype(np.float32)

"""Sub-texel alignment of a frame's partial texture to the fused texture of a surface.

In: two rasters `(H, W)` on the same texel grid (float32 physical values, NaN = no value).
Out: the shift `d = (dx, dy)` in texels with `partial(x) ≈ fused(x − d)` (so sampling the frame at
texel positions `x + d` aligns it), and the correlation peak, or None when rejected.

Method: phase correlation on the overlap's bounding box (values outside the overlap set to the
overlap mean, Hann apodisation, normalised cross-power spectrum, peak located to sub-texel
precision by a parabola through its neighbours), then a few Gauss-Newton (Lucas-Kanade) steps
on the texels observed in both rasters, which removes the parabola's bias. The shift is bounded
and rejected when the peak is weak (no common structure), the overlap small or flat, or the
least-squares system ill-conditioned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class AlignOptions:
    """Options of the partial-texture alignment.

    Attributes:
        max_shift_texels: longer shifts are rejected.
        min_peak: smallest accepted phase-correlation peak (1 = identical up to a shift).
        min_contrast: smallest standard deviation of the overlap worth aligning on (physical unit).
        min_overlap_texels: smallest number of texels observed in both rasters.
        min_overlap_side: smallest side of the overlap's bounding box, texels.
        refine_iterations: Gauss-Newton steps after the phase correlation (0: none).
        max_lk_texels: at most this many texels enter the least-squares refinement.
        max_window: the correlation runs on at most `max_window × max_window` texels of the
            overlap (around its centre), which bounds its cost on large surfaces.
    """

    max_shift_texels: float = 3.0
    min_peak: float = 0.1
    min_contrast: float = 0.05
    min_overlap_texels: int = 400
    min_overlap_side: int = 16
    refine_iterations: int = 3
    max_lk_texels: int = 8000
    max_window: int = 128


def _parabola(m1: float, c: float, p1: float) -> float:
    """Vertex offset in (-0.5, 0.5) of the parabola through (-1, m1), (0, c), (1, p1)."""
    den = m1 - 2.0 * c + p1
    if den >= 0 or not math.isfinite(den):
        return 0.0
    return float(np.clip(0.5 * (m1 - p1) / den, -0.5, 0.5))


def phase_correlation(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """Shift `(dx, dy, peak)` with `b(x) ≈ a(x − d)` for two equally sized float rasters (no NaN)."""
    h, w = a.shape
    win = np.outer(np.hanning(h), np.hanning(w)) if min(h, w) > 2 else np.ones((h, w))
    fa = np.fft.rfft2((a - a.mean()) * win)
    fb = np.fft.rfft2((b - b.mean()) * win)
    cross = np.conj(fa) * fb
    cross /= np.maximum(np.abs(cross), 1e-12)
    r = np.fft.irfft2(cross, s=(h, w))
    iy, ix = np.unravel_index(int(np.argmax(r)), r.shape)
    peak = float(r[iy, ix])
    dy = _parabola(r[(iy - 1) % h, ix], peak, r[(iy + 1) % h, ix])
    dx = _parabola(r[iy, (ix - 1) % w], peak, r[iy, (ix + 1) % w])
    sy = iy - h if iy > h // 2 else iy
    sx = ix - w if ix > w // 2 else ix
    return float(sx + dx), float(sy + dy), peak


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of `img (H, W)` at raster positions `x, y` (element centres at integers;
    positions outside give NaN; NaN in `img` propagates)."""
    H, W = img.shape
    out = np.full(x.shape, np.nan)
    ok = (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    xs, ys = x[ok], y[ok]
    x0 = np.minimum(np.floor(xs).astype(np.intp), max(W - 2, 0))
    y0 = np.minimum(np.floor(ys).astype(np.intp), max(H - 2, 0))
    fx, fy = xs - x0, ys - y0
    x1 = np.minimum(x0 + 1, W - 1)
    y1 = np.minimum(y0 + 1, H - 1)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bot = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    out[ok] = top * (1 - fy) + bot * fy
    return out


def refine_shift(
    fused: np.ndarray, partial: np.ndarray, d: tuple[float, float], options: AlignOptions
) -> tuple[float, float, float] | None:
    """Gauss-Newton refinement of `d = (dx, dy)` minimising Σ (partial(x) − fused(x − d))² over
    texels valid in both -> `(dx, dy, sigma)`, `sigma` the standard deviation of the shift's
    length from the residuals (texels, ignoring their spatial correlation: a lower bound);
    None when the system is ill-conditioned (no structure)."""
    rows, cols = np.nonzero(np.isfinite(partial))
    if len(rows) > options.max_lk_texels:
        step = math.ceil(len(rows) / options.max_lk_texels)
        rows, cols = rows[::step], cols[::step]
    p = partial[rows, cols].astype(np.float64)
    f = fused.astype(np.float64)
    dx, dy = d
    sigma = float("inf")
    for _ in range(options.refine_iterations):
        x, y = cols - dx, rows - dy
        fs = _bilinear(f, x, y)
        gx = 0.5 * (_bilinear(f, x + 1, y) - _bilinear(f, x - 1, y))
        gy = 0.5 * (_bilinear(f, x, y + 1) - _bilinear(f, x, y - 1))
        ok = np.isfinite(fs) & np.isfinite(gx) & np.isfinite(gy)
        if ok.sum() < options.min_overlap_texels:
            return None
        gx, gy, r = gx[ok], gy[ok], (fs - p)[ok]
        r = r - r.mean()  # insensitive to an offset between the two
        A = np.array([[gx @ gx, gx @ gy], [gx @ gy, gy @ gy]])
        eig = np.linalg.eigvalsh(A)
        if eig[0] < 1e-6 * ok.sum() or eig[0] < 1e-3 * eig[1]:
            return None
        # p ≈ fused(x − d − δ) ≈ fs − g·δ  =>  g·δ ≈ fs − p
        delta = np.linalg.solve(A, np.array([gx @ r, gy @ r]))
        dx, dy = dx + float(delta[0]), dy + float(delta[1])
        e = r - gx * delta[0] - gy * delta[1]
        s2 = float(e @ e) / max(len(e) - 3, 1)
        sigma = math.sqrt(s2 / eig[0])
        if math.hypot(float(delta[0]), float(delta[1])) < 1e-3:
            break
    return dx, dy, sigma


def align_partial(
    fused: np.ndarray, partial: np.ndarray, options: AlignOptions
) -> tuple[float, float, float, float] | None:
    """Shift `(dx, dy, peak, sigma)` of `partial (H, W)` against `fused (H, W)` (NaN = no value),
    with `partial(x) ≈ fused(x − d)`, the correlation peak and the shift's standard deviation
    (texels; inf without the least-squares refinement); None when rejected (see the module
    docstring)."""
    both = np.isfinite(fused) & np.isfinite(partial)
    if int(both.sum()) < options.min_overlap_texels:
        return None
    rows = np.nonzero(both.any(axis=1))[0]
    cols = np.nonzero(both.any(axis=0))[0]
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    if min(r1 - r0, c1 - c0) < options.min_overlap_side:
        return None
    m = options.max_window
    if r1 - r0 > m or c1 - c0 > m:  # a window around the overlap's centre of mass
        rr, cc = np.nonzero(both)
        rc, ccn = int(np.median(rr)), int(np.median(cc))
        if r1 - r0 > m:
            r0 = min(max(rc - m // 2, r0), r1 - m)
            r1 = r0 + m
        if c1 - c0 > m:
            c0 = min(max(ccn - m // 2, c0), c1 - m)
            c1 = c0 + m
        if int(both[r0:r1, c0:c1].sum()) < options.min_overlap_texels:
            return None
    win = both[r0:r1, c0:c1]
    a = fused[r0:r1, c0:c1]
    b = partial[r0:r1, c0:c1]
    va, vb = a[win].astype(np.float64), b[win].astype(np.float64)
    if float(va.std()) < options.min_contrast or float(vb.std()) < options.min_contrast:
        return None
    fa = a.astype(np.float64)
    a = np.where(win, a, va.mean()).astype(np.float64)
    b = np.where(win, b, vb.mean()).astype(np.float64)
    dx, dy, peak = phase_correlation(a, b)
    if peak < options.min_peak or math.hypot(dx, dy) > options.max_shift_texels + 1.0:
        return None
    sigma = float("inf")
    if options.refine_iterations > 0:
        part = np.where(win, b, np.nan)
        refined = refine_shift(fa, part, (dx, dy), options)
        if refined is None:
            return None
        dx, dy, sigma = refined
    if not (math.isfinite(dx) and math.isfinite(dy)) or math.hypot(dx, dy) > options.max_shift_texels:
        return None
    return float(dx), float(dy), float(peak), float(sigma)

"""Leak candidates: compact warm regions of a surface, with half-maximum outlines.

In: the residual excess over typical `(H, W)` (linear bridges removed, `lines`; over window panes
against the panes' level), its smoothed version, where regions may lie, the edge band, frames
per texel, the threshold, texel size, options. Out: `Region`s of kind "leak" or "bridge"
(elongated or thin), each a texel mask with its amplitude, mean excess, centre and outline area.

Rules (`docs/anomalies.md`):
- seed: a connected set of texels outside the edge band and the window zone whose smoothed
  excess exceeds the threshold; seeds are taken strongest first;
- peak: a Gaussian fitted to the 5 × 5 texels around the seed's maximum (log-quadratic, weights
  value²) gives the centre; amplitude `A` and local background `B` of `B + A·exp(−d²/2σ²)` are
  then fitted within 3σ (σ from the half-maximum area), twice;
- outline: the texels connected to the maximum (also across window frames) whose smoothed
  excess is ≥ `B + A/2` (the half-maximum contour), edge band included;
- edge effect: a region whose maximum lies near the polygon's outline, or touches the edge of the
  observed area while the edge texels 0.8–1.2 m away are still as warm (a rim, a ramp along a
  cut), is dropped;
- frames: a region seen by fewer than `min_frames` distinct frames, or whose texels are mostly
  seen by fewer, is dropped;
- size: fewer than `min_texels` texels or less than `min_area_m2` is dropped;
- contrast: an amplitude below 0.75 × the threshold (a broad warm area) is dropped;
- tails: a seed within three half-maximum radii of a stronger leak is that leak's tail;
- shape: a region `bridge_aspect` times longer than wide and at least `bridge_min_length_m` long,
  or narrower than `line_width_m`, is a bridge; its compact core (an opening with a 0.4 m disk)
  is still a leak when its own amplitude exceeds the threshold.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from workers.pipeline.anomalies.options import AnomalyOptions

_FIT_RADIUS = 2  # texels around the maximum used by the peak fit
HALF_MAX_RADIUS = math.sqrt(2 * math.log(2))  # half-maximum radius of a Gaussian, in σ
MIN_AMPLITUDE = 0.75  # a leak's amplitude over its local background, in units of the threshold
_CLOSE = np.ones((9, 9), np.uint8)  # closes gaps up to 8 texels (a window frame and its margins)


@dataclass(frozen=True, eq=False)
class Region:
    """A candidate region: `mask (H, W)` bool, `peak`/`mean` excess (K), `centre_xy` continuous
    raster coordinates `(2,)` of its peak, `kind` "leak" or "bridge", `shape (H, W)` bool the
    area its outline encloses (the mask closed over the window frames it spans)."""

    mask: np.ndarray
    peak: float
    mean: float
    centre_xy: np.ndarray
    kind: str
    shape: np.ndarray


@dataclass(frozen=True)
class LeakInputs:
    """Per-texel inputs of `find_leaks` (all `(H, W)`): residual excess (NaN unobserved), its
    smoothed version (−inf where not usable), where regions may lie (`grow`), the edge band, the
    texels a background fit may use (`usable`: observed outside the window zone, or on a pane
    with the pane's level removed), the texels a region may connect across without including
    them (`passable`: window frames and margins), the outermost observed texels (`edge`) and
    those of them on the polygon's outline (`outline`: next to a texel outside the mask)."""

    residual: np.ndarray
    smoothed: np.ndarray
    grow: np.ndarray
    band: np.ndarray
    usable: np.ndarray
    passable: np.ndarray
    edge: np.ndarray
    outline: np.ndarray


def _solve(A: np.ndarray, z: np.ndarray, w: np.ndarray) -> np.ndarray | None:
    """Weighted least squares `A (N, P) x ≈ z (N,)` with weights `w (N,)` (normal equations)."""
    Aw = A * w[:, None]
    try:
        return np.linalg.solve(Aw.T @ A, Aw.T @ z)
    except np.linalg.LinAlgError:
        return None


def fit_peak(values: np.ndarray, valid: np.ndarray, i: int, j: int) -> tuple[float, float, float] | None:
    """Gaussian peak `(value, x, y)` (continuous raster coordinates) fitted around texel `(i, j)`
    of `values (H, W)`; None when the fit is not a peak near `(i, j)`."""
    H, W = values.shape
    r = _FIT_RADIUS
    i0, i1, j0, j1 = max(i - r, 0), min(i + r + 1, H), max(j - r, 0), min(j + r + 1, W)
    v = values[i0:i1, j0:j1].astype(np.float64)
    vmax = v[i - i0, j - j0]
    ok = valid[i0:i1, j0:j1] & (v > 0.2 * vmax)  # NaN compares False
    if not vmax > 0 or np.count_nonzero(ok) < 6:
        return None
    yy, xx = np.nonzero(ok)
    x, y, w = (xx + (j0 - j)).astype(np.float64), (yy + (i0 - i)).astype(np.float64), v[ok]
    sol = _solve(np.stack([np.ones_like(x), x, y, x * x + y * y], axis=1), np.log(w), w * w)
    if sol is None or sol[3] >= -1e-6:
        return None
    a, b, c, d = sol
    dx, dy = -b / (2 * d), -c / (2 * d)
    if max(abs(dx), abs(dy)) > 1.0:
        return None
    peak = math.exp(a - (b * b + c * c) / (4 * d))
    if not 0.8 * vmax <= peak <= 1.5 * vmax:
        return None
    return peak, j + 0.5 + dx, i + 0.5 + dy


def fit_amplitude(
    values: np.ndarray, valid: np.ndarray, cx: float, cy: float, sigma: float
) -> tuple[float, float] | None:
    """Amplitude `A` and background `B` of `B + A·exp(−d²/2σ²)` around the continuous raster point
    `(cx, cy)` with `sigma` in texels, least squares over the `valid` texels within 3σ; None when
    too few texels lie in the background (beyond 1.5σ)."""
    H, W = values.shape
    R = math.ceil(3 * sigma) + 1
    i0, i1 = max(int(cy) - R, 0), min(int(cy) + R + 1, H)
    j0, j1 = max(int(cx) - R, 0), min(int(cx) + R + 1, W)
    dy2 = (np.arange(i0, i1) + 0.5 - cy)[:, None] ** 2
    d2 = dy2 + (np.arange(j0, j1) + 0.5 - cx)[None, :] ** 2
    v = values[i0:i1, j0:j1]
    ok = valid[i0:i1, j0:j1] & (d2 <= 9 * sigma * sigma) & np.isfinite(v)
    if np.count_nonzero(ok & (d2 > 2.25 * sigma * sigma)) < 8:
        return None
    g = np.exp(-d2[ok] / (2 * sigma * sigma))
    z = v[ok].astype(np.float64)
    gm, zm = g.mean(), z.mean()
    var = float(np.dot(g - gm, g - gm))
    if var <= 1e-9:
        return None
    amp = float(np.dot(g - gm, z - zm)) / var
    return (amp, float(zm - amp * gm)) if amp > 0 else None


def fit_blob(
    values: np.ndarray,
    valid: np.ndarray,
    cx: float,
    cy: float,
    sigma_obs: float,
    blur: float,
    blur_short: float | None = None,
) -> tuple[float, float, float, float, float] | None:
    """Amplitude `A`, background `B`, σ (texels) and centre `(x, y)` (continuous raster
    coordinates) of a round Gaussian blob `A·exp(−d²/2σ²)` seen through a Gaussian blur of σ
    `blur` (texels), near the raster point `(cx, cy)`: the blurred blob is
    `A σ²/σo² · exp(−d²/2σo²)`, `σo² = σ² + blur²` (the blur conserves its volume). With
    `blur_short` the blur is `blur` along one axis and `blur_short` across: the blurred blob
    is elliptic, the round fit's σo² the geometric mean of its variances, and σ² solves
    `(σ² + blur²)(σ² + blur_short²) = σo⁴` (`_deblurred`; the geometric mean of the two blurs
    as one round blur would leave σ too large and `A` too small, by 14 % for σ = 3, blurs of
    3 and 1 texels).

    σo is searched on a geometric grid (3 % steps) from a third to twice `sigma_obs` (the
    half-maximum estimate) at `(cx, cy)`, then the centre on a quarter-texel grid within half a
    texel of it (σo within 3 steps of the first), then σo again at that centre; `A` and `B`
    are linear least squares over the `valid` texels within `3·sigma_obs + 1` of `(cx, cy)`
    (the same texels for every trial); the trial with the smallest squared residual wins. None
    when fewer than 8 of those texels lie beyond 1.5 `sigma_obs` (no background to fit) or no
    trial gives a positive amplitude."""
    H, W = values.shape
    R = 3 * sigma_obs + 1
    i0, i1 = max(int(cy - R), 0), min(int(cy + R) + 1, H)
    j0, j1 = max(int(cx - R), 0), min(int(cx + R) + 1, W)
    yy, xx = np.mgrid[i0:i1, j0:j1] + 0.5
    d2 = (yy - cy) ** 2 + (xx - cx) ** 2
    v = values[i0:i1, j0:j1]
    ok = valid[i0:i1, j0:j1] & (d2 <= R * R) & np.isfinite(v)
    if np.count_nonzero(ok & (d2 > 2.25 * sigma_obs * sigma_obs)) < 8:
        return None
    xs, ys, z = xx[ok], yy[ok], v[ok].astype(np.float64)
    so2 = (np.geomspace(1 / 3, 2.0, 61) * sigma_obs) ** 2  # steps of 3 %
    so2 = so2[_deblurred(so2, blur, blur_short) >= 0.09]  # narrower than 0.3 texel: not resolved
    if len(so2) == 0:
        return None
    zc = z - z.mean()
    zz = float(zc @ zc)

    def trial(dx: float, dy: float, ks: np.ndarray) -> tuple[float, int, float]:
        """Smallest residual sum of squares over the σo of `so2[ks]` at centre offset
        `(dx, dy)`: (rss, index into so2, amplitude of the blurred blob)."""
        r2 = (xs - cx - dx) ** 2 + (ys - cy - dy) ** 2
        g = np.exp(-r2[None] / (2 * so2[ks, None]))  # (S, N)
        gc = g - g.mean(axis=1, keepdims=True)
        var = np.einsum("sn,sn->s", gc, gc)
        a = (gc @ zc) / np.maximum(var, 1e-12)
        ss = np.where((a > 0) & (var > 1e-9), zz - a * a * var, np.inf)
        k = int(np.argmin(ss))
        return float(ss[k]), int(ks[k]), float(a[k])

    # σ at the first centre, the centre at the σ found (± 3 steps), σ again at that centre
    every = np.arange(len(so2))
    _, k, _ = trial(0.0, 0.0, every)
    near = every[max(k - 3, 0) : k + 4]
    steps = (-0.5, -0.25, 0.0, 0.25, 0.5)
    ss, dx, dy = min((trial(dx, dy, near)[0], dx, dy) for dy in steps for dx in steps)
    ss, k, a = trial(dx, dy, every)
    if not math.isfinite(ss):
        return None
    r2 = (xs - cx - dx) ** 2 + (ys - cy - dy) ** 2
    b = float(z.mean() - a * np.exp(-r2 / (2 * so2[k])).mean())
    sig2 = float(_deblurred(so2[k : k + 1], blur, blur_short)[0])
    return a * float(so2[k]) / sig2, b, math.sqrt(sig2), cx + dx, cy + dy


def _deblurred(so2: np.ndarray, blur: float, blur_short: float | None) -> np.ndarray:
    """σ² of a round blob whose blurred image, fitted by a round Gaussian, has σo² = `so2`:
    `σo² − blur²` for a round blur; for a blur of σ `blur` along one axis and `blur_short`
    across, the root of `(σ² + blur²)(σ² + blur_short²) = σo⁴` (the round fit's σo² is the
    geometric mean of the blurred blob's two variances: it keeps the volume)."""
    if blur_short is None:
        return so2 - blur * blur
    a2, b2 = blur * blur, blur_short * blur_short
    return 0.5 * (-(a2 + b2) + np.sqrt((a2 - b2) ** 2 + 4 * so2 * so2))


def _component(mask: np.ndarray, i: int, j: int, passable: np.ndarray) -> np.ndarray:
    """The texels of `mask` 8-connected to texel `(i, j)` through `mask` or `passable` texels
    (empty if `(i, j)` is not set)."""
    if not mask[i, j]:
        return np.zeros_like(mask)
    _, lab = cv2.connectedComponents((mask | passable).view(np.uint8), connectivity=8)
    return (lab == lab[i, j]) & mask


def _elongation(region: np.ndarray, size: float) -> tuple[float, float, float]:
    """Aspect ratio (long / short axis), length and width (m) of a texel region, from its second
    moments (a uniform bar of `l × w` texels has variances `l²/12`, `w²/12`)."""
    m = cv2.moments(region.view(np.uint8), binaryImage=True)
    if m["m00"] < 2:
        return 1.0, size, size
    a, b, c = m["mu20"] / m["m00"] + 1 / 12, m["mu11"] / m["m00"], m["mu02"] / m["m00"] + 1 / 12
    root = math.sqrt(0.25 * (a - c) ** 2 + b * b)
    hi, lo = 0.5 * (a + c) + root, 0.5 * (a + c) - root
    return math.sqrt(hi / lo), math.sqrt(12.0 * hi) * size, math.sqrt(12.0 * lo) * size


def is_line(region: np.ndarray, size: float, o: AnomalyOptions) -> bool:
    """A linear thermal bridge: `bridge_aspect` times longer than wide and `bridge_min_length_m`
    long, or narrower than `line_width_m` and half again as long as wide (a piece of a pipe)."""
    aspect, length, width = _elongation(region, size)
    return (aspect >= o.bridge_aspect and length >= o.bridge_min_length_m) or (
        width < o.line_width_m and aspect >= 1.5
    )


def _core(region: np.ndarray, size: float) -> np.ndarray:
    """The largest part of `region` left by an opening with a disk wider than a line (0.4 m)."""
    d = max(3, math.ceil(0.4 / size)) | 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))
    opened = cv2.morphologyEx(region.astype(np.uint8), cv2.MORPH_OPEN, kernel)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
    if n < 2:
        return np.zeros_like(region)
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return lab == k


def _closed(region: np.ndarray, passable: np.ndarray) -> np.ndarray:
    """`region` with the passable texels it encloses (window frames it spans) filled in."""
    near = cv2.dilate(region.view(np.uint8), _CLOSE).astype(bool) & passable
    if not near.any():
        return region
    closed = cv2.morphologyEx(region.view(np.uint8), cv2.MORPH_CLOSE, _CLOSE).astype(bool)
    return region | (closed & passable)


def _region(
    inp: LeakInputs, seed: np.ndarray, thr: float
) -> tuple[np.ndarray, float, float, np.ndarray, tuple[int, int]]:
    """Half-maximum region, amplitude, local background, centre and maximum texel of one seed."""
    rows, cols = np.nonzero(seed)
    k = int(np.argmax(inp.smoothed[rows, cols]))
    i, j = int(rows[k]), int(cols[k])
    fit = fit_peak(inp.residual, inp.usable, i, j)
    peak, cx, cy = fit if fit is not None else (float(inp.smoothed[i, j]), j + 0.5, i + 0.5)
    peak, bg = max(peak, thr), 0.0
    sm = inp.smoothed
    region = _component(inp.usable & (sm >= 0.5 * peak), i, j, inp.passable)
    for _ in range(2):  # amplitude over the local background, then the half-maximum again
        sigma = max(math.sqrt(region.sum() / math.pi) / HALF_MAX_RADIUS, 0.7)
        ab = fit_amplitude(inp.residual, inp.usable, cx, cy, sigma)
        if ab is None or not 0.5 * peak <= ab[0] <= 2.0 * peak:
            break
        again = _component(inp.usable & (sm >= ab[1] + 0.5 * ab[0]), i, j, inp.passable)
        if not again.any():
            break
        (peak, bg), region = ab, again
    return region, peak, bg, np.array([cx, cy]), (i, j)


def _edge_effect(inp: LeakInputs, top: tuple[int, int], near_band: np.ndarray, size: float) -> bool:
    """The excess keeps rising toward the edge rather than forming a peak: the region's maximum
    lies on the polygon's outermost texels, or it touches the outermost observed texels (or the
    edge band) and the edge texels 0.8–1.2 m (at least 2–4 texels) from it are still warm
    (median ≥ 60 % of the maximum): a warm rim or a ramp along a cut, not a bump."""
    if not near_band[top]:
        return False
    if inp.outline[top]:
        return True  # on the polygon's outline: corners, eaves, mixed pixels of the silhouette
    i, j = top
    r0, r1 = max(2.0, 0.8 / size), max(4.0, 1.2 / size)
    R = math.ceil(r1)
    H, W = near_band.shape
    win = (slice(max(i - R, 0), min(i + R + 1, H)), slice(max(j - R, 0), min(j + R + 1, W)))
    yy, xx = np.mgrid[win]
    d = np.hypot(yy - i, xx - j)
    ring = (inp.band[win] | inp.edge[win]) & (d >= r0) & (d <= r1)
    if not ring.any():
        return True  # a small observed patch: nothing to compare with
    return float(np.median(inp.smoothed[win][ring])) >= 0.6 * float(inp.smoothed[top])


def find_leaks(
    inp: LeakInputs,
    frames_n: np.ndarray,
    region_frames: Callable[[np.ndarray], int],
    thr: float,
    size: float,
    o: AnomalyOptions,
) -> list[Region]:
    """Leak and bridge regions (module docstring), strongest first.

    Args:
        inp: per-texel inputs.
        frames_n: `(H, W)` int distinct frames per texel.
        region_frames: callable `mask -> number of distinct frames over mask`.
        thr: seed threshold over typical, kelvin.
        size: texel size, metres.
        o: options (`min_frames` already capped by the texture's kept observations).
    """
    seeds = inp.grow & (inp.smoothed > thr)
    n, lab = cv2.connectedComponents(seeds.view(np.uint8), connectivity=8)
    if n < 2:
        return []
    strength = np.full(n, -np.inf)
    np.maximum.at(strength, lab[seeds], inp.smoothed[seeds])
    done = np.zeros_like(seeds)
    near_band = cv2.dilate((inp.band | inp.edge).view(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    reach: list[tuple[np.ndarray, float]] = []  # found leaks: centre, reach of their tails (texels)
    out: list[Region] = []
    for k in np.argsort(-strength[1:]) + 1:
        seed = lab == k
        if (seed & done).any():
            continue
        region, peak, bg, centre, top = _region(inp, seed, thr)
        done |= seed | region
        if not region.any() or _edge_effect(inp, top, near_band, size):
            continue
        if any(np.hypot(top[1] + 0.5 - c[0], top[0] + 0.5 - c[1]) < r for c, r in reach):
            continue  # the tail of a stronger leak, seen past a window or a bridge
        pieces = [("leak", region, peak, bg, centre)] if peak >= MIN_AMPLITUDE * thr else []
        if is_line(region, size, o):
            pieces = [("bridge", region, float(inp.smoothed[top]), 0.0, centre)]
            core = _core(region, size)
            if core.any() and not is_line(core, size, o):
                region_c, peak_c, bg_c, centre_c, _ = _region(
                    inp, core & seeds if (core & seeds).any() else core, thr
                )
                if peak_c >= thr:  # the core stands out on its own, not only with the line
                    pieces.append(("leak", region_c & core, peak_c, bg_c, centre_c))
        for kind, m, pk, b, c in pieces:
            count = int(m.sum())
            if count < o.min_texels or count * size * size < o.min_area_m2:
                continue
            if region_frames(m) < o.min_frames or np.mean(frames_n[m] >= o.min_frames) < 0.5:
                continue
            mean = float(np.nanmean(inp.residual[m])) - b
            out.append(Region(m, float(pk), mean, c, kind, _closed(m, inp.passable)))
            if kind == "leak":
                reach.append((c, 3.0 * math.sqrt(count / math.pi)))
    return out

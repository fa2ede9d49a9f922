"""`analyse_surface`: typical value, windows, linear bridges and leak candidates of one surface.

In: a `TexelGrid` and its fused `SurfaceTexture` (kelvin), `AnomalyOptions`. Out: a
`SurfaceAnalysis`: the facade figures, the anomalies (`results.Anomaly`, 3D outlines in the
model CRS) and a label raster.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from workers.pipeline.anomalies import figures
from workers.pipeline.anomalies.leaks import (
    HALF_MAX_RADIUS,
    MIN_AMPLITUDE,
    LeakInputs,
    Region,
    find_leaks,
    fit_blob,
)
from workers.pipeline.anomalies.lines import line_profiles, narrow_lines, runs
from workers.pipeline.anomalies.options import AnomalyError, AnomalyOptions
from workers.pipeline.anomalies.outline import bbox, box_ring, outline, world_ring
from workers.pipeline.anomalies.typical import edge_band, frames_per_texel, robust_stats, smooth
from workers.pipeline.anomalies.windows import Window, find_windows
from workers.pipeline.results import Anomaly
from workers.pipeline.texture.fused import SurfaceTexture
from workers.pipeline.texture.texel import TexelGrid

OUTSIDE, NORMAL, WINDOW, LEAK, BRIDGE = 0, 1, 2, 3, 4
NAN = float("nan")


@dataclass(frozen=True, eq=False)
class SurfaceAnalysis:
    """The thermal analysis of one surface.

    Attributes:
        polygon_id, building_id: the surface.
        typical: robust typical value (median of the observed texels outside windows and
            candidates; NaN: fewer than `min_observed_texels` observed or analysis disabled).
        spread: 1.4826 · MAD of their residual (linear bridges removed); the leak threshold
            uses the finer spread below `spread_scale_m` (`docs/anomalies.md`).
        hot_share, window_share, heat_loss_index: `figures` (`docs/anomalies.md`).
        anomalies: windows, leaks and bridges, ids `<polygon_id>-<kind>-<n>` (n from 0, in
            reading order: top to bottom, left to right).
        labels: `(H, W)` uint8: 0 not observed/outside the mask, 1 observed normal, 2 window,
            3 leak, 4 bridge.
    """

    polygon_id: str
    building_id: str
    typical: float
    spread: float
    hot_share: float
    window_share: float
    heat_loss_index: float
    anomalies: tuple[Anomaly, ...]
    labels: np.ndarray

    def of_kind(self, kind: str) -> tuple[Anomaly, ...]:
        """The anomalies of one kind ("leak", "window", "bridge")."""
        return tuple(a for a in self.anomalies if a.kind == kind)


def _confidence(peak: float, thr: float, texels: int, frames: int, support: float) -> float:
    """`min(1, 0.5·peak/thr) · (1 − e^(−texels/9)) · (1 − 0.5^frames) · support` (0-1)."""
    c = min(1.0, 0.5 * peak / thr) * (1 - math.exp(-texels / 9.0)) * (1 - 0.5**frames) * support
    return max(0.0, min(1.0, float(c)))


def _line_bridges(col: np.ndarray, row: np.ndarray, usable: np.ndarray, thr: float) -> list[Region]:
    """Bridges found by the row/column profiles: runs of columns (rows) whose profile ≥ `thr`;
    region = their usable texels, outline box = their extent."""
    out = []
    for axis, prof in ((1, col), (0, row)):
        for a, b in runs(prof >= thr):
            band = np.zeros_like(usable)
            if axis == 1:
                band[:, a:b] = True
            else:
                band[a:b, :] = True
            m = band & usable
            if not m.any():
                continue
            ys, xs = np.nonzero(m)
            box = np.zeros_like(usable)
            box[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1] = True
            c = np.array([0.5 * (xs.min() + xs.max() + 1), 0.5 * (ys.min() + ys.max() + 1)])
            seg = prof[a:b]
            out.append(Region(m, float(seg.max()), float(seg.mean()), c, "bridge", box))
    return out


def _empty(grid: TexelGrid, labels: np.ndarray) -> SurfaceAnalysis:
    return SurfaceAnalysis(grid.polygon_id, grid.building_id, NAN, NAN, NAN, NAN, NAN, (), labels)


def analyse_surface(
    grid: TexelGrid, texture: SurfaceTexture, options: AnomalyOptions = AnomalyOptions()
) -> SurfaceAnalysis:
    """Figures, windows, bridges and leak candidates of one surface (package docstring)."""
    o = options
    if texture.value.shape != grid.shape:
        raise AnomalyError(f"texture shape {texture.value.shape} does not match grid {grid.shape}")
    size = grid.size
    value = texture.value.astype(np.float32)
    observed = grid.mask & np.isfinite(value)
    labels = np.where(observed, NORMAL, OUTSIDE).astype(np.uint8)
    if not o.enabled or observed.sum() < o.min_observed_texels:
        return _empty(grid, np.zeros_like(labels) if not o.enabled else labels)
    # 1. typical value, first pass over everything observed; windows; second pass without them
    t0 = float(np.median(value[observed][::3]))  # a first level for the window segmentation
    scan = find_windows(np.where(observed, value, np.nan), t0, size, o)
    windows, window_mask, exclusion = scan.windows, scan.window_mask, scan.exclusion
    keep = observed & ~exclusion
    if keep.sum() < o.min_observed_texels:
        keep = observed
    t1 = float(np.median(value[keep]))
    # 2. linear bridges along the texel axes (row/column profiles) leave the residual excess;
    # typical and spread from the texels whose residual is calm (no window, no candidate)
    col, row, residual = line_profiles(
        np.where(observed, value - t1, np.nan), keep, size, o.line_min_m, o.line_narrow_m
    )
    m1, s1 = robust_stats(residual[keep][::3])  # only to tell calm texels
    calm = keep & (np.abs(residual - m1) <= max(o.k_mad * s1, o.floor_k))
    if calm.sum() < o.min_observed_texels:
        calm = keep
    typical = float(np.median(value[calm]))
    shift, spread = robust_stats(residual[calm])
    residual -= shift
    excess = np.where(observed, value - typical, np.nan).astype(np.float32)

    # the threshold rests on the spread at scales below `spread_scale_m` (noise and texture):
    # gradients, seams and the leaks themselves do not raise it; its floor is a leak's ΔT as
    # the imaging blur shows it (`floor_attenuation`)
    floor = o.floor_k * floor_attenuation(texture, observed, o)
    thr = leak_threshold(residual, calm, size, replace(o, floor_k=floor))
    # 3. leak candidates on the residual; over window panes against the pane's own level
    panes = observed & np.isfinite(scan.pane_level) & ~keep
    residual[panes] = value[panes] - scan.pane_level[panes]
    usable = keep | panes
    band = edge_band(observed, round(o.edge_band_m / size))
    smoothed = np.nan_to_num(
        smooth(residual, usable, o.smooth_m / size if o.smooth_m >= size / 3 else 0.0), nan=-np.inf
    )
    edge = edge_band(observed, 1)
    on_outline = observed & edge_band(grid.mask, max(1, round(o.outline_band_m / size)))
    inp = LeakInputs(residual, smoothed, usable & ~band, band, usable, observed & ~usable, edge, on_outline)
    frames_n = frames_per_texel(texture.obs_frame)
    min_frames = min(o.min_frames, max(1, texture.obs_frame.shape[0]))
    o_eff = o if min_frames == o.min_frames else replace(o, min_frames=min_frames)

    def n_frames(m: np.ndarray) -> int:
        return _frames(texture, m)

    regions = find_leaks(inp, frames_n, n_frames, thr, size, o_eff)
    regions += [r for r in _line_bridges(col, row, keep, thr) if n_frames(r.mask) >= min_frames]
    # 3. anomalies, labels, figures
    found: list[tuple[str, Anomaly]] = []
    for w in windows:
        a = _window_anomaly(grid, texture, excess, observed, w)
        if a is not None:
            found.append(("window", a))
    leak_mask = np.zeros_like(observed)
    fit_on = (residual, usable)
    leaks = regions_mask(regions, "leak", observed)
    if leaks.any():  # the leaks' own heat out of the line profiles
        fit_on = (fit_residual(value - t1, observed, keep, leaks, size, o) - shift, usable)
        fit_on[0][panes] = residual[panes]
        if 3 * size <= o.line_width_m:  # pipes resolved: their texels out of the amplitude fit
            fit_on = (fit_on[0], usable & ~narrow_lines(col, row, MIN_AMPLITUDE * thr))
    for r in regions:
        a = _region_anomaly(grid, texture, r, frames_n, thr, min_frames, o, fit_on)
        if a is None:
            continue
        found.append((r.kind, a))
        if r.kind == "leak":
            leak_mask |= r.mask
    labels[regions_mask(regions, "bridge", observed)] = BRIDGE
    labels[window_mask & observed] = WINDOW
    labels[leak_mask] = LEAK
    return SurfaceAnalysis(
        polygon_id=grid.polygon_id,
        building_id=grid.building_id,
        typical=typical,
        spread=spread,
        hot_share=figures.hot_share(excess, observed, window_mask, o.hot_delta_k),
        window_share=figures.window_share(observed, window_mask),
        heat_loss_index=figures.heat_loss_index(residual, observed, leak_mask),
        anomalies=with_ids(grid, found),
        labels=labels,
    )


#: the fine spread of `leak_threshold` is measured on a calm area of at least a disk of this
#: radius, in units of `spread_scale_m` (bench, seeds 1 and 2: radii 1.7 and 2 find the same,
#: 2.45 one false leak more in the seed-2 leak-free flight, 2.8 one in each seed's; under 1.56
#: the errors drive's leak on a 1.1 m strip of wall is missed)
SPREAD_DISK = 2.0


def leak_threshold(residual: np.ndarray, calm: np.ndarray, size: float, o: AnomalyOptions) -> float:
    """Seed threshold (K): `max(k_mad · s_fine, floor_k)`, `s_fine` the robust spread over the
    `calm` texels `(H, W)` of the residual `(H, W)` less its Gaussian smoothing of σ
    `spread_scale_m` (noise and fine texture). A leak covering much of a small wall is "calm"
    in its tails, and its own curvature passes that high-pass: it would raise its own threshold
    (measured: 1.2 → 2.9 K on a 3 × 4 m wall with a 3.8 K leak). So the spread is taken once
    more without the texels within `spread_scale_m` of those whose residual exceeds half the
    first threshold, when enough calm texels remain; the threshold never rises by it.

    On a calm area smaller than a disk of radius `SPREAD_DISK · spread_scale_m` (4.5 m² for
    0.6 m: a strip of a wall seen 1.1 m tall, a small polygon) the high-pass keeps the
    structures of that scale themselves (a leak, part of a pane: measured 0.73 K of "spread",
    a threshold of 2.3 K, on a 2.8 × 1.1 m strip holding a 4 K leak): the floor alone applies."""
    if np.count_nonzero(calm) * size * size < math.pi * (SPREAD_DISK * o.spread_scale_m) ** 2:
        return o.floor_k
    fine = residual - smooth(residual, calm, o.spread_scale_m / size)
    thr = max(o.k_mad * robust_stats(fine[calm])[1], o.floor_k)
    warm = calm & (residual > 0.5 * thr)
    if not warm.any():
        return thr
    r = max(1, round(o.spread_scale_m / size))
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    quiet = calm & ~cv2.dilate(warm.view(np.uint8), disk).astype(bool)
    if quiet.sum() < o.min_observed_texels:
        return thr
    return min(thr, max(o.k_mad * robust_stats(fine[quiet])[1], o.floor_k))


def fit_residual(
    excess: np.ndarray,
    observed: np.ndarray,
    keep: np.ndarray,
    leaks: np.ndarray,
    size: float,
    o: AnomalyOptions,
) -> np.ndarray:
    """The residual `(H, W)` a leak's amplitude is fitted on: `excess (H, W)` (over the first
    typical value) less line profiles (`lines.line_profiles`) taken over the `keep (H, W)`
    texels (outside the window zone) farther than `spread_scale_m` from the `leaks (H, W)`
    (their half-maximum regions). A leak covering most of a half row or column (narrow walls,
    short columns) lifts that half's median: with the profiles of the detection step the fit
    would lose that part of the leak (`docs/anomalies.md`)."""
    r = max(1, round(o.spread_scale_m / size))
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    use = keep & ~cv2.dilate(leaks.view(np.uint8), disk).astype(bool)
    return line_profiles(np.where(observed, excess, np.nan), use, size, o.line_min_m)[2]


def floor_attenuation(texture: SurfaceTexture, observed: np.ndarray, o: AnomalyOptions) -> float:
    """Share 0-1 of a leak's ΔT that the texture shows at its peak for the smallest leak the
    floor is meant for (a Gaussian of σ `floor_sigma_m`): `σ² / sqrt((σ² + bl²)(σ² + bs²))`,
    `bl`, `bs` the imaging blur along and across the footprint (`imaging_blur_m`) at the
    median resolution and viewing angle of the `observed (H, W)` texels. The floor `floor_k`
    is a leak's ΔT; the blur conserves a blob's volume and lowers its peak by that share, so
    the seed threshold's floor is `floor_k` times it (with σ 0.45 m: about 0.7 on flights,
    0.4-0.5 m/px; 0.98-1 on drives). 1 when `floor_sigma_m` or `psf_sigma_px` is 0 or the resolution is
    unknown."""
    if o.floor_sigma_m <= 0 or o.psf_sigma_px <= 0:
        return 1.0
    res = texture.resolution[observed]
    res = res[np.isfinite(res)]
    if len(res) == 0:
        return 1.0
    ang = texture.view_angle[observed]
    ang = ang[np.isfinite(ang)]
    bl, bs = imaging_blur_m(float(np.median(res)), float(np.median(ang)) if len(ang) else 0.0, o.psf_sigma_px)
    s2 = o.floor_sigma_m**2
    return s2 / math.sqrt((s2 + bl * bl) * (s2 + bs * bs))


def regions_mask(regions: list[Region], kind: str, observed: np.ndarray) -> np.ndarray:
    """Union `(H, W)` of the masks of the regions of one kind, within `observed`."""
    m = np.zeros_like(observed)
    for r in regions:
        if r.kind == kind:
            m |= r.mask
    return m & observed


def _window_anomaly(
    grid: TexelGrid, texture: SurfaceTexture, excess: np.ndarray, observed: np.ndarray, w: Window
) -> Anomaly | None:
    H, W = grid.shape
    around = grid.mask[max(w.y0 - 1, 0) : w.y1 + 1, max(w.x0 - 1, 0) : w.x1 + 1]
    if w.x0 > 0 and w.y0 > 0 and w.x1 < W and w.y1 < H and around.all():
        ring, area = world_ring(grid, box_ring(w.x0, w.y0, w.x1, w.y1))
    else:  # next to the polygon outline: traced and kept inside
        box = np.zeros_like(observed)
        box[w.box] = True
        res = outline(grid, box)
        if res is None:
            return None
        ring, area = res
    obs = observed[w.box]
    e = excess[w.box][obs]
    if len(e) == 0:
        return None
    k = int(0.1 * (len(e) - 1))
    peak = float(np.partition(e, k)[k] if w.sign < 0 else -np.partition(-e, k)[k])
    centre = grid.points_at(np.array([[0.5 * (w.x0 + w.x1), 0.5 * (w.y0 + w.y1)]]))[0]
    f = texture.obs_frame[(slice(None), *w.box)][:, obs]
    res_m = texture.resolution[w.box][obs]
    conf = w.fill * max(0.25, 1 - 0.5 ** (w.group - 1))
    return Anomaly(
        grid.building_id, grid.polygon_id, ring, centre, area, peak, float(e.mean()), "window",
        frames=len(np.unique(f[f >= 0])), best_resolution_m=_min_finite(res_m), confidence=conf,
    )  # fmt: skip


def _region_anomaly(
    grid: TexelGrid,
    texture: SurfaceTexture,
    r: Region,
    frames_n: np.ndarray,
    thr: float,
    min_frames: int,
    o: AnomalyOptions,
    fit_on: tuple[np.ndarray, np.ndarray],
) -> Anomaly | None:
    """The anomaly of one region; a leak's ΔT is the amplitude of the blob before the imaging
    blur (`leaks.fit_blob` on `fit_on` = (residual, usable texels); `blur_gain` on the measured
    amplitude when that fit finds no background)."""
    res = outline(grid, r.shape)
    if res is None:
        return None
    ring, area = res
    frames = _frames(texture, r.mask)
    support = float(np.mean(frames_n[r.mask] >= min_frames))
    conf = _confidence(r.peak, thr, int(r.mask.sum()), frames, support)
    centre_xy = r.centre_xy
    best = _best_res(texture, r.mask)
    k = 1.0
    if r.kind == "leak" and o.psf_sigma_px > 0:
        b_long, b_short = region_blur_m(texture, r.mask, o.psf_sigma_px)
        n = float(r.mask.sum())
        k = blur_gain(n * grid.size**2, b_long, b_short)
        sigma_obs = math.sqrt(n / math.pi) / HALF_MAX_RADIUS
        blob = fit_blob(*fit_on, *r.centre_xy, sigma_obs, b_long / grid.size, b_short / grid.size)
        if blob is not None and r.peak > 0:
            k = min(blob[0] / r.peak, BLUR_GAIN_CAP)
            centre_xy = np.array(blob[3:])
    centre = grid.points_at(centre_xy[None])[0]
    return Anomaly(
        grid.building_id, grid.polygon_id, ring, centre, area, r.peak * k, r.mean * k, r.kind,
        frames=frames, best_resolution_m=best, confidence=conf,
    )  # fmt: skip


#: the largest factor a blur correction applies (a blob hardly larger than the blur is not
#: resolved: its ΔT is unknown)
BLUR_GAIN_CAP = 3.0

#: variance, in pixels², of the blur one observation adds besides the optics: the pixel's area
#: (a box of one pixel: 1/12) and the bilinear resampling of the image at the texel centre (a
#: triangle of two pixels: 1/6)
PIXEL_VAR_PX2 = 1.0 / 12.0 + 1.0 / 6.0


def imaging_blur_m(resolution_m: float, view_angle_deg: float, psf_sigma_px: float) -> tuple[float, float]:
    """σ (m) of the blur one observation puts on the surface, along the footprint's long axis
    (the local resolution `resolution_m`, m/px, is the coarser of the two surface axes) and its
    short axis (foreshortened by the cosine of the viewing angle): `res · sqrt(psf² + 1/12 +
    1/6)` (optics, pixel area, bilinear resampling), times `cos(view angle)` across.

    >>> [round(v, 3) for v in imaging_blur_m(0.5, 60.0, 0.6)]
    [0.391, 0.195]
    """
    k = resolution_m * math.sqrt(psf_sigma_px**2 + PIXEL_VAR_PX2)
    c = math.cos(math.radians(view_angle_deg)) if math.isfinite(view_angle_deg) else 1.0
    return k, k * max(c, 0.0)


def region_blur_m(texture: SurfaceTexture, m: np.ndarray, psf_sigma_px: float) -> tuple[float, float]:
    """σ (m) of the blur of the fused texture over the region `m (H, W)`, as one round blur
    (both returned values equal; (0, 0) when unknown).

    A fused texel is the mean of the observations within `FusedOptions.blend_ratio` of its best
    resolution, weighted by 1 / resolution²; its blur is that mean of their blurs (of their
    covariances), not the best observation's. Each observation's is `imaging_blur_m` of its own
    resolution and viewing angle (σl along its footprint, σl · cos across), taken round,
    `(σl² + σs²) / 2`: the frames see a texel from different directions. The region's blur is
    the median over its texels. The observations a texel keeps (`obs_res`, `obs_angle`)
    decide; without them (inf) the texel's best observation (`resolution`, `view_angle`).

    Until session 12 it was the best observation alone, σl along and σs across. On the bench
    flights (seeds 1 / 2) the round blur that matches the truth field to the fused texture
    around the observed leaks has a median of 0.35 m, the old model's round equivalent (its
    geometric mean) 0.30 / 0.31 m, this one 0.32 m; the leaks' ΔT error median 0.360 / 0.277 →
    0.306 / 0.224 K (the best observation's blur taken round alone: 0.354 / 0.263 K)."""
    b = bbox(m)
    if b is None:
        return 0.0, 0.0
    k2 = psf_sigma_px**2 + PIXEL_VAR_PX2
    res = texture.obs_res[(slice(None), *b)][:, m[b]].astype(np.float64)  # (K, N)
    ang = texture.obs_angle[(slice(None), *b)][:, m[b]].astype(np.float64)
    best = np.min(res, axis=0) if len(res) else np.full(int(m[b].sum()), np.inf)
    if not np.isfinite(best).any():  # no kept observations recorded: the best one
        res = texture.resolution[b][m[b]][None].astype(np.float64)
        ang = texture.view_angle[b][m[b]][None].astype(np.float64)
        best = res[0]
    ratio = texture.options.blend_ratio
    use = np.isfinite(res) & (res <= best * ratio)
    w = np.where(use, 1.0 / np.maximum(np.where(use, res, 1.0), 1e-9) ** 2, 0.0)
    cos2 = np.cos(np.radians(np.where(np.isfinite(ang), ang, 0.0))) ** 2
    var = np.where(use, k2 * np.where(use, res, 0.0) ** 2 * 0.5 * (1.0 + cos2), 0.0)
    wsum = w.sum(axis=0)
    ok = wsum > 0
    if not ok.any():
        return 0.0, 0.0
    sigma = math.sqrt(float(np.median((w * var).sum(axis=0)[ok] / wsum[ok])))
    return sigma, sigma


def blur_gain(area_m2: float, blur_long_m: float, blur_short_m: float, cap: float = BLUR_GAIN_CAP) -> float:
    """Factor restoring the amplitude of a round Gaussian blob seen through a Gaussian blur of σ
    `blur_long_m` along one axis and `blur_short_m` across: the blur conserves the blob's volume,
    `A σ² = A_obs σx σy` with `σx² = σ² + bl²`, `σy² = σ² + bs²`, and `σx σy` is measured by the
    half-maximum area (`area = 2 ln 2 · π σx σy`); σ² solves `(σ² + bl²)(σ² + bs²) = (σx σy)²`.
    At most `cap` (a blob hardly larger than the blur is not resolved: its ΔT is unknown).

    >>> round(blur_gain(math.pi * 2 * math.log(2) * 0.5**2, 0.3, 0.3), 2)
    1.56
    >>> blur_gain(1.0, 0.0, 0.0)
    1.0
    """
    s = area_m2 / (math.pi * 2 * math.log(2))  # σx σy
    a2, b2 = blur_long_m**2, blur_short_m**2
    u = 0.5 * (-(a2 + b2) + math.sqrt((a2 - b2) ** 2 + 4 * s * s))  # σ² of the blob
    return cap if u <= s / cap else min(cap, s / u)


def _min_finite(r: np.ndarray) -> float:
    r = r[np.isfinite(r)]
    return float(r.min()) if len(r) else NAN


def _best_res(texture: SurfaceTexture, m: np.ndarray) -> float:
    b = bbox(m)
    return _min_finite(texture.resolution[b][m[b]]) if b is not None else NAN


def _frames(texture: SurfaceTexture, m: np.ndarray) -> int:
    """Distinct frames among the kept observations of the texels of `m (H, W)`."""
    b = bbox(m)
    if b is None:
        return 0
    f = texture.obs_frame[:, b[0], b[1]][:, m[b]]
    return len(np.unique(f[f >= 0]))


def with_ids(grid: TexelGrid, found: list[tuple[str, Anomaly]]) -> tuple[Anomaly, ...]:
    """Ids `<polygon_id>-<kind>-<n>` numbered per kind in reading order of the centres (rows of
    half a metre from the top, then left to right)."""
    if not found:
        return ()
    xy = grid.raster_xy(np.array([a.centre for _, a in found])) * grid.size
    out: list[Anomaly] = []
    for kind in ("window", "leak", "bridge"):
        idx = [i for i, (k, _) in enumerate(found) if k == kind]
        idx.sort(key=lambda i: (int(xy[i, 1] // 0.5), float(xy[i, 0]), float(xy[i, 1])))
        for n, i in enumerate(idx):
            out.append(replace(found[i][1], kind=kind, id=f"{grid.polygon_id}-{kind}-{n}"))
    return tuple(out)

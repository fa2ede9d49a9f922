"""Windows: rectangle-like blobs that deviate from the typical value and form a regular structure.

In: the values `(H, W)` (NaN: not observed), a first typical value, texel size, options. Out: a `WindowScan`:
the accepted windows (`Window`, texel boxes), the exclusion zone of leak seeds: every cold
rectangle-like blob of window size (accepted or not) and every accepted warm one, as its
bounding box dilated by `window_margin_m` (frames are warm), and the level of each such pane.

Regular structure (Hoegner & Stilla find windows as regular structures among segmented blobs):
two blobs are linked when they have a similar size (each side within 20 % + 1 texel) and sit in
one row (centres within a quarter of the height) or one column; a linked group of at least
`window_min_count` blobs whose column and row positions lie on a lattice (each position an
integer multiple of the smallest spacing, ±20 %) is a window group. A cold blob outside any group
is a window too when it is a clean rectangle (`window_lone_fill`) of 0.6–2.5 m a side.

Coarse textures (`coarse`: flights), where the imaging blur decides a small pane's segmented
shape: cold local minima also give pane candidates by their half-depth regions, measured
sub-texel (`half_depth_extent`), linked with one texel more of slack (`_blurred_blobs`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy import ndimage

from workers.pipeline.anomalies.options import AnomalyOptions

_CORNERS = 6.0  # texels a cold pane's segmented blob may miss at its blurred corners


@dataclass(frozen=True)
class Window:
    """A detected window pane: texel box rows `y0:y1`, columns `x0:x1` (end exclusive)."""

    x0: int
    y0: int
    x1: int
    y1: int
    sign: int  # -1 colder than typical, +1 warmer
    fill: float  # share of the box the blob fills
    group: int  # size of its regular group
    blurred: bool = False  # found on a coarse texture by its half-depth region (`_blurred_blobs`)
    extent: tuple[float, float] = (0.0, 0.0)  # its half-depth width and height, texels (blurred)
    depth: float = 0.0  # the depth of its local extremum, K (blurred)

    @property
    def box(self) -> tuple[slice, slice]:
        return slice(self.y0, self.y1), slice(self.x0, self.x1)


def _blobs(excess: np.ndarray, sign: int, size: float, o: AnomalyOptions) -> list[Window]:
    """Rectangle-like blobs of window size whose `sign · excess` ≥ `window_delta_k`."""
    seg = np.nan_to_num(sign * excess, nan=-np.inf) >= o.window_delta_k
    n, lab = cv2.connectedComponents(seg.view(np.uint8), connectivity=4)
    if n < 2:
        return []
    lo = max(o.window_min_texels, math.ceil(o.window_min_m / size - 1e-9))
    hi = o.window_max_m / size
    areas = np.bincount(lab.ravel(), minlength=n)
    out = []
    for k, box in enumerate(ndimage.find_objects(lab), start=1):
        if box is None or areas[k] < lo * lo:
            continue
        y, x = box[0].start, box[1].start
        h, w = box[0].stop - y, box[1].stop - x
        if not (lo <= w <= hi and lo <= h <= hi):
            continue
        fill = areas[k] / (w * h)
        corners = _CORNERS / (w * h) if sign < 0 else 0.0  # cold panes: blurred corners forgiven
        if fill >= o.window_fill - corners:
            out.append(Window(x, y, x + w, y + h, sign, float(fill), 0))
    return out


def coarse(size: float, o: AnomalyOptions) -> bool:
    """Whether a texture is coarse for windows: the smallest pane (`window_min_m`) spans fewer
    than `window_min_texels` texels, so that the imaging blur (about a texel there) decides a
    pane's segmented shape more than the pane does."""
    return o.window_min_m < o.window_min_texels * size


def _blurred_blobs(
    excess: np.ndarray, sign: int, size: float, o: AnomalyOptions, delta: float
) -> list[Window]:
    """Pane candidates of a coarse texture (`coarse`): every local extremum of `sign · excess`
    (3 × 3) of at least `window_delta_k`, strongest first, with the texels 4-connected to it at
    half its depth or more (its half-depth region; a blurred box's half-depth contour lies near
    the box's edge). Kept when its half-depth extents (`half_depth_extent`, sub-texel) reach
    `window_min_texels − 1` texels and `window_min_m` and stay under `window_max_m` on both
    sides. They carry no rectangle evidence of their own (`fill` is the region's share of its
    box): a regular group, or the lone-pane rule on their extents (`_lone_pane`), makes them
    windows (`find_windows`)."""
    d = np.nan_to_num(sign * excess, nan=0.0).astype(np.float32)
    peak = (d >= delta) & (d >= cv2.dilate(d, np.ones((3, 3), np.uint8)))
    H, W = d.shape
    lo = max(o.window_min_texels - 1.0, o.window_min_m / size)
    hi = o.window_max_m / size
    R = math.ceil(hi) + 1
    taken = np.zeros(d.shape, bool)
    out = []
    for k in np.argsort(-d[peak]):
        i, j = (int(v[k]) for v in np.nonzero(peak))
        if taken[i, j]:
            continue
        win = (slice(max(i - R, 0), min(i + R + 1, H)), slice(max(j - R, 0), min(j + R + 1, W)))
        _, lab = cv2.connectedComponents((d[win] >= 0.5 * d[i, j]).view(np.uint8), connectivity=4)
        region = lab == lab[i - win[0].start, j - win[1].start]
        ys, xs = np.nonzero(region)
        y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
        taken[win] |= region
        grown = np.maximum(d[win][max(y0 - 1, 0) : y1 + 1, max(x0 - 1, 0) : x1 + 1], 0.0)
        bw, bh = half_depth_extent(grown.max(axis=0)), half_depth_extent(grown.max(axis=1))
        if not (lo <= min(bw, bh) and max(bw, bh) <= hi):
            continue
        fill = float(region.sum()) / ((y1 - y0) * (x1 - x0))
        y, x = int(y0) + win[0].start, int(x0) + win[1].start
        out.append(
            Window(x, y, x + int(x1 - x0), y + int(y1 - y0), sign, fill, 0, True, (bw, bh), float(d[i, j]))
        )
    return out


def half_depth_extent(profile: np.ndarray) -> float:
    """Width (texels, sub-texel) of the part of a 1D `profile` (≥ 0, a blob's depth per column
    or row) at or above half its maximum: the whole texels from the first to the last above it
    plus, at each end, the fraction of the step to the next texel where the linear interpolation
    crosses half the maximum, less half a texel (a box of width L blurred by a Gaussian of σ <
    L/2 has a half-depth width ≈ L, whatever the phase of the texel grid).

    >>> round(half_depth_extent(np.array([0.0, 0.6, 1.5, 1.6, 0.6, 0.0])), 2)
    2.58
    """
    p = np.nan_to_num(np.asarray(profile, np.float64), nan=0.0)
    half = 0.5 * float(p.max())
    above = np.flatnonzero(p >= half)
    a, b = int(above[0]), int(above[-1])
    width = float(b - a + 1)
    for inner, outer in ((a, a - 1), (b, b + 1)):
        if 0 <= outer < len(p) and p[inner] > p[outer]:
            width += min(1.0, (p[inner] - half) / (p[inner] - p[outer])) - 0.5
    return float(width)


def _lone_pane(w: Window, size: float, o: AnomalyOptions) -> bool:
    """A cold blob outside any group that is still a window: fill ≥ `window_lone_fill`, sides
    0.6–2.5 m (a facade seen in part often shows one window only); a blurred blob (coarse
    texture: no fill to judge) by its half-depth extents, when `window_lone_fill` < 1."""
    lo, hi = max(0.6, o.window_min_m), min(2.5, o.window_max_m)
    if w.blurred:
        return (
            o.window_lone_fill < 1
            and w.depth >= o.window_delta_k
            and all(lo <= v * size <= hi for v in w.extent)
        )
    sides = ((w.x1 - w.x0) * size, (w.y1 - w.y0) * size)
    corners = _CORNERS / ((w.x1 - w.x0) * (w.y1 - w.y0))  # blurred corners forgiven, as in `_blobs`
    return w.fill >= o.window_lone_fill - corners and all(lo <= v <= hi for v in sides)


def _on_lattice(pos: np.ndarray, tol_px: float) -> bool:
    """Positions `(N,)` (texels) cluster into lines (gaps > `tol_px`) whose spacings are integer
    multiples of one pitch, within 20 % of it plus a texel.

    >>> _on_lattice(np.array([11.0, 24, 36, 48.5, 61]), 2.5), _on_lattice(np.array([0.0, 30, 42, 90]), 1)
    (True, False)
    """
    p = np.sort(pos)
    groups = [[p[0]]]
    for v in p[1:]:
        if v - groups[-1][-1] > tol_px:
            groups.append([])
        groups[-1].append(v)
    if len(groups) < 3:
        return True
    c = np.array([np.mean(g) for g in groups])
    span = c[-1] - c[0]
    pitch = span / max(1, round(span / float(np.min(np.diff(c)))))
    q = (c - c[0]) / pitch
    return bool(np.all(np.abs(q - np.round(q)) * pitch <= 0.2 * pitch + 1.0))


def _regular(blobs: list[Window], min_count: int) -> list[Window]:
    """The blobs belonging to regular groups (module docstring), with their group size."""
    n = len(blobs)
    if n < min_count:
        return []
    b = np.array([[w.x0, w.y0, w.x1, w.y1] for w in blobs], dtype=np.float64)
    w, h = b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]
    cx, cy = 0.5 * (b[:, 0] + b[:, 2]), 0.5 * (b[:, 1] + b[:, 3])
    sim_w = np.abs(w[:, None] - w[None]) <= 0.2 * np.maximum(w[:, None], w[None]) + 1
    sim_h = np.abs(h[:, None] - h[None]) <= 0.2 * np.maximum(h[:, None], h[None]) + 1
    slack = 0.5 + np.array([blob.blurred for blob in blobs], float)  # a blurred box: ± a texel more
    slack = np.maximum(slack[:, None], slack[None])
    row = np.abs(cy[:, None] - cy[None]) <= 0.25 * np.maximum(h[:, None], h[None]) + slack
    col = np.abs(cx[:, None] - cx[None]) <= 0.25 * np.maximum(w[:, None], w[None]) + slack
    link = sim_w & sim_h & (row | col)
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in zip(*np.nonzero(np.triu(link, 1)), strict=True):
        parent[find(int(i))] = find(int(j))
    roots = np.array([find(i) for i in range(n)])
    out = []
    for r in np.unique(roots):
        m = np.flatnonzero(roots == r)
        if len(m) < min_count:
            continue
        if not (_on_lattice(cx[m], 0.5 * w[m].mean()) and _on_lattice(cy[m], 0.5 * h[m].mean())):
            continue
        out += [replace(blobs[i], group=len(m)) for i in m]
    return out


@dataclass(frozen=True, eq=False)
class WindowScan:
    """What `find_windows` found on one surface.

    Attributes:
        windows: accepted panes, row-major by their boxes.
        window_mask: `(H, W)` bool, the accepted panes' boxes.
        exclusion: `(H, W)` bool, texels leak detection does not seed in (module docstring).
        pane_level: `(H, W)` float32, inside the cores of the excluded panes (boxes less their
            outer texel) the level of the panes (median over all panes of one sign, radiometry
            unit), NaN elsewhere: a leak reaching over a pane is measured against the panes.
    """

    windows: list[Window]
    window_mask: np.ndarray
    exclusion: np.ndarray
    pane_level: np.ndarray


def find_windows(values: np.ndarray, typical: float, size: float, o: AnomalyOptions) -> WindowScan:
    """Windows of one surface: `values (H, W)` float32 (NaN: not observed), a first `typical`
    value, texel size (m), options."""
    shape = values.shape
    window_mask = np.zeros(shape, bool)
    exclusion = np.zeros(shape, bool)
    pane_level = np.full(shape, np.nan, np.float32)
    if not o.windows:
        return WindowScan([], window_mask, exclusion, pane_level)
    excess = values - np.float32(typical)
    windows: list[Window] = []
    for sign in (-1, 1):
        blobs = _blobs(excess, sign, size, o)
        if sign < 0 and coarse(size, o):  # blurred panes, not already segmented as blobs
            seen = np.zeros(shape, bool)
            for w in blobs:
                seen[w.box] = True
            delta = min(o.window_delta_k, o.window_coarse_delta_k)
            blobs += [w for w in _blurred_blobs(excess, sign, size, o, delta) if not seen[w.box].any()]
        regular = _regular(blobs, o.window_min_count)
        if sign < 0:  # a lone cold pane: a clean rectangle of a window's size
            grouped = {(w.x0, w.y0) for w in regular}
            regular += [w for w in blobs if (w.x0, w.y0) not in grouped and _lone_pane(w, size, o)]
        windows += regular
        panes = np.zeros(shape, bool)
        accepted = {(w.x0, w.y0, w.x1, w.y1) for w in regular}
        for w in blobs if sign < 0 else regular:
            if w.blurred and w.depth < o.window_delta_k and (w.x0, w.y0, w.x1, w.y1) not in accepted:
                continue  # a shallow minimum outside a regular group: not a pane
            exclusion[w.box] = True
            panes[w.y0 + 1 : w.y1 - 1, w.x0 + 1 : w.x1 - 1] = True
        panes &= np.isfinite(values)
        if panes.sum() >= 4:  # one level for all panes of a sign: a leak on one pane does not move it
            pane_level[panes] = np.median(values[panes])
    for w in windows:
        window_mask[w.box] = True
    margin = max(1, math.ceil(o.window_margin_m / size - 1e-9))
    if exclusion.any():
        kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
        exclusion = cv2.dilate(exclusion.view(np.uint8), kernel).astype(bool)
    windows.sort(key=lambda w: (w.y0, w.x0))
    return WindowScan(windows, window_mask, exclusion, pane_level)

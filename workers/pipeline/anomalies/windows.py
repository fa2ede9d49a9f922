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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from workers.pipeline.anomalies.options import AnomalyOptions


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
        corners = 6.0 / (w * h) if sign < 0 else 0.0  # cold panes: blurred corners forgiven
        if fill >= o.window_fill - corners:
            out.append(Window(x, y, x + w, y + h, sign, float(fill), 0))
    return out


def _lone_pane(w: Window, size: float, o: AnomalyOptions) -> bool:
    """A cold blob outside any group that is still a window: fill ≥ `window_lone_fill`, sides
    0.6–2.5 m (a facade seen in part often shows one window only)."""
    lo, hi = max(0.6, o.window_min_m), min(2.5, o.window_max_m)
    sides = ((w.x1 - w.x0) * size, (w.y1 - w.y0) * size)
    return w.fill >= o.window_lone_fill and all(lo <= v <= hi for v in sides)


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
    row = np.abs(cy[:, None] - cy[None]) <= 0.25 * np.maximum(h[:, None], h[None]) + 0.5
    col = np.abs(cx[:, None] - cx[None]) <= 0.25 * np.maximum(w[:, None], w[None]) + 0.5
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
        out += [Window(*(int(v) for v in b[i]), blobs[i].sign, blobs[i].fill, len(m)) for i in m]
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
        regular = _regular(blobs, o.window_min_count)
        if sign < 0:  # a lone cold pane: a clean rectangle of a window's size
            grouped = {(w.x0, w.y0) for w in regular}
            regular += [w for w in blobs if (w.x0, w.y0) not in grouped and _lone_pane(w, size, o)]
        windows += regular
        panes = np.zeros(shape, bool)
        for w in blobs if sign < 0 else regular:
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

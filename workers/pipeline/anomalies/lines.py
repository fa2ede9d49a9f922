"""Linear thermal bridges along the texel axes: heating pipes (vertical), floor slabs
(horizontal), building corners (the wall's vertical edges).

In: the excess over typical `(H, W)`, the texels a profile may use (observed, outside windows),
texel size, options. Out: a column profile `(W,)` and a row profile `(H,)` of the excess, and
the residual excess with their positive parts removed, so that a compact leak on a pipe stands
out on its own and a line never seeds a leak.

A column's profile is the smaller of the medians of its upper and lower half (by the count of
usable texels); each half needs `line_min_m` of usable length, else the profile is 0. A line
runs through both halves; a leak lifts the median of a half only where it covers most of it, and
of both halves only on columns barely longer than itself, so it is not taken for a line. Rows
are profiled the same way after the columns are removed.

Short columns (rows), whose halves hold fewer than `line_min_m` but at least 3 usable texels
(a narrow wall: its rows; with `narrow_m` > 0), get only the narrow part of that profile: what
a window of `narrow_m` on either side of each entry (0.7 m wide for 0.3 m at 0.1 m texels) opens
away (a white top-hat, `narrow_part`). A slab line or pipe (σ 0.08-0.15 m: 0.6 m wide at 2σ)
goes whole, shoulders included; a leak's broad bump (σ ≥ 0.3 m), which lifts the profile of a
short row it covers, loses at most its top over its value `narrow_m` away (39 % for σ 0.3 m,
16 % for σ 0.5 m), and a ramp nothing, so they stay in the residual.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

_PERCENTILE = 0.5  # the median of each half
_MIN_SHORT = 3  # usable texels in each half a short column (row) needs for its narrow part


def _halves(excess: np.ndarray, usable: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column of `excess (H, W)`: the medians `(2, W)` of its upper and lower half of
    `usable (H, W)` texels (by their count; inf for an empty half) and the counts `(2, W)`."""
    cum = np.cumsum(usable, axis=0)
    upper = usable & (2 * cum <= cum[-1][None])
    med, cnt = [], []
    for half in (upper, usable & ~upper):
        c = half.sum(axis=0)
        srt = np.sort(np.where(half, excess, np.inf), axis=0)
        k = np.clip((_PERCENTILE * (c - 1)).astype(np.int64), 0, excess.shape[0] - 1)
        med.append(np.take_along_axis(srt, k[None], axis=0)[0])
        cnt.append(c)
    return np.array(med), np.array(cnt)


def _profile(excess: np.ndarray, usable: np.ndarray, min_half: int, narrow: int = 0) -> np.ndarray:
    """Per column of `excess (H, W)`: min over the two halves of their median (see module);
    `narrow` > 0: short columns (halves of 3 to `min_half` − 1 texels) get the part of that
    profile narrower than `2 · narrow + 1` columns (`narrow_part`)."""
    med, cnt = _halves(excess, usable)
    out = np.min(np.where(cnt >= min_half, med, 0.0), axis=0)
    least = cnt.min(axis=0)
    short = (least < min_half) & (least >= _MIN_SHORT)
    if narrow > 0 and short.any():
        relaxed = np.where(least >= _MIN_SHORT, med.min(axis=0), np.nan)
        out = np.where(short, narrow_part(relaxed, narrow), out)
    return np.where(np.isfinite(out), out, 0.0).astype(np.float32)


def narrow_part(profile: np.ndarray, half: int) -> np.ndarray:
    """The part `(N,)` of a profile `(N,)` (NaN: undefined) narrower than `2 · half + 1`
    entries: the profile less its grey opening with a flat window of that width (a white
    top-hat; undefined entries are left out of the window); 0 where fewer than half of the
    `half` entries on either side are defined (a profile's end is not a peak) or the entry is
    undefined. A line narrower than the window keeps all of its height, shoulders included; a
    bump much wider than the window, or a ramp, hardly any.

    >>> narrow_part(np.array([0, 0, 0, 1, 2, 1, 0, 0, 0.]), 2).tolist()  # a line
    [0.0, 0.0, 0.0, 1.0, 2.0, 1.0, 0.0, 0.0, 0.0]
    >>> bump = 3 * np.exp(-0.5 * (np.arange(21) - 10.0) ** 2 / 5**2)
    >>> round(float(narrow_part(bump, 3)[10]), 2)  # its top over its value 3 entries away
    0.49
    """
    p = np.asarray(profile, np.float64)
    defined = np.isfinite(p)
    size = 2 * half + 1
    eroded = ndimage.minimum_filter1d(np.where(defined, p, np.inf), size, mode="constant", cval=np.inf)
    opened = ndimage.maximum_filter1d(
        np.where(np.isfinite(eroded), eroded, -np.inf), size, mode="constant", cval=-np.inf
    )
    n = np.concatenate([[0], np.cumsum(defined)])
    idx = np.arange(len(p))
    before = n[idx] - n[np.maximum(idx - half, 0)]
    after = n[np.minimum(idx + half + 1, len(p))] - n[idx + 1]
    need = max(1, (half + 1) // 2)
    ok = defined & (before >= need) & (after >= need)
    return np.where(ok, p - np.where(ok, opened, 0.0), 0.0).astype(np.float32)


def narrow_lines(col: np.ndarray, row: np.ndarray, level: float) -> np.ndarray:
    """`(H, W)` bool: the columns (rows) of a raster whose profile `col (W,)` (`row (H,)`) stands
    at least `level` above the profile one entry away on either side (`narrow_part` with a
    window of 3), with their neighbours: a line one or two texels wide (a heating pipe resolved
    by 0.1 m texels: its narrow top is 0.54 × its ΔT), where a leak's broad bump loses at most
    `1 − exp(−1/2σ²)` of its top (5 % for σ of 3 texels).

    >>> narrow_lines(np.array([0, 0, 1.5, 0, 0.]), np.zeros(2), 1.0).astype(int).tolist()
    [[0, 1, 1, 1, 0], [0, 1, 1, 1, 0]]
    """
    c = narrow_part(np.asarray(col, np.float64), 1) >= level
    r = narrow_part(np.asarray(row, np.float64), 1) >= level
    c = c | np.concatenate([c[1:], [False]]) | np.concatenate([[False], c[:-1]])
    r = r | np.concatenate([r[1:], [False]]) | np.concatenate([[False], r[:-1]])
    return c[None, :] | r[:, None]


def line_profiles(
    excess: np.ndarray, usable: np.ndarray, size: float, line_min_m: float, narrow_m: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Column profile `(W,)`, row profile `(H,)` (kelvin over typical, ≥ 0 where a line may be)
    and the residual `(H, W)` = excess − positive parts of both (NaN where `excess` is NaN).
    `narrow_m` > 0: short columns (rows) get the narrow part of their profile (module)."""
    min_half = max(_MIN_SHORT, int(np.ceil(line_min_m / size)))
    narrow = max(1, math.floor(narrow_m / size + 1e-6)) if narrow_m > 0 else 0
    e = np.nan_to_num(excess, nan=0.0).astype(np.float32)
    ok = usable & np.isfinite(excess)
    col = _profile(e, ok, min_half, narrow)
    e_col = e - np.maximum(col, 0)[None, :]
    row = _profile(e_col.T, ok.T, min_half, narrow)
    residual = e_col - np.maximum(row, 0)[:, None]
    return col, row, np.where(np.isfinite(excess), residual, np.nan).astype(np.float32)


def runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """Runs `[start, end)` of consecutive True entries of a 1D bool array.

    >>> runs(np.array([0, 1, 1, 0, 1], bool))
    [(1, 3), (4, 5)]
    """
    f = np.concatenate(([False], np.asarray(flags, bool), [False]))
    d = np.flatnonzero(f[1:] != f[:-1])
    return [(int(a), int(b)) for a, b in zip(d[::2], d[1::2], strict=True)]

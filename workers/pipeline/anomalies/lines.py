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
"""

from __future__ import annotations

import numpy as np

_PERCENTILE = 0.5  # the median of each half


def _profile(excess: np.ndarray, usable: np.ndarray, min_half: int) -> np.ndarray:
    """Per column of `excess (H, W)`: min over the two halves of their median (see module)."""
    cum = np.cumsum(usable, axis=0)
    n = cum[-1]
    upper = usable & (2 * cum <= n[None])
    lower = usable & ~upper
    out = np.full(excess.shape[1], np.inf, np.float32)
    for half in (upper, lower):
        cnt = half.sum(axis=0)
        srt = np.sort(np.where(half, excess, np.inf), axis=0)
        k = np.clip((_PERCENTILE * (cnt - 1)).astype(np.int64), 0, excess.shape[0] - 1)
        p = np.take_along_axis(srt, k[None], axis=0)[0]
        out = np.minimum(out, np.where(cnt >= min_half, p, 0.0))
    return np.where(np.isfinite(out), out, 0.0).astype(np.float32)


def line_profiles(
    excess: np.ndarray, usable: np.ndarray, size: float, line_min_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Column profile `(W,)`, row profile `(H,)` (kelvin over typical, ≥ 0 where a line may be)
    and the residual `(H, W)` = excess − positive parts of both (NaN where `excess` is NaN)."""
    min_half = max(3, int(np.ceil(line_min_m / size)))
    e = np.nan_to_num(excess, nan=0.0).astype(np.float32)
    ok = usable & np.isfinite(excess)
    col = _profile(e, ok, min_half)
    e_col = e - np.maximum(col, 0)[None, :]
    row = _profile(e_col.T, ok.T, min_half)
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

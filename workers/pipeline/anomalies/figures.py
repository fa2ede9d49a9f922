"""Facade figures for energy auditors (`docs/anomalies.md` gives the formulas and their limits).

In: the excess over typical `(H, W)`, the observed texels, the window texels, the leak texels and
their residual excess. Out: hot share, window share and heat-loss index of one surface.
"""

from __future__ import annotations

import numpy as np


def hot_share(excess: np.ndarray, observed: np.ndarray, windows: np.ndarray, hot_delta_k: float) -> float:
    """Share (0-1) of the observed area outside windows warmer than typical + `hot_delta_k`
    (NaN when that area is empty)."""
    wall = observed & ~windows
    n = int(wall.sum())
    if n == 0:
        return float("nan")
    return float(np.count_nonzero(excess[wall] > hot_delta_k)) / n


def window_share(observed: np.ndarray, windows: np.ndarray) -> float:
    """Window area / observed area (0-1; NaN when nothing was observed)."""
    n = int(observed.sum())
    return float(np.count_nonzero(windows & observed)) / n if n else float("nan")


def heat_loss_index(residual: np.ndarray, observed: np.ndarray, leaks: np.ndarray) -> float:
    """Σ over leak texels of their excess · texel area / observed area, kelvin
    (= Σ excess over leak texels / observed texels; 0 without leaks, NaN when nothing observed).

    >>> r = np.full((2, 2), 1.0); obs = np.ones((2, 2), bool); lk = np.zeros((2, 2), bool)
    >>> lk[0, 0] = True
    >>> heat_loss_index(r * 3.0, obs, lk)
    0.75
    """
    n = int(observed.sum())
    if n == 0:
        return float("nan")
    m = leaks & observed
    return float(np.sum(np.maximum(residual[m], 0.0))) / n

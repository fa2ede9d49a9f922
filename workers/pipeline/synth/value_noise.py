"""A fixed random surface texture for the synthetic thermal scene (`ThermalOptions.facade_noise_k`)."""

from __future__ import annotations

import numpy as np


def value_noise(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Value noise in [-1, 1] `(N,)` float32 at cell coordinates `a`, `b` `(N,)` of polygons `p`
    `(N,)`: a hashed random value per integer lattice point (per polygon), smoothly interpolated."""
    ia, ib = np.floor(a), np.floor(b)
    fa, fb = a - ia, b - ib
    fa, fb = fa * fa * (3 - 2 * fa), fb * fb * (3 - 2 * fb)
    i, j, q = ia.astype(np.int64), ib.astype(np.int64), np.asarray(p, dtype=np.int64)

    def h(di: int, dj: int) -> np.ndarray:
        x = ((i + di) * 73856093) ^ ((j + dj) * 19349663) ^ (q * 83492791)
        x = ((x ^ (x >> 13)) * 1274126177) & 0xFFFFFFFF
        return ((x ^ (x >> 16)) & 0xFFFF).astype(np.float32) / np.float32(32767.5) - np.float32(1.0)

    top = h(0, 0) + fa * (h(1, 0) - h(0, 0))
    bottom = h(0, 1) + fa * (h(1, 1) - h(0, 1))
    return (top + fb * (bottom - top)).astype(np.float32)

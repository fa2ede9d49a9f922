"""The reduced normal system of the bundle adjustment (`bundle`): assembly and block-sparse solve.

In: per observation its frame slot, track and Jacobians; per frame and for the common correction
their prior blocks. Out: the reduced system of the frames and the common correction (points
eliminated, Schur complement), its solution and the diagonal blocks of its inverse.

Structure: the frames of a block are in recording order and a track spans a few consecutive
frames, so the frames' part `A` `(6n, 6n)` of the reduced system is banded (half-bandwidth
6 × the longest frame distance a track ties, plus 5); the common correction (last 6 unknowns)
couples to every frame, a dense border. The solve factorises the band once
(`scipy.linalg.cholesky_banded`, O(n b²) instead of O(n³)) and eliminates the border through
its 6 × 6 Schur complement. Where the band is not narrow (long tracks over a short block) the
dense Cholesky is as fast and is used.

Sums over observations go through a sparse indicator matrix (one compiled product) instead of
`np.add.at` (an order of magnitude slower for small blocks).

The factorisations run with OpenBLAS on one thread (`single_threaded_blas`): these systems are
small (a few hundred unknowns), and OpenBLAS's threads spin while they wait for each other. On
this 2-core machine under load, one 720 × 720 Cholesky took 0.14 CPU s with OpenBLAS's default
threads and 0.006 s on one; its banded form 0.15 s and 0.0006 s.
"""

from __future__ import annotations

import ctypes
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache

import numpy as np
from scipy.linalg import cho_factor, cho_solve, cho_solve_banded, cholesky_banded
from scipy.sparse import csr_matrix

__all__ = ["banded_width", "block_sums", "diagonal_inverse_blocks", "single_threaded_blas", "solve_reduced"]

# the banded factorisation is used while the half-bandwidth is below this share of the size
_BAND_SHARE = 0.5


@cache
def _openblas_threads() -> tuple[tuple[ctypes._CFuncPtr, ctypes._CFuncPtr], ...]:
    """(get, set) of the thread count of every OpenBLAS loaded in this process (numpy and scipy
    each ship one; their symbols carry a prefix and a suffix per build)."""
    try:
        with open("/proc/self/maps", encoding="utf-8") as fh:
            paths = sorted({line.split()[-1] for line in fh if "openblas" in line and ".so" in line})
    except OSError:
        return ()
    out = []
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for get_name, set_name in (("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
                                   ("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
                                   ("openblas_get_num_threads", "openblas_set_num_threads")):
            get, put = getattr(lib, get_name, None), getattr(lib, set_name, None)
            if get is not None and put is not None:
                get.restype, put.argtypes = ctypes.c_int, [ctypes.c_int]
                out.append((get, put))
                break
    return tuple(out)


@contextmanager
def single_threaded_blas() -> Iterator[None]:
    """OpenBLAS (numpy's and scipy's) on one thread inside the block, the thread counts restored
    after it (a no-op where no OpenBLAS is found)."""
    libs = _openblas_threads()
    before = [get() for get, _ in libs]
    for _, put in libs:
        put(1)
    try:
        yield
    finally:
        for (_, put), k in zip(libs, before, strict=True):
            put(k)


def block_sums(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """`out[k] = Σ values[index == k]`: `values` `(K, ...)`, `index` `(K,)` in [0, n) -> `(n, ...)`
    (the same as `np.add.at` into zeros)."""
    shape = values.shape[1:]
    if len(index) == 0:
        return np.zeros((n, *shape))
    K = len(index)
    ind = csr_matrix((np.ones(K), (index, np.arange(K))), shape=(n, K))
    return np.asarray(ind @ values.reshape(K, -1)).reshape((n, *shape))


def banded_width(t_obs: np.ndarray, f_obs: np.ndarray, n_tracks: int) -> int:
    """Half-bandwidth (unknowns, 6 per frame) of the frames' part of the reduced system when the
    observations `(M,)` of tracks `t_obs` in frame slots `f_obs` couple the frames of a track."""
    if len(t_obs) == 0:
        return 5
    lo = np.full(n_tracks, np.iinfo(np.int64).max)
    hi = np.full(n_tracks, -1)
    np.minimum.at(lo, t_obs, f_obs)
    np.maximum.at(hi, t_obs, f_obs)
    seen = hi >= 0
    return 6 * int(np.max(hi[seen] - lo[seen])) + 5


def solve_reduced(S: np.ndarray, b: np.ndarray, n: int, band: int) -> np.ndarray | None:
    """Solve the reduced system `S` `(6(n+c), 6(n+c))` (c = 0 or 1 common block last, SPD) for
    `b`; `band` the half-bandwidth of its frames' part (`banded_width`). None when `S` is not
    positive definite."""
    m = 6 * n
    with single_threaded_blas():
        return _solve(S, b, m, band)


def _solve(S: np.ndarray, b: np.ndarray, m: int, band: int) -> np.ndarray | None:
    """`solve_reduced` with `m` = 6 n."""
    try:
        if band >= _BAND_SHARE * m:
            return cho_solve(cho_factor(S), b)
        ab = _upper_band(S[:m, :m], band)
        cb = cholesky_banded(ab)
        if len(S) == m:
            return cho_solve_banded((cb, False), b)
        B = S[:m, m:]
        rhs = cho_solve_banded((cb, False), np.column_stack([b[:m], B]))
        y, Y = rhs[:, 0], rhs[:, 1:]
        Sc = S[m:, m:] - B.T @ Y  # Schur complement of the common block
        xc = cho_solve(cho_factor(Sc), b[m:] - B.T @ y)
        return np.concatenate([y - Y @ xc, xc])
    except np.linalg.LinAlgError:
        return None


def diagonal_inverse_blocks(S: np.ndarray, n: int) -> np.ndarray | None:
    """The `n` diagonal `(6, 6)` blocks of `S⁻¹` (the frames' blocks; a common block after them
    is inverted with the rest) -> `(n, 6, 6)`; None when `S` is not positive definite."""
    with single_threaded_blas():
        try:
            c = cho_factor(S)
        except np.linalg.LinAlgError:
            return None
        # once per adjustment: the whole inverse, its diagonal blocks kept
        Sinv = cho_solve(c, np.eye(len(S)))
    idx = np.arange(n)[:, None] * 6 + np.arange(6)[None, :]
    return Sinv[idx[:, :, None], idx[:, None, :]]


def _upper_band(A: np.ndarray, u: int) -> np.ndarray:
    """`A` `(m, m)` symmetric -> its upper band `(u + 1, m)` in LAPACK's storage
    (`ab[u + i - j, j] = A[i, j]` for `j - u ≤ i ≤ j`)."""
    m = len(A)
    u = min(u, m - 1)
    ab = np.zeros((u + 1, m))
    for d in range(u + 1):
        ab[u - d, d:] = np.diagonal(A, offset=d)
    return ab

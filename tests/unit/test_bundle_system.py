"""The reduced system of the bundle adjustment (`workers.pipeline.orientation.bundle_system`): block
sums, the banded solve with the common correction's border and the covariance blocks against dense
numpy on random systems with the structure of a block of frames."""

from __future__ import annotations

import numpy as np

from workers.pipeline.orientation.bundle_system import (
    banded_width,
    block_sums,
    diagonal_inverse_blocks,
    solve_reduced,
)


def _system(seed: int, n: int, reach: int, common: bool) -> np.ndarray:
    """A random SPD reduced system of `n` frames (6 unknowns each) coupled to the frames within
    `reach` of them, with a dense 6-unknown border when `common`."""
    rng = np.random.default_rng(seed)
    m = 6 * (n + int(common))
    S = np.zeros((m, m))
    for k in range(n):  # one 'track' of frames k .. k + reach: a rank-deficient positive block
        hi = min(n, k + reach + 1)
        J = rng.normal(size=(8, 6 * (hi - k)))
        S[6 * k:6 * hi, 6 * k:6 * hi] += J.T @ J
    S[:6 * n, :6 * n] += np.eye(6 * n) * 0.1  # the priors
    if common:
        P = -0.1 * np.tile(np.eye(6), (n, 1))
        S[:6 * n, 6 * n:] = P
        S[6 * n:, :6 * n] = P.T
        S[6 * n:, 6 * n:] = np.eye(6) * (0.1 * n + 1.0)
    return S


def test_block_sums_equal_add_at() -> None:
    rng = np.random.default_rng(0)
    idx = rng.integers(0, 7, 50)
    vals = rng.normal(size=(50, 6, 3))
    ref = np.zeros((9, 6, 3))
    np.add.at(ref, idx, vals)
    assert np.allclose(block_sums(idx, vals, 9), ref)
    assert block_sums(np.zeros(0, int), np.zeros((0, 2)), 3).shape == (3, 2)


def test_band_of_tracks() -> None:
    # tracks 0: frames 1..4, 1: frames 0 and 2, 2: unseen
    t = np.array([0, 0, 0, 1, 1])
    f = np.array([1, 4, 2, 0, 2])
    assert banded_width(t, f, 3) == 6 * 3 + 5
    assert banded_width(np.zeros(0, int), np.zeros(0, int), 0) == 5


def test_banded_solve_with_the_common_border_equals_the_dense_solve() -> None:
    for common in (True, False):
        n, reach = 40, 3
        S = _system(1, n, reach, common)
        b = np.random.default_rng(2).normal(size=len(S))
        band = 6 * reach + 5
        x = solve_reduced(S, b, n, band)
        assert x is not None
        assert np.allclose(x, np.linalg.solve(S, b), rtol=1e-9, atol=1e-12)
        # a band as wide as the system: the dense path, same answer
        assert np.allclose(solve_reduced(S, b, n, 6 * n), x, rtol=1e-9, atol=1e-12)


def test_a_system_that_is_not_positive_definite_gives_none() -> None:
    S = _system(3, 10, 2, True)
    S[0, 0] = -1.0
    assert solve_reduced(S, np.ones(len(S)), 10, 17) is None
    assert diagonal_inverse_blocks(S, 10) is None


def test_covariance_blocks_are_the_inverse_blocks() -> None:
    n = 12
    S = _system(4, n, 2, True)
    blocks = diagonal_inverse_blocks(S, n)
    inv = np.linalg.inv(S)
    assert blocks is not None and blocks.shape == (n, 6, 6)
    for k in range(n):
        assert np.allclose(blocks[k], inv[6 * k:6 * k + 6, 6 * k:6 * k + 6], rtol=1e-9, atol=1e-14)

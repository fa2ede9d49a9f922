"""Windows on coarse textures (flights: 0.4 m texels, panes of 1.2 × 1.4 m ≈ 3 texels blurred by
about a texel): found by their half-depth regions in a regular group (`windows._blurred_blobs`),
never invented where the field has no panes.

The wall field is `test_anomalies.wall_field` (4 × 2 panes, −2.5 K, warm frames, slabs, corners,
sinusoids), sampled 3 × 3 per texel, blurred by a Gaussian of σ = 1 texel (a flight's pixel
footprint) and noisy, at four sub-texel phases of the pane lattice.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.special import erf

from tests.unit.test_anomalies import LEAKS, WALL_H, pane_centres, wall_field, wall_grid
from workers.pipeline.anomalies import AnomalyOptions, analyse_surface
from workers.pipeline.anomalies.windows import coarse, half_depth_extent
from workers.pipeline.texture.fused import SurfaceTexture
from workers.pipeline.texture.texel import TexelGrid


def blurred_texture(grid: TexelGrid, shift_m: float, seed: int, blur_px: float = 1.0, **kw) -> SurfaceTexture:
    """The wall field shifted by `shift_m` along both axes (phase against the texel grid),
    sampled 3 × 3 per texel, blurred by σ `blur_px` texels, noise 0.05 K; 3 frames per texel."""
    rng = np.random.default_rng(seed)
    H, W = grid.shape
    sub = (np.arange(3) + 0.5) / 3
    y = (np.arange(H)[:, None] + sub[None]).ravel()
    x = (np.arange(W)[:, None] + sub[None]).ravel()
    X, Y = np.meshgrid(x, y)
    T = wall_field(X * grid.size - shift_m, WALL_H - Y * grid.size - shift_m, rng, **kw)
    T = T.reshape(H, 3, W, 3).mean(axis=(1, 3)).astype(np.float32)
    T = cv2.GaussianBlur(T, (0, 0), blur_px, borderType=cv2.BORDER_REPLICATE)
    T += rng.normal(0, 0.05, T.shape).astype(np.float32)
    tex = SurfaceTexture.empty((H, W))
    tex.value[:] = np.where(grid.mask, T, np.nan)
    tex.resolution[:] = grid.size
    tex.frame[:] = 0
    tex.count[:] = 3
    tex.obs_frame[:3] = np.arange(3)[:, None, None]
    tex.obs_res[:3] = grid.size
    return tex


def pane_points(grid: TexelGrid, shift_m: float) -> np.ndarray:
    """World centres `(8, 3)` of the panes shifted by `shift_m`."""
    xy = np.array(
        [[(s + shift_m) / grid.size, (WALL_H - h - shift_m) / grid.size] for s, h in pane_centres()]
    )
    return grid.points_at(xy)


def test_half_depth_extent_of_a_blurred_box_is_its_width_at_any_phase():
    """A box of width L texels blurred by σ = 1 texel, sampled at texel centres: the half-depth
    extent is L within 0.6 texel at every phase (never less: a blur widens a narrow box's
    half-depth region), exact for wide boxes."""
    x = np.arange(40) + 0.5
    for width in (3.0, 4.0, 6.0):
        for phase in (0.0, 0.25, 0.5, 0.75):
            lo = 18.0 + phase
            prof = 0.5 * (erf((x - lo) / np.sqrt(2)) - erf((x - lo - width) / np.sqrt(2)))
            got = half_depth_extent(prof)
            assert width - 0.05 <= got <= width + 0.6
            if width >= 6:
                assert got == pytest.approx(width, abs=0.05)


def test_coarse_textures_are_the_ones_a_small_pane_spans_few_texels_of():
    o = AnomalyOptions()
    assert not coarse(0.1, o) and coarse(0.4, o)


@pytest.mark.parametrize("shift_m", [0.0, 0.1, 0.2, 0.3])
def test_blurred_panes_on_04_m_texels_are_found_on_their_lattice(shift_m):
    grid = wall_grid(px_per_m=2.5)
    assert grid.size == pytest.approx(0.4)
    res = analyse_surface(grid, blurred_texture(grid, shift_m, seed=3, leaks=(), pipe=False))
    found = np.array([w.centre for w in res.of_kind("window")]).reshape(-1, 3)
    truth = pane_points(grid, shift_m)
    d = np.linalg.norm(truth[:, None] - found[None], axis=2) if len(found) else np.full((8, 1), np.inf)
    assert np.sum(d.min(axis=1) < 0.5) >= 7  # recall ≥ 7/8 at every phase
    assert len(found) == 0 or np.all(d.min(axis=0) < 0.5)  # every window a real pane
    assert res.of_kind("leak") == ()


def test_no_windows_are_invented_on_a_coarse_wall_without_panes():
    grid = wall_grid(px_per_m=2.5)
    for seed in range(3):
        tex = blurred_texture(grid, 0.1 * seed, seed=seed, windows=False, leaks=LEAKS)
        assert analyse_surface(grid, tex).of_kind("window") == ()


@pytest.mark.parametrize("shift_m", [0.0, 0.1, 0.2, 0.3])
def test_shallow_blurred_panes_count_in_their_lattice(shift_m):
    """A blur of σ = 1.3 texels leaves the −2.5 K panes 0.8–1 K deep in the texture: their
    minima pass `window_coarse_delta_k` (0.8 K) but not `window_delta_k` (1 K), so they count in
    their regular group (with 1 K: 2–3 of 8 at some phases); without panes, nothing is found."""
    grid = wall_grid(px_per_m=2.5)
    res = analyse_surface(grid, blurred_texture(grid, shift_m, seed=3, blur_px=1.3, leaks=(), pipe=False))
    found = np.array([w.centre for w in res.of_kind("window")]).reshape(-1, 3)
    truth = pane_points(grid, shift_m)
    d = np.linalg.norm(truth[:, None] - found[None], axis=2) if len(found) else np.full((8, 1), np.inf)
    assert np.sum(d.min(axis=1) < 0.5) >= 7
    assert len(found) == 0 or np.all(d.min(axis=0) < 0.5)
    assert res.of_kind("leak") == ()
    bare = blurred_texture(grid, shift_m, seed=3, blur_px=1.3, windows=False, leaks=LEAKS)
    assert analyse_surface(grid, bare).of_kind("window") == ()

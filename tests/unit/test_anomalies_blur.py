"""The imaging blur in the leak threshold's floor and in a leak's ΔT.

The floor is a leak's ΔT as the imaging blur shows it (`analysis.floor_attenuation`,
`AnomalyOptions.floor_sigma_m`).

On coarse textures (flights: 0.4 m texels, blur σ about a texel) a leak of 2.6 K and σ 0.35 m
peaks near 1 K in the texture, below the 1.2 K floor: with the floor taken through the blur it
is found, with the floor on the texture as it is (`floor_sigma_m=0`) it is not. The wall is
`test_anomalies.wall_field` (panes, frames, slabs, corners, a pipe, sinusoids) sampled as
`test_anomalies_coarse.blurred_texture` does, at six seeds and four phases of the pane lattice;
without the leak nothing is reported.

An elongated blur (a footprint foreshortened along one axis) is deconvolved exactly
(`leaks.fit_blob` with `blur_short`), not as one round blur of the geometric mean.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from tests.unit.test_anomalies import WALL_H, Leak, wall_grid
from tests.unit.test_anomalies_coarse import blurred_texture
from workers.pipeline.anomalies import AnomalyOptions, analyse_surface
from workers.pipeline.anomalies.analysis import floor_attenuation, imaging_blur_m, region_blur_m
from workers.pipeline.anomalies.leaks import fit_blob
from workers.pipeline.texture.fused import SurfaceTexture

LEAK = Leak(9.0, 7.5, 0.35, 2.6)  # attic, away from panes, slabs, corners and the pipe


def uniform_texture(shape: tuple[int, int], res_m: float, angle_deg: float) -> SurfaceTexture:
    """A texture `shape` observed everywhere at one resolution (m/px) and viewing angle."""
    tex = SurfaceTexture.empty(shape)
    tex.value[:] = 276.0
    tex.resolution[:] = res_m
    tex.view_angle[:] = angle_deg
    return tex


def test_floor_attenuation_is_the_peak_share_of_a_blurred_blob():
    o = AnomalyOptions()
    obs = np.ones((10, 10), bool)
    bl, bs = imaging_blur_m(0.5, 50.0, o.psf_sigma_px)
    s2 = o.floor_sigma_m**2
    want = s2 / math.sqrt((s2 + bl**2) * (s2 + bs**2))
    got = floor_attenuation(uniform_texture((10, 10), 0.5, 50.0), obs, o)
    assert got == pytest.approx(want, rel=1e-6) and 0.6 < got < 0.8  # a flight
    assert floor_attenuation(uniform_texture((10, 10), 0.05, 30.0), obs, o) > 0.98  # a drive
    assert (
        floor_attenuation(uniform_texture((10, 10), 0.5, 50.0), obs, AnomalyOptions(floor_sigma_m=0)) == 1.0
    )
    unobserved = SurfaceTexture.empty((10, 10))  # resolution inf: unknown
    assert floor_attenuation(unobserved, obs, o) == 1.0


@pytest.mark.parametrize("seed", range(6))
def test_a_blurred_leak_below_the_floor_on_the_texture_is_found(seed):
    grid = wall_grid(px_per_m=2.5)
    tex = blurred_texture(grid, 0.1 * (seed % 4), seed=seed, leaks=(LEAK,))
    tex.resolution[:] = 0.5  # a flight's pixels (m/px) seen head-on
    tex.view_angle[:] = 0.0
    at = grid.points_at(np.array([[LEAK.s / grid.size, (WALL_H - LEAK.h) / grid.size]]))[0]

    def found(options: AnomalyOptions) -> list[float]:
        res = analyse_surface(grid, tex, options)
        return [a.peak_delta_k for a in res.of_kind("leak") if np.linalg.norm(a.centre - at) < 0.5]

    assert len(found(AnomalyOptions())) == 1
    assert found(AnomalyOptions(floor_sigma_m=0.0)) == []  # the peak the texture shows < 1.2 K


@pytest.mark.parametrize("seed", range(6))
def test_no_leak_on_a_coarse_wall_without_one(seed):
    grid = wall_grid(px_per_m=2.5)
    tex = blurred_texture(grid, 0.1 * (seed % 4), seed=seed, leaks=())
    tex.resolution[:] = 0.5
    tex.view_angle[:] = 0.0
    assert analyse_surface(grid, tex).of_kind("leak") == ()


@pytest.mark.parametrize("seed", range(3))
def test_fit_blob_deconvolves_an_elongated_blur(seed):
    """A 3 K blob of σ 3 texels blurred by σ 3 texels along x and 1 across (a footprint
    foreshortened at 70°), point-sampled with 0.03 K noise: the texels show 2 K; through both
    blurs the fit gives 3 K within 5 %, through their geometric mean as one round blur it
    stays 10 % or more low."""
    sigma, bl, bs, peak, n, sub = 3.0, 3.0, 1.0, 3.0, 41, 8
    cx, cy = 20.3, 19.8
    f = (np.arange(n * sub) + 0.5) / sub
    X, Y = np.meshgrid(f, f)
    T = peak * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) / (2 * sigma**2))
    T = cv2.GaussianBlur(T, (0, 0), sigmaX=bl * sub, sigmaY=bs * sub)
    img = T[sub // 2 :: sub, sub // 2 :: sub].astype(np.float32)
    img += np.random.default_rng(seed).normal(0, 0.03, img.shape).astype(np.float32)
    assert img.max() == pytest.approx(
        peak * sigma**2 / math.sqrt((sigma**2 + bl**2) * (sigma**2 + bs**2)), rel=0.03
    )
    valid = np.ones(img.shape, bool)
    sigma_obs = math.sqrt((img >= 0.5 * img.max()).sum() / math.pi) / math.sqrt(2 * math.log(2))
    exact = fit_blob(img, valid, 20.5, 19.5, sigma_obs, bl, bs)
    round_ = fit_blob(img, valid, 20.5, 19.5, sigma_obs, math.sqrt(bl * bs))
    assert exact is not None and round_ is not None
    assert exact[0] == pytest.approx(peak, rel=0.05)
    assert round_[0] < 0.9 * peak


def fused_blob(seed: int, size: float = 0.4, n: int = 31) -> tuple[SurfaceTexture, float, float]:
    """A 3 K blob of σ 0.6 m on 0.4 m texels as a texture fuses it: five frames at 0.5-0.9 m/px
    and 10-60° viewing angles, their footprints turned 0-135° on the surface (each an
    elongated Gaussian blur, `imaging_blur_m`), the four within `blend_ratio` of the best
    averaged with weights 1 / resolution², 0.03 K noise. Returns the texture and the blob's
    centre (continuous raster coordinates)."""
    res, ang, turn = [0.5, 0.55, 0.6, 0.7, 0.9], [60, 40, 20, 50, 10], [0, 45, 90, 135, 30]
    sigma, peak, cx, cy = 0.6 / size, 3.0, 15.3, 14.8
    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    dx, dy = xx - cx, yy - cy
    tex = SurfaceTexture.empty((n, n))
    num, den = np.zeros((n, n)), 0.0
    for i, (r, a, q) in enumerate(zip(res, ang, turn, strict=True)):
        bl, bs = (b / size for b in imaging_blur_m(r, a, 0.6))
        c, s = math.cos(math.radians(q)), math.sin(math.radians(q))
        rot = np.array([[c, -s], [s, c]])
        cov = sigma**2 * np.eye(2) + rot @ np.diag([bl**2, bs**2]) @ rot.T  # blob * blur
        inv = np.linalg.inv(cov)
        q2 = inv[0, 0] * dx * dx + 2 * inv[0, 1] * dx * dy + inv[1, 1] * dy * dy
        img = peak * sigma**2 / math.sqrt(np.linalg.det(cov)) * np.exp(-0.5 * q2)
        tex.obs_res[i], tex.obs_angle[i], tex.obs_frame[i] = r, a, i
        if r <= tex.options.blend_ratio * res[0]:
            num, den = num + img / r**2, den + 1 / r**2
    noise = np.random.default_rng(seed).normal(0, 0.03, (n, n))
    tex.value[:] = num / den + noise
    tex.resolution[:], tex.view_angle[:] = res[0], ang[0]
    return tex, cx, cy


@pytest.mark.parametrize("seed", range(3))
def test_the_blur_of_a_fused_texture_averages_its_observations(seed):
    """The fused blob's blur is the weighted mean of its observations' blurs, their footprints
    turned every way (`analysis.region_blur_m`): through it the fit gives the 3 K within 8 %;
    through the best observation's footprint alone (the model until session 12) 10 % or more
    low."""
    size = 0.4
    tex, cx, cy = fused_blob(seed, size)
    val = tex.value
    half = val >= 0.5 * val.max()
    sigma_obs = math.sqrt(half.sum() / math.pi) / math.sqrt(2 * math.log(2))
    valid = np.ones(val.shape, bool)
    b = region_blur_m(tex, half, 0.6)
    assert b[0] == b[1]
    fused = fit_blob(val, valid, round(cx), round(cy), sigma_obs, b[0] / size, b[1] / size)
    bl, bs = imaging_blur_m(0.5, 60.0, 0.6)
    best_only = fit_blob(val, valid, round(cx), round(cy), sigma_obs, bl / size, bs / size)
    assert fused is not None and best_only is not None
    assert fused[0] == pytest.approx(3.0, rel=0.08)
    assert best_only[0] < 0.9 * 3.0

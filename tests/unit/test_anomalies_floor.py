"""The leak threshold's floor is a leak's ΔT as the imaging blur shows it
(`analysis.floor_attenuation`, `AnomalyOptions.floor_sigma_m`).

On coarse textures (flights: 0.4 m texels, blur σ about a texel) a leak of 2.6 K and σ 0.35 m
peaks near 1 K in the texture, below the 1.2 K floor: with the floor taken through the blur it
is found, with the floor on the texture as it is (`floor_sigma_m=0`) it is not. The wall is
`test_anomalies.wall_field` (panes, frames, slabs, corners, a pipe, sinusoids) sampled as
`test_anomalies_coarse.blurred_texture` does, at six seeds and four phases of the pane lattice;
without the leak nothing is reported.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.unit.test_anomalies import WALL_H, Leak, wall_grid
from tests.unit.test_anomalies_coarse import blurred_texture
from workers.pipeline.anomalies import AnomalyOptions, analyse_surface
from workers.pipeline.anomalies.analysis import floor_attenuation, imaging_blur_m
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
    want = o.floor_sigma_m**2 / (o.floor_sigma_m**2 + bl * bs)
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

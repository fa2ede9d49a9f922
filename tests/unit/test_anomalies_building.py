"""Facades across polygons (`anomalies.building`) and the blur-aware leak amplitude
(`leaks.fit_blob`, `analysis.blur_gain`): a wall split into coplanar polygons is analysed as one
facade; a leak blurred by the imaging keeps its ΔT."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from tests.unit.test_anomalies import LEAKS, WALL_H, WALL_W, Leak, wall_field, wall_grid, wall_texture
from tests.unit.texture_scene import box_building
from workers.pipeline.anomalies import AnomalyOptions, analyse_building, analyse_surface, facade_groups
from workers.pipeline.anomalies.analysis import blur_gain, imaging_blur_m
from workers.pipeline.anomalies.building import merge_facade
from workers.pipeline.anomalies.leaks import fit_blob
from workers.pipeline.texture.fused import SurfaceTexture
from workers.pipeline.texture.texel import TexelOptions, texel_grid

#: the per-facade analysis (off by default in the product)
GROUPED = AnomalyOptions(facade_grouping=True)

OPTS = TexelOptions(resolution_px_per_m=10.0, follow_frames=False)


def split_wall(cuts: tuple[float, ...], offset_y: float = 0.0, turn_deg: float = 0.0):
    """The test wall (y = 0, x 0..12, z 0..9) cut into vertical strips at the `cuts` (x, m); the
    last strip moved by `offset_y` off the plane; the second turned by `turn_deg` about its left
    edge (a vertical axis)."""
    wall = box_building("B", 0, 0, WALL_W, 8, WALL_H).polygons[0]
    xs = (0.0, *cuts, WALL_W)
    polys = []
    for k, (x0, x1) in enumerate(itertools.pairwise(xs)):
        y = offset_y if k == len(xs) - 2 else 0.0
        ring = np.array([[x0, y, 0], [x1, y, 0], [x1, y, WALL_H], [x0, y, WALL_H], [x0, y, 0]], float)
        if k == 1 and turn_deg:
            a = math.radians(turn_deg)
            u = ring[:, 0] - x0
            ring[:, 0], ring[:, 1] = x0 + u * math.cos(a), ring[:, 1] + u * math.sin(a)
        polys.append(replace(wall, id=f"B-w-{k}", exterior=replace(wall.exterior, coords=ring)))
    return [texel_grid(p, "B", OPTS) for p in polys]


def part_texture(whole: SurfaceTexture, grid_whole, grid) -> SurfaceTexture:
    """The texels of `whole` (the uncut wall) under `grid` (a strip of it)."""
    off = np.round(grid_whole.raster_xy(grid.centres(np.array([0]), np.array([0])))[0] - 0.5).astype(int)
    sub = (slice(off[1], off[1] + grid.shape[0]), slice(off[0], off[0] + grid.shape[1]))
    t = SurfaceTexture.empty(grid.shape)
    for name in ("value", "resolution", "view_angle", "frame", "count", "worst"):
        getattr(t, name)[:] = np.where(grid.mask, getattr(whole, name)[sub], getattr(t, name))
    for name in ("obs_value", "obs_res", "obs_angle", "obs_frame"):
        getattr(t, name)[:] = np.where(grid.mask, getattr(whole, name)[(slice(None), *sub)], getattr(t, name))
    return t


def test_facade_groups_coplanar_adjacent_only():
    strips = split_wall((4.0, 8.0))
    roof = texel_grid(box_building("B", 0, 0, WALL_W, 8, WALL_H).polygons[-1], "B", OPTS)
    assert facade_groups([*strips, roof]) == [[0, 1, 2], [3]]
    # 0.2 m off the plane: not the same facade; another building: neither
    moved = split_wall((4.0, 8.0), offset_y=0.2)
    assert facade_groups(moved) == [[0, 1], [2]]
    other = replace(strips[2], building_id="C")
    assert facade_groups([strips[0], strips[1], other]) == [[0, 1], [2]]
    # not adjacent: the first and last strips share no edge
    assert facade_groups([strips[0], strips[2]]) == [[0], [1]]
    # the middle strip turned about its shared edge with the first: grouped within 1°, not at 1.5°
    for deg, want in ((0.5, [[0, 1]]), (1.5, [[0], [1]])):
        turned = split_wall((4.0, 8.0), turn_deg=deg)[1]
        opts = AnomalyOptions(facade_plane_m=1.0)
        assert facade_groups([strips[0], turned], opts) == want, deg


def test_merged_facade_is_the_uncut_wall():
    whole_grid = wall_grid()
    strips = split_wall((4.0, 8.0))
    whole = wall_texture(whole_grid, seed=0)
    parts = [part_texture(whole, whole_grid, g) for g in strips]
    grid, tex, owner, offs = merge_facade(strips, parts)
    assert grid.shape == whole_grid.shape and offs == [(0, 0), (0, 40), (0, 80)]
    assert np.allclose(grid.corner, whole_grid.corner) and grid.mask.all()
    assert np.array_equal(np.isfinite(tex.value), np.isfinite(whole.value))
    assert np.allclose(tex.value, whole.value, equal_nan=True)
    assert set(np.unique(owner)) == {0, 1, 2}


def test_analyse_building_finds_a_leak_on_a_polygon_edge_once():
    """A leak centred 0.1 m from the cut between two strips: the strips alone put its maximum
    on their outline (an edge effect: dropped) or measure it against half a background; the
    facade finds it once, on the strip under its centre, with its ΔT."""
    leak = Leak(4.1, 4.5, 0.45, 3.0)
    whole_grid = wall_grid()
    strips = split_wall((4.0, 8.0))
    rng = np.random.default_rng(3)
    H, W = whole_grid.shape
    s, h = np.meshgrid((np.arange(W) + 0.5) * 0.1, WALL_H - (np.arange(H) + 0.5) * 0.1)
    T = wall_field(s, h, rng, leaks=(leak,), windows=False, pipe=False).astype(np.float32)
    T = cv2.GaussianBlur(T, (0, 0), 0.5) + rng.normal(0, 0.08, T.shape).astype(np.float32)
    whole = wall_texture(whole_grid, seed=0)
    whole.value[:] = T
    parts = [part_texture(whole, whole_grid, g) for g in strips]
    alone = [a for g, t in zip(strips, parts, strict=True) for a in analyse_surface(g, t).of_kind("leak")]
    near = [a for a in alone if abs(a.centre[0] - leak.s) < 0.5 and abs(a.centre[2] - leak.h) < 0.5]
    assert not near or all(abs(a.peak_delta_k - leak.peak) > 0.3 for a in near)
    res = analyse_building(strips, parts, GROUPED)
    assert [r.polygon_id for r in res] == ["B-w-0", "B-w-1", "B-w-2"]
    leaks = [(r.polygon_id, a) for r in res for a in r.of_kind("leak")]
    assert len(leaks) == 1
    pid, a = leaks[0]
    assert pid == "B-w-1" and a.polygon_id == "B-w-1" and a.id == "B-w-1-leak-0"
    assert math.hypot(a.centre[0] - leak.s, a.centre[2] - leak.h) < 0.15
    assert abs(a.peak_delta_k - leak.peak) < 0.7  # the wall's sinusoids: ±0.6 K under a leak
    assert len({r.typical for r in res}) == 1 and all(
        r.labels.shape == g.shape for r, g in zip(res, strips, strict=True)
    )
    assert res[1].labels[np.isfinite(parts[1].value)].min() >= 1


def test_fit_blob_restores_a_blurred_leak():
    """A 3 K leak of σ 0.35 m on 0.4 m texels, blurred by σ 0.4 m (a flight's pixel footprint):
    the texels show about 1.3 K; the blob fit through the known blur gives 3 K back (within 20 %:
    σ² = σo² − blur² amplifies an error of σo by 2σo²/σ² ≈ 4.6 here) and the centre to a fifth
    of a texel."""
    size, sigma, blur, peak = 0.4, 0.35, 0.4, 3.0
    n, sub = 21, 8
    cx, cy = 10.3, 9.8  # texels
    f = (np.arange(n * sub) + 0.5) / sub
    X, Y = np.meshgrid(f, f)
    T = peak * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2) * size**2 / (2 * sigma**2))
    T = cv2.GaussianBlur(T, (0, 0), blur / size * sub)
    img = T[sub // 2 :: sub, sub // 2 :: sub].astype(np.float32)  # point samples at texel centres
    img += np.random.default_rng(0).normal(0, 0.05, img.shape).astype(np.float32)
    assert img.max() < 0.6 * peak
    valid = np.ones(img.shape, bool)
    half = img >= 0.5 * img.max()
    sigma_obs = math.sqrt(half.sum() / math.pi) / math.sqrt(2 * math.log(2))
    got = fit_blob(img, valid, 10.5, 9.5, sigma_obs, blur / size)
    assert got is not None
    a, b, s, x, y = got
    assert a == pytest.approx(peak, rel=0.2) and abs(b) < 0.1
    assert s * size == pytest.approx(sigma, rel=0.25)
    assert math.hypot(x - cx, y - cy) < 0.2
    assert fit_blob(img, np.zeros_like(valid), 10.5, 9.5, sigma_obs, blur / size) is None


def test_blur_gain_conserves_volume():
    # a round blob of σ 0.5 m seen through 0.3 m × 0.1 m blur: σx σy measured by its area
    sx, sy = math.hypot(0.5, 0.3), math.hypot(0.5, 0.1)
    area = 2 * math.log(2) * math.pi * sx * sy
    assert blur_gain(area, 0.3, 0.1) == pytest.approx(sx * sy / 0.25, rel=1e-9)
    assert blur_gain(area, 0.0, 0.0) == pytest.approx(1.0)
    assert blur_gain(0.01, 0.5, 0.5) == 3.0  # not resolved: the cap
    bl, bs = imaging_blur_m(0.1, 0.0, 0.6)
    assert bl == bs == pytest.approx(0.1 * math.sqrt(0.36 + 0.25))


def test_disabled_or_unobserved_facade_has_no_figures():
    whole_grid = wall_grid()
    strips = split_wall((4.0, 8.0))
    parts = [part_texture(wall_texture(whole_grid, seed=0), whole_grid, g) for g in strips]
    for r in analyse_building(strips, parts, AnomalyOptions(enabled=False, facade_grouping=True)):
        assert not r.anomalies and math.isnan(r.typical) and math.isnan(r.hot_share) and not r.labels.any()
    empty = [SurfaceTexture.empty(g.shape) for g in strips]
    for r in analyse_building(strips, empty, GROUPED):
        assert not r.anomalies and math.isnan(r.window_share) and math.isnan(r.heat_loss_index)
    with pytest.raises(ValueError, match="textures"):
        analyse_building(strips, parts[:2], GROUPED)


def test_single_polygon_is_analyse_surface():
    g = wall_grid()
    t = wall_texture(g, seed=1)
    one = analyse_building([g], [t], GROUPED)[0]
    ref = analyse_surface(g, t)
    assert [a.id for a in one.anomalies] == [a.id for a in ref.anomalies] and len(ref.of_kind("leak")) == len(
        LEAKS
    )
    assert np.array_equal(one.labels, ref.labels)

"""Robust fusion of several observations per texel, the frames' sight of each surface (the
resolution a surface gets, why a surface gets none) and texel grids on thin polygons."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.unit.texture_scene import box_building, look_at, ring
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Polygon
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
from workers.pipeline.texture.fused import FusedOptions, SurfaceTexture
from workers.pipeline.texture.sight import surface_resolution, surface_sight
from workers.pipeline.texture.texel import TexelOptions, texel_grid
from workers.pipeline.texture.visibility import VisibilityOptions

CAM = Camera(320, 256, 300.0, 300.0, 159.5, 127.5)


def _merge_all(tex: SurfaceTexture, values: list[float], res: list[float]) -> None:
    one = np.array([0])
    for f, (v, r) in enumerate(zip(values, res, strict=True)):
        tex.merge(one, one, np.array([v], np.float32), np.array([r]), np.array([10.0]), f)


def test_one_bad_observation_among_several_does_not_decide_a_texel() -> None:
    rng = np.random.default_rng(4)
    truth = 290.0
    obs = list(truth + 0.05 * rng.standard_normal(4))
    obs[1] = truth + 9.0  # a mixed pixel: sky or a neighbour in front
    tex = SurfaceTexture.empty((1, 1), FusedOptions(keep=4, blend_ratio=2.0))
    _merge_all(tex, obs, [0.05, 0.04, 0.05, 0.06])  # the bad one even has the best resolution
    assert abs(float(tex.value[0, 0]) - truth) < 0.1
    assert int(tex.count[0, 0]) == 3
    assert tex.frame[0, 0] == 1 and tex.resolution[0, 0] == pytest.approx(0.04)


def test_agreeing_observations_are_averaged_by_resolution_and_coarse_ones_left_out() -> None:
    tex = SurfaceTexture.empty((1, 1), FusedOptions(keep=4, blend_ratio=2.0))
    _merge_all(tex, [290.0, 290.2, 290.1, 291.0], [0.05, 0.05, 0.10, 0.5])
    w = np.array([1 / 0.05**2, 1 / 0.05**2, 1 / 0.10**2])
    expected = float(np.average([290.0, 290.2, 290.1], weights=w))
    assert float(tex.value[0, 0]) == pytest.approx(expected, abs=1e-4)
    assert int(tex.count[0, 0]) == 3


def test_only_the_best_observations_are_kept_and_the_worst_is_replaced() -> None:
    tex = SurfaceTexture.empty((1, 1), FusedOptions(keep=2))
    _merge_all(tex, [290.0, 291.0, 290.5], [0.10, 0.20, 0.05])
    assert sorted(tex.obs_res[:, 0, 0].tolist()) == pytest.approx([0.05, 0.10])
    assert tex.worst[0, 0] == pytest.approx(0.10)
    assert sorted(tex.frames_used(np.ones((1, 1), bool)).tolist()) == [0, 2]


def test_the_resolution_of_a_surface_follows_the_frames_on_a_halving_ladder() -> None:
    assert surface_resolution(10.0, 0.03, 1.5) == 10.0
    assert surface_resolution(10.0, 0.44, 1.5) == 2.5  # 0.4 m texels for 0.44 m pixels
    assert surface_resolution(10.0, math.inf, 1.5) == 10.0  # not seen: as asked


def test_sight_tells_seen_hidden_and_grazing_surfaces_apart() -> None:
    wall = box_building("A", 0, 0, 10, 6, 5)
    front = box_building("B", -2, -6, 12, -4, 8)  # a taller block in front of A's south wall
    caster = RayCaster(build_scene_mesh([wall, front]))
    south, east, roof = (next(p for p in wall.polygons if p.id == i) for i in ("A_w0", "A_w1", "A_roof"))
    opts = VisibilityOptions(max_view_angle_deg=80.0)
    # from the south, behind B: A's south wall is hidden; from the east, A's east wall is seen
    behind = look_at(np.array([5.0, -30.0, 2.0]), np.array([5.0, 0.0, 2.5]))
    east_view = look_at(np.array([30.0, 3.0, 2.0]), np.array([10.0, 3.0, 2.5]))
    s_south, s_east, s_roof = surface_sight([south, east, roof], CAM, [behind, east_view], caster, opts)
    assert not s_south.seen and "hidden" in s_south.reason_unseen(80.0)
    assert s_east.seen and s_east.best_resolution_m == pytest.approx(20 / 300, rel=0.3)
    # the flat roof from 2 m height (below the roof): facing away, no reason needed
    assert not s_roof.seen and s_roof.reason_unseen(80.0) == ""
    # the roof from just above its plane, far off: in front of it but beyond the grazing limit
    grazing = look_at(np.array([60.0, 3.0, 5.5]), np.array([5.0, 3.0, 5.0]))
    (s_roof2,) = surface_sight([roof], CAM, [grazing], caster, opts)
    assert not s_roof2.seen and "grazing" in s_roof2.reason_unseen(80.0)


def test_a_polygon_too_thin_for_a_texel_centre_still_gets_texels() -> None:
    outline = ring("r", [[0, 0, 0], [4, 0, 0], [4, 0, 0.04], [0, 0, 0.04]])
    strip = Polygon("strip", outline, surface_class="WallSurface")
    grid = texel_grid(strip, "b", TexelOptions(resolution_px_per_m=10.0, min_area_m2=0.01))
    assert grid is not None and grid.n_texels == 40


def test_sorted_columns_matches_numpy_sort_with_empty_slots() -> None:
    """The sorting network of the kept observations orders every column as `np.sort` does,
    empty slots (inf) last, for every number of kept observations."""
    from workers.pipeline.texture.fused import sorted_columns

    rng = np.random.default_rng(7)
    for k in range(1, 11):
        x = rng.normal(300.0, 5.0, (k, 500)).astype(np.float32)
        x[rng.random((k, 500)) < 0.3] = np.inf
        x[:, :3] = 290.0  # ties
        assert np.array_equal(sorted_columns(x), np.sort(x, axis=0)), k


def test_a_frame_that_contradicts_the_others_is_dropped_as_a_whole() -> None:
    """A frame whose pose is off by pixels (its view of a roof shifted onto the sky on a third of
    the texels) is the only view of some texels: the per-texel median cannot reject it there,
    the frame-level test does;
    frames that agree within their noise stay, and so do two passes of a sequence that disagree
    as a whole (the surface's temperature changed between them)."""
    from workers.pipeline.texture.consistency import ConsistencyOptions, reject_inconsistent_frames

    rng = np.random.default_rng(11)
    H, W = 20, 30
    truth = 280.0 + 0.5 * np.sin(np.arange(W) / 4.0)[None, :] * np.ones((H, 1))
    rows, cols = (a.ravel() for a in np.mgrid[0:H, 0:W])

    def texture(bands: list[tuple[int, int, float]]) -> SurfaceTexture:
        tex = SurfaceTexture.empty((H, W))
        for f, (r0, r1, offset) in enumerate(bands):  # frame f sees rows r0..r1-1
            m = (rows >= r0) & (rows < r1)
            n = int(m.sum())
            vals = truth[rows[m], cols[m]] + offset + 0.05 * rng.standard_normal(n)
            tex.merge(rows[m], cols[m], vals.astype(np.float32), np.full(n, 0.06), np.full(n, 60.0), f)
        return tex

    tex = texture([(0, 10, 0.0), (0, 15, 0.0), (5, 15, 0.0), (10, 15, 0.0)])  # rows 15-19: none
    bad = truth[rows, cols] - np.where(rows % 3 == 0, 15.0, 0.0)  # a third of its view: sky
    tex.merge(rows, cols, bad.astype(np.float32), np.full(len(rows), 0.05), np.full(len(rows), 60.0), 4)
    assert float(np.nanmax(np.abs(tex.value - truth))) > 10.0  # the bad frame decides some texels
    assert reject_inconsistent_frames([tex], ConsistencyOptions(enabled=False)) == []
    assert reject_inconsistent_frames([tex]) == [4]
    assert float(np.nanmax(np.abs(tex.value - truth))) < 0.3
    assert 4 not in tex.frames_used(tex.observed).tolist()
    assert tex.observed[:15].all() and not tex.observed[15:].any()  # seen by the bad frame alone
    assert reject_inconsistent_frames([texture([(0, 20, 0.0), (0, 20, 0.0), (0, 20, 0.0)])]) == []
    two_passes = texture([(0, 20, 0.0), (0, 20, 0.0), (0, 20, 1.0), (0, 20, 1.0)])
    assert reject_inconsistent_frames([two_passes]) == []

"""Visibility: frustum test, geometric texel tests, occlusion through the whole scene."""

from __future__ import annotations

import numpy as np
import pytest

from tests.unit.texture_scene import box_building, field, look_at, render
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.manifest import MemoryFrames, Radiometry
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
from workers.pipeline.plan import PlanOptions, plan_units
from workers.pipeline.texture.texel import TexelOptions, texel_grid
from workers.pipeline.texture.visibility import (
    VisibilityOptions,
    boxes_in_frustum,
    buried_texels,
    project_texels,
)
from workers.pipeline.units import texture_unit

CAM = Camera(200, 160, 180.0, 180.0, 99.5, 79.5, k1=-0.08)


def test_frustum_test_is_conservative_and_rejects_what_cannot_be_seen():
    pose = look_at([0, 0, 0], [0, 10, 0])
    rng = np.random.default_rng(3)
    lo = rng.uniform([-60, -60, -20], [60, 60, 20], size=(400, 3))
    hi = lo + rng.uniform(0.2, 6.0, size=(400, 3))
    inside = boxes_in_frustum(CAM, pose, lo, hi)
    # any box with a corner projecting into the image must pass
    for k in range(len(lo)):
        corners = np.array([[(hi if i & m else lo)[k][a] for a, m in enumerate((1, 2, 4))] for i in range(8)])
        uv, depth = pose.project(CAM, corners)
        xc = pose.cam_from_world(corners)
        with np.errstate(divide="ignore", invalid="ignore"):
            in_fov = np.all(np.abs(xc[:, :2] / xc[:, 2:]) < 1.0, axis=1)  # (the polynomial folds beyond)
        if np.any((depth > 0.5) & in_fov & CAM.in_image(uv)):
            assert inside[k]
    assert not boxes_in_frustum(CAM, pose, [[-1, -20, -1]], [[1, -10, 1]])[0]  # behind
    assert not boxes_in_frustum(CAM, pose, [[40, 5, -1]], [[42, 8, 1]])[0]  # far right
    assert not boxes_in_frustum(CAM, pose, [[-1, 900, -1]], [[1, 901, 1]])[0]  # beyond range
    assert boxes_in_frustum(CAM, pose, [[-1, 10, -1]], [[1, 12, 1]])[0]


def test_geometric_tests_on_texels():
    b = box_building("B", 0, 0, 10, 8, 6)
    pose = look_at([5, -12, 1.6], [5, 0, 3])
    south, north = b.polygons[0], b.polygons[2]
    pts = np.array([[5.0, 0, 3], [0.2, 0, 0.5], [9.8, 0, 5.9]])
    proj = project_texels(CAM, pose, pts, np.array([0, -1.0, 0]), VisibilityOptions())
    assert proj.ok[0]
    uv, _ = pose.project(CAM, pts)
    assert np.allclose(proj.uv[proj.ok], uv[proj.ok])
    assert np.all(proj.ok == CAM.in_image(uv, margin=1.0))
    # the north wall faces away: nothing passes
    back = project_texels(CAM, pose, np.array([[5.0, 8, 3]]), np.array([0, 1.0, 0]), VisibilityOptions())
    assert not back.ok.any()
    assert south.id == "B_w0" and north.id == "B_w2"


def _segment_hits_box(p: np.ndarray, q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) bool: segment p->q (N,3 each) passes through the open box (slab test)."""
    d = q - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - p) / d
        t2 = (hi - p) / d
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return (tmax > np.maximum(tmin, 0.0) + 1e-6) & (tmin < 1.0 - 1e-6)


@pytest.mark.parametrize("ray_step_px", [0, 8])
def test_a_building_hidden_behind_another_gets_no_texels_from_the_frames_where_it_is_hidden(ray_step_px):
    front = box_building("FRONT", 0, 0, 12, 6, 10)
    back = box_building("BACK", 0, 20, 12, 28, 8)
    poses = [look_at([6, -15, 1.6], [6, 20, 4])]  # back wall entirely hidden
    poses += [look_at([x, -15, 1.6], [6, 24, 4]) for x in (-14, -10, 24)]  # partly hidden
    poses += [look_at([6 + dx, 13, 1.6], [6 + dx, 20, 4]) for dx in (-2, 2)]  # between: visible
    frames = {i: render(CAM, p, [front, back]) for i, p in enumerate(poses)}
    plan = PlanOptions(ray_step_px=ray_step_px)
    units = plan_units(
        [front, back], CAM, poses, MemoryFrames(frames), Radiometry(), targets=["BACK"], plan=plan
    )
    (unit,) = units
    assert [o.id for o in unit.occluders] == ["FRONT"]
    # the box test keeps frame 0 (the texel test must reject it); the ray test drops it already
    assert (0 in unit.frames) == (ray_step_px == 0)
    rc = RayCaster(build_scene_mesh([unit.building, *unit.occluders]))
    tex = texture_unit(unit, dict(zip(unit.frames, unit.poses, strict=True)), rc)
    k = [p.id for p in tex.polygons].index("BACK_w0")
    grid, fused = tex.grids[k], tex.textures[k]
    used = np.unique(fused.frame[fused.observed])
    assert 0 not in used
    assert {4, 5} <= set(used.tolist())
    lo, hi = np.array([0.0, 0, 0]), np.array([12.0, 6, 10])
    partly_hidden_used = 0
    for f in used:
        r, c = np.nonzero(fused.frame == f)
        pts = grid.centres(r, c)
        hidden = _segment_hits_box(pts, np.broadcast_to(poses[f].center, pts.shape), lo, hi)
        assert not hidden.any(), f"frame {f} gave {hidden.sum()} texels hidden by FRONT"
        partly_hidden_used += f in (1, 2, 3)
    # the values are the back wall's, never the occluder's
    r, c = np.nonzero(fused.observed)
    err = fused.value[r, c] - field(grid.centres(r, c))
    assert np.sqrt(np.mean(err**2)) < 0.2
    assert partly_hidden_used >= 1


def test_texels_on_a_shared_wall_are_never_visible():
    a = box_building("A", 0, 0, 10, 8, 6)
    b = box_building("B", 10, 0, 18, 8, 4)  # touches A's east wall (x = 10) up to 4 m
    rc = RayCaster(build_scene_mesh([a, b]))
    east = a.polygons[1]
    g = texel_grid(east, "A", TexelOptions(resolution_px_per_m=5))
    r, c = g.masked_indices()
    pts = g.centres(r, c)
    got = buried_texels(rc, pts, g.normal)
    assert np.array_equal(got, pts[:, 2] < 4.0)


def test_coarse_window_extremes_decide_as_the_element_wise_test():
    """The coarse occlusion step decides from window minima and maxima (`_coarse_all`); on a
    scene with an occluder, silhouettes and sky it must agree sample for sample with the
    element-wise test of the 2x2 window and of that window grown by one element."""
    from workers.pipeline.texture.occlusion import OcclusionScene, consistent_samples

    front = box_building("FRONT", 0, 0, 12, 6, 10)
    back = box_building("BACK", -6, 20, 20, 28, 14)
    rc = RayCaster(build_scene_mesh([front, back]))
    opts = VisibilityOptions()
    scene = OcclusionScene(rc, CAM, opts)
    pose = look_at([4, -15, 1.6], [6, 24, 5])
    rng = np.random.default_rng(11)
    uv = rng.uniform([2, 2], [CAM.width - 3, CAM.height - 3], (4000, 2))
    # the distance each sample's ray has to the first surface, and a plane group per sample:
    # half of them the true one, half a wrong one or a wrong distance
    hits = rc.cast(np.broadcast_to(pose.center, (len(uv), 3)), CAM.bearing(uv) @ pose.R_world_from_cam.T)
    seen = np.isfinite(hits.t)
    uv, t, poly = uv[seen], hits.t[seen], hits.polygon[seen]
    group = scene.polygon_group[poly].copy()
    wrong = rng.random(len(uv)) < 0.25
    group[wrong] = scene.polygon_group[(poly[wrong] + 1) % rc.mesh.n_polygons]
    t = np.where(rng.random(len(uv)) < 0.1, t + 2.0, t)
    buf = scene.buffer(pose, uv, scene.step, 1)
    got = scene._coarse_all(buf, uv, t, group)
    pg = scene.polygon_group
    core = consistent_samples(buf, uv, t, group, pg, opts, 0)
    ring_ = consistent_samples(buf, uv, t, group, pg, opts, 1)
    assert np.array_equal(got, core & ring_)
    assert 0.2 < got.mean() < 0.9  # both outcomes occur


def test_stacked_candidates_lose_no_texel_the_frame_would_improve():
    """The per-frame block culling of all surfaces at once (`UnitTexels.candidates`) keeps every
    texel that the projection and ranking (`observe`) would accept from the whole surface."""
    from workers.pipeline.texture.frame_pass import UnitTexels, observe
    from workers.pipeline.texture.fused import SurfaceTexture
    from workers.pipeline.texture.fusion import SurfaceTexels

    b = box_building("B", 0, 0, 30, 12, 9)
    grids = [g for p in b.polygons if (g := texel_grid(p, "B", TexelOptions(resolution_px_per_m=10)))]
    surfaces = [SurfaceTexels.of(g) for g in grids]
    textures = [SurfaceTexture.empty(g.shape) for g in grids]
    stack = UnitTexels.of(surfaces, textures)
    opts = VisibilityOptions()
    n_seen = 0
    for center in ([15, -12, 1.6], [-8, -6, 1.6], [40, 20, 30], [18, -4, 50]):
        pose = look_at(center, [15, 6, 4])
        every = observe(CAM, pose, stack, np.arange(len(stack.points)), opts, 1.0)
        cand = stack.candidates(CAM, pose, opts, 1.0)
        kept = observe(CAM, pose, stack, cand, opts, 1.0)
        assert np.array_equal(every.idx, kept.idx)
        assert len(cand) < len(stack.points)  # something was culled
        n_seen += len(every.idx)
    assert n_seen > 1000


def test_pixels_to_cast_are_exactly_the_sampling_windows():
    """The pixels an occlusion step casts (`_CastGrid.needed`, a dilation of the window corners)
    are exactly the union of the samples' windows: 2x2 grown by `m` around the top-left pixel,
    and the `(3 + 2m)²` pixel corners from the top-left corner."""
    from workers.pipeline.texture.occlusion import _CastGrid, _offsets

    grid = _CastGrid(np.zeros((50, 60, 3), np.float32))
    rng = np.random.default_rng(5)
    for m, n in ((0, 40), (1, 40), (2, 40), (0, 3), (1, 2)):  # dense and listed
        lin = rng.integers(m, 44 - m, n) * 60 + rng.integers(m, 54 - m, n)
        want = np.unique(lin[:, None] + _offsets(60, m)[None])
        assert np.array_equal(grid.needed(lin, 2 + 2 * m, m), want)
        k = np.arange(3 + 2 * m)
        want = np.unique(lin[:, None] + (k[:, None] * 60 + k[None, :]).ravel()[None])
        assert np.array_equal(grid.needed(lin, 3 + 2 * m, 0), want)


def test_pixels_to_cast_by_marking_equal_the_sorted_list():
    """Listed windows of more than `_SORT_MAX` elements are marked in the grid's flag array
    instead of sorted: the same pixels, and the flags are clear again for the next call."""
    from workers.pipeline.texture.occlusion import _SORT_MAX, _CastGrid, _offsets

    grid = _CastGrid(np.zeros((400, 500, 3), np.float32))
    rng = np.random.default_rng(6)
    paths = set()
    for m, n in ((1, 300), (0, 40), (1, 300), (2, 200), (1, 20)):
        lin = rng.integers(m, 396 - m, n) * 500 + rng.integers(m, 496 - m, n)
        assert n * (2 + 2 * m) ** 2 * 8 < grid.height * grid.width  # the listed path
        want = np.unique(lin[:, None] + _offsets(500, m)[None])
        got = grid.needed(lin, 2 + 2 * m, m)
        assert np.array_equal(got, want)
        paths.add(n * (2 + 2 * m) ** 2 > _SORT_MAX)
        assert not grid._mark.any()
    assert paths == {True, False}  # both the sorted and the marked list ran


def test_a_building_glimpsed_by_one_sparse_ray_is_planned_from_a_denser_grid():
    """A small far building that only one ray of the every-8th-pixel grid hits (fewer than
    `min_ray_hits`) gets its unit from the denser grid over its box, and none without it."""
    D = 30.0
    b_lo, b_hi = CAM.bearing(np.array([[97.5, 150.5], [102.5, 145.5]]))  # its image box's corners
    x0, x1 = D * b_lo[0] / b_lo[2], D * b_hi[0] / b_hi[2]
    zc = D * b_lo[1] / b_lo[2]  # camera height putting the building's foot (z = 0) at row 150.5
    h = zc - D * b_hi[1] / b_hi[2]
    tiny = box_building("TINY", x0, 0.0, x1, 0.05, h)
    pose = look_at([0, -D, zc], [0, 0, zc])
    frames = MemoryFrames({0: render(CAM, pose, [tiny])})
    sparse = plan_units([tiny], CAM, [pose], frames, Radiometry(), plan=PlanOptions(glimpse_step_px=0))
    assert sparse == []  # one hit of the sparse grid: fewer than `min_ray_hits`
    (unit,) = plan_units([tiny], CAM, [pose], frames, Radiometry())
    assert unit.frames == (0,)
    # a building no sparse ray hits stays unplanned (only glimpsed buildings get the dense grid)
    far = box_building("FAR", x0 + 2.0, 0.0, x1 + 2.0, 0.05, h)  # 12 px right: between the rays
    assert [u.building.id for u in plan_units([far], CAM, [pose], frames, Radiometry())] == []

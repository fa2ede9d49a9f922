"""Sampling, local resolution, alignment and fusion against analytic ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from tests.unit.texture_scene import box_building, field, look_at, render
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.manifest import MemoryFrames, Radiometry
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
from workers.pipeline.plan import plan_units
from workers.pipeline.texture.alignment import AlignOptions, align_partial
from workers.pipeline.texture.fusion import FusionOptions, SurfaceTexture, local_resolution, sample_bilinear
from workers.pipeline.units import UnitOptions, texture_unit

CAM = Camera(320, 256, 300.0, 300.0, 159.5, 127.5, k1=-0.05)


def test_bilinear_sampling_is_exact_on_affine_images_and_clamps_at_the_border():
    H, W = 7, 9
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    img = (300.0 + 0.5 * u - 0.25 * v).astype(np.float32)
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [W - 1, H - 1], size=(500, 2))
    uv[:4] = [[0, 0], [W - 1, H - 1], [W - 1, 0.3], [2.5, H - 1]]
    got = sample_bilinear(img, uv)
    assert got.dtype == np.float32
    assert np.allclose(got, 300.0 + 0.5 * uv[:, 0] - 0.25 * uv[:, 1], atol=1e-4)
    outside = sample_bilinear(img, np.array([[-0.4, 2.0], [W - 0.6, 2.0]]))
    assert outside == pytest.approx([img[2, 0], img[2, W - 1]])


def test_local_resolution_of_a_fronto_parallel_view_is_distance_over_focal_length():
    pose = look_at([0, -20, 0], [0, 0, 0])
    pts = np.array([[0.0, 0, 0], [3.0, 0, 2.0]])
    rs, rt = local_resolution(CAM, pose, pts, np.array([1.0, 0, 0]), np.array([0, 0, 1.0]))
    assert rs[0] == pytest.approx(20 / 300) and rt[0] == pytest.approx(20 / 300)
    # an oblique view stretches the resolution along the wall by 1/cos
    pose2 = look_at([-20, -20, 0], [0, 0, 0])
    rs2, rt2 = local_resolution(CAM, pose2, pts[:1], np.array([1.0, 0, 0]), np.array([0, 0, 1.0]))
    assert rs2[0] == pytest.approx(np.hypot(20, 20) / 300 / np.cos(np.radians(45)), rel=1e-6)
    assert rt2[0] == pytest.approx(np.hypot(20, 20) / 300, rel=1e-6)


def _wall_texture(dx: float, dy: float, H: int = 60, W: int = 100, edge: float = 0.15) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    x = (xx + 0.5 - dx) * 0.1
    z = 6 - (yy + 0.5 - dy) * 0.1
    pts = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], 1)
    return field(pts, edge).reshape(H, W).astype(np.float32)


@pytest.mark.parametrize("shift", [(0.3, -0.2), (1.4, 0.7), (-0.05, 0.02)])
def test_alignment_recovers_subtexel_shifts_on_a_partial_overlap(shift):
    rng = np.random.default_rng(5)
    fused = _wall_texture(0, 0)
    partial = _wall_texture(*shift) + rng.normal(0, 0.05, fused.shape).astype(np.float32)
    fused[:, 70:] = np.nan
    partial[:, :20] = np.nan
    partial[:10] = np.nan
    got = align_partial(fused, partial, AlignOptions())
    assert got is not None
    assert got[0] == pytest.approx(shift[0], abs=0.05) and got[1] == pytest.approx(shift[1], abs=0.05)


def test_alignment_is_rejected_without_common_structure_or_beyond_its_bound():
    rng = np.random.default_rng(6)
    fused = _wall_texture(0, 0)
    assert align_partial(fused, rng.normal(285, 2, fused.shape).astype(np.float32), AlignOptions()) is None
    assert align_partial(fused, _wall_texture(3.5, 0.0), AlignOptions(max_shift_texels=2.0)) is None
    flat = np.full(fused.shape, 285.0, np.float32)
    assert align_partial(flat, flat, AlignOptions()) is None


def test_merge_keeps_the_best_resolution_in_recording_order():
    tex = SurfaceTexture.empty((2, 2))
    rows, cols = np.array([0, 0, 1]), np.array([0, 1, 0])
    tex.merge(rows, cols, np.array([1, 2, 3], np.float32), np.array([0.05, 0.05, 0.05]), np.zeros(3), 0)
    tex.merge(rows, cols, np.array([10, 20, 30], np.float32), np.array([0.04, 0.06, 0.05]), np.zeros(3), 1)
    assert tex.value[0, 0] == 10 and tex.value[0, 1] == 2 and tex.value[1, 0] == 3
    assert tex.frame.tolist() == [[1, 0], [0, -1]]
    assert np.isnan(tex.value[1, 1])


def _drive(edge: float = 0.15, n: int = 10) -> tuple[list, list[Pose], dict]:
    b = box_building("B1", 0, 0, 12, 8, 7, holes=True)
    poses = [look_at([-4 + 2.0 * k, -14, 1.6], [-1 + 2.0 * k, 0, 4.0]) for k in range(n)]
    frames = {i: render(CAM, p, [b], edge_m=edge) for i, p in enumerate(poses)}
    return [b], poses, frames


def _errors(tex, polygon_id: str, edge: float = 0.15) -> tuple[float, float, float]:
    k = [p.id for p in tex.polygons].index(polygon_id)
    g, t = tex.grids[k], tex.textures[k]
    r, c = np.nonzero(g.mask & t.observed)
    err = t.value[r, c] - field(g.centres(r, c), edge)
    truth = np.full(g.shape, np.nan, np.float32)
    rr, cc = np.nonzero(g.mask)
    truth[rr, cc] = field(g.centres(rr, cc), edge)
    shift = align_partial(truth, np.where(t.observed, t.value, np.nan), AlignOptions(refine_iterations=5))
    assert shift is not None
    return float(np.sqrt(np.mean(err**2))), float(np.hypot(shift[0], shift[1])), len(r) / g.n_texels


def test_fused_texture_of_an_error_free_drive_matches_the_ground_truth():
    buildings, poses, frames = _drive()
    (unit,) = plan_units(buildings, CAM, poses, MemoryFrames(frames), Radiometry())
    rc = RayCaster(build_scene_mesh(buildings))
    tex = texture_unit(unit, dict(zip(unit.frames, unit.poses, strict=True)), rc)
    rmse, misreg, coverage = _errors(tex, "B1_w0")
    assert rmse < 0.05
    assert misreg < 0.05
    assert coverage > 0.93  # texels within ~2 px of the outline and the holes are left out (blur margin)
    k = [p.id for p in tex.polygons].index("B1_w0")
    # every texel records the frame it came from, and that frame had the best resolution there
    t = tex.textures[k]
    assert set(np.unique(t.frame[t.observed]).tolist()) <= set(unit.frames)
    assert np.all(np.isfinite(t.value[t.observed])) and np.all(np.isnan(t.value[~t.observed]))


def test_alignment_pulls_frames_with_a_pose_error_onto_the_fused_texture():
    buildings, poses, frames = _drive(n=8)
    # the later half of the frames was recorded 0.12 m further east than the poses say
    bad = [Pose(p.R_world_from_cam, p.center + ([0.12, 0, 0] if i >= 4 else 0)) for i, p in enumerate(poses)]
    frames = {i: render(CAM, p, buildings) for i, p in enumerate(bad)}
    results = {}
    for align in (False, True):
        opts = UnitOptions(fusion=FusionOptions(align=align))
        (unit,) = plan_units(buildings, CAM, poses, MemoryFrames(frames), Radiometry(), options=opts)
        rc = RayCaster(build_scene_mesh(buildings))
        tex = texture_unit(unit, dict(zip(unit.frames, unit.poses, strict=True)), rc)
        k = [p.id for p in tex.polygons].index("B1_w0")
        results[align] = (_errors(tex, "B1_w0"), tex.textures[k].shifts)
    (rmse_off, _, _), _ = results[False]
    (rmse_on, _, _), shifts = results[True]
    assert rmse_on < 0.6 * rmse_off
    assert shifts and all(abs(dx) > 0.5 for f, (dx, _) in shifts.items() if f >= 4)


def _keep_priors(camera, building, raycaster, frames, frame_source, prior, accuracy, **_):
    """A refiner that confirms no pose: every frame keeps its prior."""
    from workers.pipeline.results import RefinedPose

    return {f: RefinedPose(f, prior[f], "prior", float("nan"), 0) for f in frames}


@pytest.mark.parametrize(("sigma_m", "sigma_deg", "textured"), [(2.0, 1.0, False), (0.005, 0.005, True)])
def test_frames_left_at_uncertain_priors_do_not_texture_the_building(sigma_m, sigma_deg, textured):
    from workers.pipeline.geometry.manifest import Accuracy
    from workers.pipeline.units import run_building_unit

    buildings, poses, frames = _drive(n=4)
    acc = Accuracy(np.full(3, sigma_m), np.full(3, sigma_deg))
    (unit,) = plan_units(buildings, CAM, poses, MemoryFrames(frames), Radiometry(), accuracy=acc)
    result = run_building_unit(unit, refiner=_keep_priors)
    wall = next(s for s in result.surfaces if s.polygon_id == "B1_w0")
    if textured:  # priors good to a fraction of a pixel: the frames texture the building
        assert result.frames_withheld == () and wall.texels_observed > 0
    else:  # priors metres off: no texture from them, and the report says why
        assert set(result.frames_withheld) == set(unit.frames)
        assert wall.texels_observed == 0 and "withheld" in wall.reason


class _CountingFrames:
    """A `FrameSource` over `MemoryFrames` that counts the loads of each frame (fresh copies)."""

    def __init__(self, frames: dict[int, np.ndarray]) -> None:
        self.frames = MemoryFrames(frames)
        self.loads: dict[int, int] = {}

    def load(self, index: int) -> np.ndarray:
        self.loads[index] = self.loads.get(index, 0) + 1
        return self.frames.load(index).copy()


def _load_all_keep_priors(camera, building, raycaster, frames, frame_source, prior, accuracy, **kw):
    """`_keep_priors` after loading every frame, as `orientation.building.refine_building` does."""
    for f in frames:
        frame_source.load(f)
    return _keep_priors(camera, building, raycaster, frames, frame_source, prior, accuracy, **kw)


def test_a_refined_unit_loads_each_frame_once_and_textures_as_before() -> None:
    """With refinement, a unit's frames are loaded once (`units.HeldFrames`): the refiner's loads
    and the texturing read the same arrays, and the textures are those of a unit whose frames are
    loaded anew for texturing."""
    from workers.pipeline.geometry.manifest import Accuracy
    from workers.pipeline.units import run_building_unit

    buildings, poses, frames = _drive(n=4)
    acc = Accuracy(np.full(3, 0.005), np.full(3, 0.005))
    source = _CountingFrames(frames)
    (unit,) = plan_units(buildings, CAM, poses, source, Radiometry(), accuracy=acc)
    held = run_building_unit(unit, refiner=_load_all_keep_priors)
    assert source.loads == dict.fromkeys(unit.frames, 1)
    (plain,) = plan_units(buildings, CAM, poses, MemoryFrames(frames), Radiometry(), accuracy=acc)
    again = run_building_unit(plain, refiner=_keep_priors)
    assert [t.name for t in held.tiles] == [t.name for t in again.tiles] and held.tiles
    for a, b in zip(held.tiles, again.tiles, strict=True):
        np.testing.assert_array_equal(a.dn, b.dn)


@pytest.mark.parametrize("coplanar_clean", [True, False])
def test_pixels_of_a_coplanar_polygon_are_clean_only_when_asked(coplanar_clean: bool) -> None:
    """A wall split into two coplanar polygons at x = 4, seen head-on from 12 m (about 65 pixels
    per metre): a texel 1 cm from the seam reads pixels of both; they count as clean for it only
    with `VisibilityOptions.coplanar_clean` (otherwise only its own polygon's pixels do), while a
    texel 1 m from the seam is clean either way."""
    from dataclasses import replace as _replace

    from tests.unit.orientation_scenes import CAMERA, _poly
    from tests.unit.orientation_scenes import box_building as box
    from tests.unit.orientation_scenes import look_at as look
    from workers.pipeline.geometry.citymodel import Building
    from workers.pipeline.texture.occlusion import OcclusionScene
    from workers.pipeline.texture.visibility import VisibilityOptions

    b = box("S", 0, 0, 10, 8, 6)
    polys = [p for p in b.polygons if p.id != "S_ws"]
    polys += [
        _poly("S_ws1", [(0, 0, 0), (4, 0, 0), (4, 0, 6), (0, 0, 6)], "WallSurface"),
        _poly("S_ws2", [(4, 0, 0), (10, 0, 0), (10, 0, 6), (4, 0, 6)], "WallSurface"),
    ]
    opts = _replace(VisibilityOptions(), coplanar_clean=coplanar_clean, buffer_step_px=1)
    mesh = build_scene_mesh([Building(id="S", polygons=tuple(polys))])
    scene = OcclusionScene(RayCaster(mesh), CAMERA, opts)
    pose = look(np.array([4.0, -12.0, 3.0]), np.array([4.0, 0.0, 3.0]))
    X = np.array([[3.99, 0.0, 3.0], [3.0, 0.0, 3.0]])  # on S_ws1: at the seam, 1 m from it
    uv, _ = pose.project(CAMERA, X)
    dist = np.linalg.norm(X - pose.center, axis=1)
    own = scene.polygon_group[scene.polygon_index["S_ws1"]]
    ok = scene.visible_flat(pose, uv, dist, np.full(2, own))
    assert ok.tolist() == [coplanar_clean, True]

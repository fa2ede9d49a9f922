"""The synthetic world's terrain (`synth.ground`): walls end at it, flat scenes keep their plane
bit for bit, the truth keeps it, and the reference's z-buffer renders it as the renderer does."""

from __future__ import annotations

import numpy as np
import pytest

from db.citygml.reader import read_model
from tests.conftest import DATA
from tests.reference.geometry import GROUND as REF_GROUND
from tests.reference.geometry import MIXED, scene_polygons
from tests.reference.zbuffer import RefCamera, RefGround, ZBuffer
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import build_scene_mesh
from workers.pipeline.synth import (
    GROUND,
    ErrorOptions,
    Renderer,
    SensorOptions,
    SynthOptions,
    SynthTruth,
    ThermalScene,
    gable_house,
    procedural_block,
    synthesize,
)
from workers.pipeline.synth.ground import Ground, foot_points, terrain_ground

CAM = Camera(width=200, height=160, fx=180.0, fy=180.0, cx=99.5, cy=79.5, k1=-0.1, k2=0.02)
NO_SENSOR = SensorOptions(psf_sigma_px=0, netd_k=0, column_noise_k=0, vignetting_k=0)
X0 = np.array([500000.0, 5400000.0, 100.0])  # the low house's south-west corner


def look_at(center: np.ndarray, target: np.ndarray) -> Pose:
    """Camera at `center` looking at `target`, image rows level (camera y down)."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return Pose(np.stack([x, np.cross(z, x), z], axis=1), center)


def two_levels() -> list:
    """Two houses in a row 30 m apart, the east one standing 1 m higher (a 3 % slope)."""
    return [
        gable_house("low", 10.0, 8.0, 6.0, 9.0, X0),
        gable_house("high", 10.0, 8.0, 6.0, 9.0, X0 + np.array([40.0, 0.0, 1.0])),
    ]


def test_terrain_meets_every_wall_foot_on_the_nrw_tile() -> None:
    """Through the real tile's feet (bases spanning 2.4 m) the TIN runs at each footprint edge's
    height (shared walls of buildings at two heights: the lower one's); beyond it the plane."""
    _, buildings = read_model(DATA / "nrw-tile-5659-citygml1-lod2.gml")
    g = terrain_ground(buildings, 35.0)
    assert not g.flat and 1000 < len(g.triangles) < 20000
    feet = foot_points(buildings, 0.25)  # 4 times denser than the TIN's own points
    d = g.height(feet) - feet[:, 2]
    assert np.median(np.abs(d)) < 1e-3
    assert np.percentile(d, 99) < 0.03 and d.max() < 0.2  # never far above a foot
    lo = g.vertices[:, :2].min(axis=0)
    assert np.allclose(g.height(np.array([lo - 1.0, lo + np.array([-5.0, 3.0])])), 35.0)


def test_nothing_is_above_the_terrains_top_and_below_ground_skips_only_those() -> None:
    """`Ground.top` bounds every height, so `synth_eval.below_ground` looks up only the texel
    centres under it and gives what the full lookup gives; no points, no heights."""
    from workers.pipeline.texture.texel import TexelOptions, texel_grid
    from workers.synth_eval import below_ground

    _, buildings = read_model(DATA / "nrw-tile-5659-citygml1-lod2.gml")
    g = terrain_ground(buildings, 35.0)
    lo, hi = g.vertices[:, :2].min(axis=0), g.vertices[:, :2].max(axis=0)
    xy = np.random.default_rng(3).uniform(lo - 5.0, hi + 5.0, (20000, 2))
    assert g.height(xy).max() <= g.top and g.top > 35.0
    assert g.height(np.zeros((0, 2))).shape == (0,)
    walls = [(b, p) for b in buildings for p in b.polygons if p.surface_class == "WallSurface"][:40]
    compared = 0
    for b, poly in walls:
        grid = texel_grid(poly, b.id, TexelOptions(resolution_px_per_m=5.0))
        if grid is None:
            continue
        full = below_ground(grid, g.height)
        assert np.array_equal(below_ground(grid, g.height, g.top), full)
        compared += int(full.any())
    assert compared > 0  # some walls do reach below the terrain's TIN


def test_the_reference_evaluation_skips_only_points_above_the_terrains_top() -> None:
    """`tests.reference.evaluate.above_ground` looks up only points under `Ground.top` and
    answers what the full lookup answers, on points from under the TIN's lowest to above its
    top (some of them below the terrain), and on a flat ground."""
    from types import SimpleNamespace

    from tests.reference.evaluate import above_ground

    _, buildings = read_model(DATA / "nrw-tile-5659-citygml1-lod2.gml")
    g = terrain_ground(buildings, 35.0)
    lo, hi = g.vertices[:, :2].min(axis=0), g.vertices[:, :2].max(axis=0)
    rng = np.random.default_rng(5)
    X = np.column_stack([rng.uniform(lo - 5.0, hi + 5.0, (20000, 2)),
                         rng.uniform(g.vertices[:, 2].min() - 1.0, g.top + 5.0, 20000)])  # fmt: skip
    truth = SimpleNamespace(ground=g, ground_z=35.0, ground_height=g.height)
    full = X[:, 2] >= g.height(X)
    assert np.array_equal(above_ground(X, truth), full)
    assert (~full).sum() > 1000 and (X[:, 2] >= g.top).sum() > 1000  # both branches taken
    flat = SimpleNamespace(ground=None, ground_z=36.0, ground_height=lambda xy: np.full(len(xy), 36.0))
    assert np.array_equal(above_ground(X, flat), X[:, 2] >= 36.0)


def test_flat_scenes_keep_their_plane_bit_for_bit() -> None:
    """Every base at one height: the ground is the plane, frames identical with the terrain off."""
    blds = procedural_block(6, seed=2)
    assert terrain_ground(blds, 0.0).flat
    opts = SynthOptions(n_frames=3, seed=3, buildings=3, errors=ErrorOptions(enabled=False))
    a = synthesize(blds, opts)
    b = synthesize(blds, SynthOptions(**{**opts.__dict__, "terrain": False}))
    assert a.truth.ground is None and "ground" not in a.truth.to_dict()
    for k in (0, 2):
        assert np.array_equal(a.frames[k], b.frames[k])


@pytest.fixture(scope="module")
def hill() -> dict:
    blds = two_levels()
    mesh = build_scene_mesh(blds)
    thermal = ThermalScene(blds, mesh.polygon_ids, seed=1)
    ground = terrain_ground(blds, 100.5)
    return {"blds": blds, "mesh": mesh, "thermal": thermal, "ground": ground}


def test_the_low_house_wall_shows_down_to_its_foot(hill: dict) -> None:
    """A plane at the median base (100.5 m) hides the low house's wall below it; the terrain
    shows it down to its foot (100 m), and the ground right below it."""
    g: Ground = hill["ground"]
    assert not g.flat
    pose = look_at(X0 + np.array([5.0, -10.0, 1.5]), X0 + np.array([5.0, 0.0, 1.0]))
    terrain = Renderer(hill["mesh"], hill["thermal"], CAM, g, NO_SENSOR)
    plane = Renderer(hill["mesh"], hill["thermal"], CAM, 100.5, NO_SENSOR)
    south = hill["thermal"].polygon_index("low-wall-s")
    for z, want_terrain, want_plane in ((0.15, south, GROUND), (-0.15, GROUND, GROUND), (1.5, south, south)):
        uv, _ = pose.project(CAM, (X0 + np.array([5.0, 0.0, z]))[None])
        u, v = np.rint(uv[0]).astype(int)
        assert terrain.labels(pose)[0][v, u] == want_terrain, z
        assert plane.labels(pose)[0][v, u] == want_plane, z


def test_truth_keeps_the_terrain() -> None:
    _, buildings = read_model(DATA / "nrw-tile-5659-citygml1-lod2.gml")
    res = synthesize(
        buildings, SynthOptions(n_frames=2, seed=1, buildings=3, errors=ErrorOptions(enabled=False))
    )
    t = res.truth
    assert t.ground is not None and not t.ground.flat
    back = SynthTruth.from_dict(t.to_dict())
    xy = t.ground.vertices[:50, :2] + 0.3
    assert np.allclose(back.ground_height(xy), t.ground_height(xy), atol=1e-4)
    assert np.array_equal(back.ground.triangles, t.ground.triangles)


def test_reference_zbuffer_renders_the_terrain_as_the_renderer(hill: dict) -> None:
    """The reference's own rasterization of the TIN names the same thing as the renderer's ray
    casting away from edges, ground included."""
    g: Ground = hill["ground"]
    renderer = Renderer(hill["mesh"], hill["thermal"], CAM, g, NO_SENSOR)
    polys = scene_polygons(hill["blds"])
    names = {p.index: p.polygon_id for p in polys}
    ref_ground = RefGround(g.z, g.vertices, g.triangles)
    zb = ZBuffer(RefCamera.from_params(CAM), polys, ref_ground)
    for eye, target in (([20.0, -18.0, 3.0], [20.0, 4.0, 0.5]), ([60.0, -30.0, 30.0], [25.0, 4.0, 0.0])):
        pose = look_at(X0 + np.array(eye), X0 + np.array(target))
        buf = zb.render(pose.R_world_from_cam, pose.center)
        lab = renderer.labels(pose)[0]
        ok = buf.pure != MIXED
        ours = np.array([names.get(i, "ground" if i == REF_GROUND else "sky") for i in buf.pure[ok]])
        ids = hill["thermal"].polygon_ids
        theirs = np.array([ids[i] if i >= 0 else ("ground" if i == GROUND else "sky") for i in lab[ok]])
        assert (ours == "ground").mean() > 0.1
        assert np.mean(ours == theirs) > 0.999

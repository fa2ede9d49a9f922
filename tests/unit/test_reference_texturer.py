"""The reference texturer (`tests/reference`) on a hand-built scene: a house wall, a shed in front
of part of it, two frames from known poses rendered by the synthetic renderer.

What the yardstick must do: no value for texels the shed hides, values within a kelvin bound of
the truth where the wall is seen cleanly, and no observation whose sampling footprint touches the
shed's silhouette (checked against the renderer's own per-pixel labels, not the reference's)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.reference.geometry import MIXED, ref_grid, scene_polygons
from tests.reference.texturer import ReferenceOptions, RefTexture, bilinear, reference_textures
from tests.reference.zbuffer import RefCamera, ZBuffer
from workers.pipeline.geometry.citymodel import Building, Polygon, Ring
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import build_scene_mesh
from workers.pipeline.synth import Renderer, SensorOptions, ThermalScene, default_camera

GROUND_Z = -0.01


def _poly(pid: str, pts: list[list[float]], cls: str) -> Polygon:
    """A polygon from an open list of vertices (closed here)."""
    return Polygon(id=pid, exterior=Ring(pid + "_r", np.array([*pts, pts[0]], float)), surface_class=cls)


def box(name: str, x0: float, x1: float, y0: float, y1: float, z1: float) -> Building:
    """A flat-roofed box `[x0, x1] × [y0, y1] × [0, z1]` (metres), walls counter-clockwise seen
    from outside; the south wall (`<name>_s`, normal −y) faces the cameras."""
    return Building(
        id=name,
        polygons=(
            _poly(f"{name}_s", [[x0, y0, 0], [x1, y0, 0], [x1, y0, z1], [x0, y0, z1]], "WallSurface"),
            _poly(f"{name}_e", [[x1, y0, 0], [x1, y1, 0], [x1, y1, z1], [x1, y0, z1]], "WallSurface"),
            _poly(f"{name}_n", [[x1, y1, 0], [x0, y1, 0], [x0, y1, z1], [x1, y1, z1]], "WallSurface"),
            _poly(f"{name}_w", [[x0, y1, 0], [x0, y0, 0], [x0, y0, z1], [x0, y1, z1]], "WallSurface"),
            _poly(f"{name}_t", [[x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], "RoofSurface"),
        ),
    )


def look_at(center: list[float], target: list[float]) -> Pose:
    """Camera at `center` looking at `target` (world, metres), image rows level."""
    c, t = np.array(center, float), np.array(target, float)
    z = (t - c) / np.linalg.norm(t - c)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return Pose(np.stack([x, np.cross(z, x), z], axis=1), c)


SHED = (4.0, 6.5, -4.0, -2.0, 4.0)  # x0, x1, y0, y1, height


def shed_hides(X: np.ndarray, C: np.ndarray) -> np.ndarray:
    """`(N,)` bool: the segment from points `X (N, 3)` to the camera centre `C` passes through the
    shed (slab test on its box)."""
    x0, x1, y0, y1, h = SHED
    lo, hi = np.array([x0, y0, 0.0]), np.array([x1, y1, h])
    d = C - X
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - X) / d, (hi - X) / d
    tmin = np.nanmax(np.minimum(ta, tb), axis=1)
    tmax = np.nanmin(np.maximum(ta, tb), axis=1)
    return (tmax >= np.maximum(tmin, 0.0)) & (tmin <= 1.0)


@pytest.fixture(scope="module")
def scene() -> dict:
    """The rendered scene and the reference's texture of the house's south wall."""
    house, shed = box("house", 0, 12, 0, 8, 7), box("shed", *SHED)
    blds = [house, shed]
    mesh = build_scene_mesh(blds)
    thermal = ThermalScene(blds, mesh.polygon_ids, seed=3)
    cam = default_camera()
    poses = [look_at([6, -16, 2], [6, 0, 3.5]), look_at([10, -14, 2.5], [5, 0, 3.5])]
    renderer = Renderer(mesh, thermal, cam, GROUND_Z, SensorOptions(), seed=1)
    frames = [renderer.frame(p, i) for i, p in enumerate(poses)]
    labels = [renderer.labels(p)[0] for p in poses]
    tex = reference_textures(
        scene_polygons(blds), {"house_s"}, RefCamera.from_params(cam),
        [(p.R_world_from_cam, p.center) for p in poses], lambda i: frames[i],
        ReferenceOptions(texels_per_m=10), ground_z=GROUND_Z,
    )  # fmt: skip
    wall = mesh.polygon_ids.index("house_s")
    return {"tex": tex["house_s"], "poses": poses, "cam": cam, "labels": labels, "wall": wall,
            "thermal": thermal, "frames": frames}  # fmt: skip


def _blocks(scene: dict, k: int, ring: int) -> tuple[np.ndarray, np.ndarray]:
    """Per texel in frame `k`: (inside the image, every pixel of the 2 × 2 bilinear support plus
    `ring` pixels shows the wall by the renderer's labels) `(N,)` bool each."""
    tex: RefTexture = scene["tex"]
    cam, lab = scene["cam"], scene["labels"][k]
    uv, depth = scene["poses"][k].project(cam, tex.grid.centres)
    inside = np.all(np.isfinite(uv), axis=1) & (depth > 0)
    inside &= (uv[:, 0] >= ring + 1) & (uv[:, 0] < cam.width - ring - 2)
    inside &= (uv[:, 1] >= ring + 1) & (uv[:, 1] < cam.height - ring - 2)
    clean = inside.copy()
    u0 = np.floor(np.where(inside, uv[:, 0], 0)).astype(int)
    v0 = np.floor(np.where(inside, uv[:, 1], 0)).astype(int)
    for dv in range(-ring, 2 + ring):
        for du in range(-ring, 2 + ring):
            clean &= lab[v0 + dv, u0 + du] == scene["wall"]
    return inside, clean


def test_wall_normal_and_grid(scene: dict) -> None:
    tex: RefTexture = scene["tex"]
    assert np.allclose(tex.grid.polygon.normal, [0, -1, 0])
    assert len(tex.grid.rows) == pytest.approx(12 * 7 * 100, rel=0.01)  # 0.1 m texels on 12 × 7 m


def test_hidden_texels_get_no_observation(scene: dict) -> None:
    tex: RefTexture = scene["tex"]
    X = tex.grid.centres
    hidden = [shed_hides(X, p.center) for p in scene["poses"]]
    for k in range(len(scene["poses"])):
        seen_in_k = tex.obs_texel[tex.obs_frame == k]
        assert not hidden[k][seen_in_k].any(), f"frame {k}: an observation of a texel the shed hides"
    always = hidden[0] & hidden[1]
    assert always.sum() > 300  # the scene does hide part of the wall from both cameras
    assert np.all(np.isnan(tex.value[always])) and np.all(tex.count[always] == 0)
    assert not tex.seen[always].any()


def test_visible_interior_texels_match_truth(scene: dict) -> None:
    tex: RefTexture = scene["tex"]
    interior = np.ones(len(tex.value), bool)
    for k in range(len(scene["poses"])):
        inside, clean = _blocks(scene, k, ring=4)
        interior &= ~inside | clean  # never near the shed's silhouette or the wall's outline
    interior &= np.any([_blocks(scene, k, ring=4)[1] for k in range(2)], axis=0)
    assert interior.sum() > 4000
    assert np.all(np.isfinite(tex.value[interior])), "a cleanly visible texel got no value"
    truth = scene["thermal"].surface_temperature("house_s", tex.grid.centres[interior])
    err = tex.value[interior] - truth
    assert np.sqrt(np.mean(err**2)) < 0.15
    assert np.percentile(np.abs(err), 99) < 0.6


def test_silhouette_texels_are_rejected(scene: dict) -> None:
    tex: RefTexture = scene["tex"]
    rejected_near_edge = 0
    for k in range(len(scene["poses"])):
        inside, clean = _blocks(scene, k, ring=1)
        _, support = _blocks(scene, k, ring=0)
        seen_in_k = np.zeros(len(tex.value), bool)
        seen_in_k[tex.obs_texel[tex.obs_frame == k]] = True
        # the 2 × 2 bilinear support touches the shed or the sky: never an observation
        assert not (seen_in_k & inside & ~support).any()
        # the blur ring touches another surface: never an observation (a 1-pixel tolerance for
        # the reference's own rasterisation is not needed: it is stricter, see `MIXED` pixels)
        assert not (seen_in_k & inside & ~clean).any()
        rejected_near_edge += int((inside & support & ~clean).sum())
        # and it does not throw away what is clean with a 2-pixel margin to spare
        _, wide = _blocks(scene, k, ring=3)
        assert seen_in_k[wide].mean() > 0.98
    assert rejected_near_edge > 10  # texels next to the silhouette exist and were rejected


def test_zbuffer_agrees_with_renderer_labels(scene: dict) -> None:
    """Away from edges the reference's own z-buffer names the same polygon as the renderer."""
    polys = scene_polygons([box("house", 0, 12, 0, 8, 7), box("shed", *SHED)])
    zb = ZBuffer(RefCamera.from_params(scene["cam"]), polys, GROUND_Z)
    names = {p.index: p.polygon_id for p in polys}
    pose = scene["poses"][1]
    buf = zb.render(pose.R_world_from_cam, pose.center)
    lab = scene["labels"][1]
    ok = buf.pure >= 0
    ids = np.array([scene["thermal"].polygon_ids[i] if i >= 0 else "" for i in lab[ok]])
    ours = np.array([names[i] for i in buf.pure[ok]])
    assert np.mean(ids == ours) > 0.999
    assert (buf.pure == MIXED).mean() < 0.05


def test_bilinear_matches_opencv_remap(scene: dict) -> None:
    import cv2

    img = scene["frames"][0]
    rng = np.random.default_rng(0)
    uv = rng.uniform([5, 5], [600, 500], size=(200, 2))
    ref = cv2.remap(img, uv[:, :1].astype(np.float32), uv[:, 1:].astype(np.float32), cv2.INTER_LINEAR)
    diff = np.abs(bilinear(img, uv) - ref.ravel())  # OpenCV's weights are fixed point (1/32)
    assert np.median(diff) < 0.005 and diff.max() < 0.2
    assert ref_grid(scene_polygons([box("b", 0, 1, 0, 1, 1)])[0], 1.0) is not None

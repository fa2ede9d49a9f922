"""The exact edge test of the clean-pixel rule (`texture.footprint`): a polygon corner or a thin
strip inside a texel's footprint but between the occlusion test's rays makes it mixed; geometry
behind the wall or just outside the footprint does not. Checked against a dense ray cast of the
footprint (every 1/40 px) on a wall seen head-on from 12 m (65 px/m)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from tests.unit.orientation_scenes import CAMERA, _poly, box_building, look_at
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
from workers.pipeline.texture.footprint import outline_edges
from workers.pipeline.texture.occlusion import OcclusionScene
from workers.pipeline.texture.visibility_options import VisibilityOptions

POSE = look_at(np.array([4.0, -12.0, 3.0]), np.array([4.0, 0.0, 3.0]))
#: the texel on the wall `S_ws` (y = 0) whose footprint the occluders poke into
TEXEL = np.array([[3.7, 0.0, 3.2]])


def _on_plane(pose: Pose, uv: np.ndarray, y: float) -> np.ndarray:
    """World points `(N, 3)` on the plane `y = y` that project to pixels `uv (N, 2)`."""
    rays = CAMERA.bearing(uv) @ pose.R_world_from_cam.T
    s = (y - pose.center[1]) / rays[:, 1]
    return pose.center + s[:, None] * rays


def _footprint_left_top() -> tuple[float, float]:
    """Pixel coordinates of the footprint's left and top sides (the 4 × 4 block's closed area)."""
    uv, _ = POSE.project(CAMERA, TEXEL)
    return float(np.floor(uv[0, 0]) - 1.5), float(np.floor(uv[0, 1]) - 1.5)


def _scene(extra: list[np.ndarray], edges: bool) -> tuple[OcclusionScene, RayCaster]:
    """The box building `S` plus polygons `extra` (world vertex arrays) of an occluder `O`."""
    polys = [_poly(f"O_{k}", [tuple(p) for p in pts], "WallSurface") for k, pts in enumerate(extra)]
    buildings = [box_building("S", 0, 0, 10, 8, 6), Building(id="O", polygons=tuple(polys))]
    rc = RayCaster(build_scene_mesh(buildings))
    return OcclusionScene(rc, CAMERA, replace(VisibilityOptions(), boundary_edges=edges), buildings), rc


def _clean(scene: OcclusionScene) -> bool:
    """The occlusion test's verdict on `TEXEL`."""
    uv, _ = POSE.project(CAMERA, TEXEL)
    dist = np.linalg.norm(TEXEL - POSE.center, axis=1)
    own = scene.polygon_group[scene.polygon_index["S_ws"]]
    return bool(scene.visible_flat(POSE, uv, dist, np.full(1, own))[0])


def _dense_pure(scene: OcclusionScene, rc: RayCaster) -> bool:
    """Rays every 1/40 px over the footprint's closed area all hit `S_ws`."""
    u0, v0 = _footprint_left_top()
    g = np.linspace(0.0, 4.0, 161)
    uu, vv = np.meshgrid(u0 + g, v0 + g)
    d = CAMERA.bearing(np.stack([uu.ravel(), vv.ravel()], 1)) @ POSE.R_world_from_cam.T
    hits = rc.cast(np.repeat(POSE.center[None], len(d), 0), d)
    return bool(np.all(hits.polygon == scene.polygon_index["S_ws"]))


def _wedge(tip: tuple[float, float], y: float, half_width_px: float = 0.04) -> np.ndarray:
    """A thin triangle on the plane `y` whose tip projects to pixel `tip`, reaching 30 px to the
    left (its sides `half_width_px` from the tip's row there)."""
    u, v = tip
    uv = np.array([[u, v], [u - 30.0, v - half_width_px], [u - 30.0, v + half_width_px]])
    return _on_plane(POSE, uv, y)


@pytest.mark.parametrize("seed", range(6))
def test_a_corner_between_the_rays_makes_the_footprint_mixed(seed: int) -> None:
    """A wedge in front of the wall whose tip lies in the footprint midway between the rays' half-
    pixel lattice (along a row between lattice rows): the rays alone find the footprint clean,
    the dense cast and the edge test do not."""
    rng = np.random.default_rng(seed)
    u0, v0 = _footprint_left_top()
    i, j = rng.integers(0, 8, size=2)
    tip = (u0 + 0.25 + 0.5 * i, v0 + 0.25 + 0.5 * j)
    rays_only, rc = _scene([_wedge(tip, -3.0)], edges=False)
    exact, _ = _scene([_wedge(tip, -3.0)], edges=True)
    assert not _dense_pure(exact, rc)
    assert _clean(rays_only)
    assert not _clean(exact)


def test_a_strip_thinner_than_the_ray_spacing_makes_the_footprint_mixed() -> None:
    """A 0.2 px strip in front of the wall crossing the whole footprint between two ray rows."""
    u0, v0 = _footprint_left_top()
    v = v0 + 1.25
    strip = _on_plane(POSE, np.array([[u0 - 30, v - 0.1], [u0 + 30, v - 0.1], [u0 + 30, v + 0.1],
                                      [u0 - 30, v + 0.1]]), -3.0)  # fmt: skip
    rays_only, rc = _scene([strip], edges=False)
    exact, _ = _scene([strip], edges=True)
    assert not _dense_pure(exact, rc)
    assert _clean(rays_only) and not _clean(exact)


@pytest.mark.parametrize("where", ["behind the wall", "just outside the footprint"])
def test_edges_that_cannot_be_seen_in_the_footprint_leave_it_clean(where: str) -> None:
    """A wedge behind the wall (hidden by it) with its tip in the footprint, or in front of the
    wall with its tip 0.05 px left of the footprint: the footprint is clean (dense cast), and
    the edge test says so."""
    u0, v0 = _footprint_left_top()
    tip = (u0 + 1.25, v0 + 1.75) if where == "behind the wall" else (u0 - 0.05, v0 + 1.75)
    exact, rc = _scene([_wedge(tip, 3.0 if where == "behind the wall" else -3.0)], edges=True)
    assert _dense_pure(exact, rc)
    assert _clean(exact)


def test_outline_edges_are_the_rings_not_the_triangles() -> None:
    """A rectangle has 4 outline edges, an L-shaped polygon 6, a wall with two windows in a row
    12 (its triangulation joins the windows' collinear bottoms into one edge across the wall)."""
    from workers.pipeline.geometry.citymodel import Polygon, Ring

    L = _poly("L", [(0, 0, 0), (4, 0, 0), (4, 0, 1), (1, 0, 1), (1, 0, 3), (0, 0, 3)], "WallSurface")
    rect = _poly("R", [(0, 1, 0), (4, 1, 0), (4, 1, 2), (0, 1, 2)], "WallSurface")
    outer = np.array([(0, 2, 0), (12, 2, 0), (12, 2, 7), (0, 2, 7), (0, 2, 0)], float)
    holes = [np.array([(x, 2, 1), (x, 2, 2.5), (x + 1.5, 2, 2.5), (x + 1.5, 2, 1), (x, 2, 1)], float)
             for x in (2.4, 7.2)]  # fmt: skip
    wall = Polygon(id="W", exterior=Ring(id="We", coords=outer), surface_class="WallSurface",
                   interiors=tuple(Ring(id=f"Wi{k}", coords=h) for k, h in enumerate(holes)))  # fmt: skip
    buildings = [Building(id="B", polygons=(L, rect, wall))]
    mesh = build_scene_mesh(buildings)
    a, b, poly = outline_edges(buildings, mesh)
    assert np.bincount(poly, minlength=3).tolist() == [6, 4, 12]
    # no edge runs along z = 1 between the windows (x 3.9 .. 7.2)
    z1 = (np.abs(a[:, 2] + mesh.origin[2] - 1) < 1e-6) & (np.abs(b[:, 2] + mesh.origin[2] - 1) < 1e-6)
    xs = np.sort(np.stack([a[z1, 0], b[z1, 0]], 1) + mesh.origin[0], axis=1)
    assert not np.any((xs[:, 0] < 5.0) & (xs[:, 1] > 6.0))

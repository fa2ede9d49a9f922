"""Model wireframe: merging, creases, T-junctions, classes, corners, hidden-edge removal."""

from __future__ import annotations

import numpy as np
import pytest

from tests.unit.orientation_scenes import CAMERA, _poly, box_building, look_at
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
from workers.pipeline.orientation.wireframe import (
    GROUND,
    ROOF,
    WALL,
    WireframeError,
    building_wireframe,
    mesh_wireframe,
    visible_wireframe,
)


def test_box_has_twelve_merged_edges_and_eight_corners():
    wf = building_wireframe(box_building("B", 0, 0, 10, 8, 6))
    assert len(wf.vertices) == 8
    assert len(wf.edges) == 12  # each shared by two polygons, merged once
    assert len(wf.corners) == 8
    # 4 ground edges, 4 vertical wall edges, 4 roof edges
    assert np.bincount(wf.edge_class, minlength=3).tolist() == [4, 4, 4]
    assert np.all(wf.edge_weight[wf.edge_class == GROUND] < wf.edge_weight[wf.edge_class == WALL].min())


def test_gable_house_edges_classes_and_corners():
    wf = building_wireframe(box_building("G", 0, 0, 10, 8, 6, ridge=3))
    # 4 ground + 4 vertical + 2 eaves + 4 gable rakes + 1 ridge
    assert len(wf.edges) == 15
    z = wf.vertices[wf.edges][:, :, 2]
    ridge = np.all(z > 8.9, axis=1)
    assert ridge.sum() == 1 and wf.edge_class[ridge][0] == ROOF
    assert len(wf.corners) == 10  # 8 box corners + 2 gable tops


def test_split_wall_crease_is_dropped_and_t_junction_merged():
    # the south wall of a box split into two coplanar polygons; its top edge is split too,
    # while the flat roof's south edge is one long edge (a T-junction at x = 4)
    b = box_building("S", 0, 0, 10, 8, 6)
    polys = [p for p in b.polygons if p.id != "S_ws"]
    polys += [
        _poly("S_ws1", [(0, 0, 0), (4, 0, 0), (4, 0, 6), (0, 0, 6)], "WallSurface"),
        _poly("S_ws2", [(4, 0, 0), (10, 0, 0), (10, 0, 6), (4, 0, 6)], "WallSurface"),
    ]
    wf = building_wireframe(Building(id="S", polygons=tuple(polys)))
    assert len(wf.edges) == 12 + 2  # box edges, the top and ground edge split once at x = 4 ...
    # ... and no vertical crease at x = 4
    d = wf.vertices[wf.edges[:, 1]] - wf.vertices[wf.edges[:, 0]]
    mid = wf.vertices[wf.edges].mean(axis=1)
    vertical = np.abs(d[:, 2]) > 1
    assert not np.any(vertical & (np.abs(mid[:, 0] - 4) < 1e-6))
    assert len(wf.corners) == 8  # the split points are collinear: no corner


def test_scene_mesh_wireframe_recovers_the_outlines_of_all_buildings():
    a = box_building("A", 0, 0, 10, 8, 6, ridge=2)
    b = box_building("B", 20, 0, 6, 6, 4)
    wf = building_wireframe(a)
    scene = mesh_wireframe(build_scene_mesh([a, b]))
    # triangulation diagonals are gone: the outlines of both buildings remain
    assert len(scene.edges) == len(wf.edges) + 12
    assert len(scene.corners) == len(wf.corners) + 8
    with pytest.raises(WireframeError):
        mesh_wireframe(build_scene_mesh([]))


def test_empty_building_is_refused():
    with pytest.raises(WireframeError, match="B0"):
        building_wireframe(Building(id="B0", polygons=()))


def test_hidden_edges_removed_by_self_occlusion_and_by_a_neighbour():
    box = box_building("A", 0, 0, 10, 8, 6)
    pose = look_at([5, -30, 10], [5, 4, 3])  # from the south, above the roof
    caster = RayCaster(build_scene_mesh([box]))
    wf = building_wireframe(box)
    vis = visible_wireframe(wf, CAMERA, pose, caster)
    seen = set(vis.edge.tolist())
    mid = wf.vertices[wf.edges].mean(axis=1)
    # the north ground edge (y = 8, z = 0) is hidden behind the building; the south one is seen
    north_ground = int(np.argmin(np.abs(mid[:, 1] - 8) + np.abs(mid[:, 2]) + np.abs(mid[:, 0] - 5)))
    south_ground = int(np.argmin(np.abs(mid[:, 1]) + np.abs(mid[:, 2]) + np.abs(mid[:, 0] - 5)))
    assert north_ground not in seen and south_ground in seen
    # the roof's north edge is seen over the roof
    north_roof = int(np.argmin(np.abs(mid[:, 1] - 8) + np.abs(mid[:, 2] - 6) + np.abs(mid[:, 0] - 5)))
    assert north_roof in seen
    # samples project inside the frame
    uv, z = pose.project(CAMERA, vis.points)
    assert np.all(z > 0) and np.all(CAMERA.in_image(uv))
    # a taller neighbour between the camera and the box hides all of it
    wall = box_building("N", -5, -12, 20, 2, 30)
    caster2 = RayCaster(build_scene_mesh([box, wall]))
    vis2 = visible_wireframe(wf, CAMERA, pose, caster2)
    assert len(vis2.points) == 0 and len(vis2.corners) == 0

"""Ray casting against a triangulated box at UTM-sized coordinates (float32 precision trap)."""

from __future__ import annotations

import numpy as np

from workers.pipeline.geometry.citymodel import Building, Polygon, Ring
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh

X0, Y0, Z0 = 691000.0, 5334000.0, 500.0


def box(bid: str, x0: float, y0: float, w: float, d: float, h: float) -> Building:
    """An axis-aligned box building with outward-facing polygons (walls, roof, ground)."""
    x1, y1 = x0 + w, y0 + d
    z0, z1 = Z0, Z0 + h
    faces = {
        "south": [(x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1)],
        "east": [(x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1)],
        "north": [(x1, y1, z0), (x0, y1, z0), (x0, y1, z1), (x1, y1, z1)],
        "west": [(x0, y1, z0), (x0, y0, z0), (x0, y0, z1), (x0, y1, z1)],
        "roof": [(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)],
        "ground": [(x0, y0, z0), (x0, y1, z0), (x1, y1, z0), (x1, y0, z0)],
    }
    polys = []
    for name, pts in faces.items():
        ring = np.array([*pts, pts[0]], dtype=np.float64)
        cls = {"roof": "RoofSurface", "ground": "GroundSurface"}.get(name, "WallSurface")
        polys.append(Polygon(f"{bid}_{name}", Ring(f"{bid}_{name}_r", ring), surface_class=cls))
    return Building(bid, tuple(polys))


def test_normals_point_outwards_and_hits_are_exact() -> None:
    mesh = build_scene_mesh([box("B", X0, Y0, 10, 8, 6)])
    idx = mesh.polygon_index()
    np.testing.assert_allclose(mesh.polygon_normals[idx["B_south"]], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(mesh.polygon_normals[idx["B_roof"]], [0, 0, 1], atol=1e-12)
    caster = RayCaster(mesh)
    origins = np.array(
        [[X0 + 3.3, Y0 - 20.0, Z0 + 2.7], [X0 + 5.0, Y0 + 4.0, Z0 + 50.0], [X0 - 5, Y0 - 5, Z0 + 1]]
    )
    dirs = np.array([[0, 1.0, 0], [0, 0, -1.0], [-1.0, 0, 0]])
    hits = caster.cast(origins, dirs)
    assert [mesh.polygon_ids[i] for i in hits.polygon[:2]] == ["B_south", "B_roof"]
    np.testing.assert_allclose(hits.t[:2], [20.0, 44.0], atol=1e-3)  # float32 relative to origin
    assert hits.polygon[2] == -1 and np.isinf(hits.t[2])


def test_visibility_with_an_occluder() -> None:
    front = box("F", X0, Y0 - 15.0, 10, 4, 10)  # between the camera and B's south wall
    back = box("B", X0, Y0, 10, 8, 6)
    caster = RayCaster(build_scene_mesh([front, back]))
    center = np.array([X0 + 5.0, Y0 - 30.0, Z0 + 2.0])
    on_wall = np.array([[X0 + 5.0, Y0, Z0 + 3.0], [X0 + 5.0, Y0, Z0 + 3.0]])
    assert not caster.visible(on_wall, center).any()
    center_side = np.array([X0 + 30.0, Y0 - 30.0, Z0 + 2.0])
    visible_pts = np.array([[X0 + 9.9, Y0, Z0 + 1.0]])
    # from the side, the point on B's south wall is seen past F's east edge
    assert caster.visible(visible_pts, center_side).all()
    # a point on the surface does not occlude itself; a point behind the wall is hidden
    assert caster.visible(np.array([[X0 + 5.0, Y0 - 15.0, Z0 + 3.0]]), center).all()
    assert not caster.visible(np.array([[X0 + 5.0, Y0 - 14.0, Z0 + 3.0]]), center).any()

"""Geometry checks on synthetic polygons and buildings with known defects."""

from __future__ import annotations

import numpy as np
import pytest

from db.citygml.checks import CheckOptions, check_building, check_polygon
from tests.conftest import DATA
from workers.pipeline.geometry.citymodel import Building, Polygon, Ring


def _poly(
    pid: str, pts: list, cls: str = "WallSurface", closed: bool = True, in_solid: bool = False
) -> Polygon:
    c = np.asarray(pts, float)
    if closed:
        c = np.vstack([c, c[:1]])
    return Polygon(id=pid, exterior=Ring(f"{pid}_r", c), surface_class=cls, in_solid=in_solid)


def _prism(footprint: list, height: float, flip: set[int] = frozenset(), in_solid: bool = True) -> Building:
    """Extruded footprint (counter-clockwise seen from above): walls, roof, ground, outward normals."""
    f = np.asarray(footprint, float)
    n = len(f)
    polys = []
    for i in range(n):
        a, b = f[i], f[(i + 1) % n]
        quad = [[*a, 0], [*b, 0], [*b, height], [*a, height]]
        if i in flip:
            quad = quad[::-1]
        polys.append(_poly(f"w{i}", quad, in_solid=in_solid))
    polys.append(_poly("roof", [[*p, height] for p in f], "RoofSurface", in_solid=in_solid))
    polys.append(_poly("ground", [[*p, 0] for p in f[::-1]], "GroundSurface", in_solid=in_solid))
    return Building(id="B", polygons=tuple(polys))


L_SHAPE = [(0, 0), (10, 0), (10, 4), (4, 4), (4, 10), (0, 10)]


def test_clean_prism_passes() -> None:
    checks = check_building(_prism(L_SHAPE, 6.0))
    assert len(checks) == 8
    assert all(c.ok for c in checks), [c.problems for c in checks]
    walls = [c for c in checks if c.surface_class == "WallSurface"]
    assert all(c.normal_outward for c in walls)
    roof = next(c for c in checks if c.polygon_id == "roof")
    np.testing.assert_allclose(roof.normal, [0, 0, 1], atol=1e-12)
    assert roof.offset == pytest.approx(6.0)
    assert roof.area_m2 == pytest.approx(64.0)
    assert roof.normal_outward is None  # only walls are tested


@pytest.mark.parametrize("in_solid", [True, False])
def test_flipped_walls_reported(in_solid: bool) -> None:
    checks = check_building(_prism(L_SHAPE, 6.0, flip={1, 3}, in_solid=in_solid))
    inward = {c.polygon_id for c in checks if c.normal_outward is False}
    assert inward == {"w1", "w3"}
    assert all("wall_normal_inward" in c.problems for c in checks if c.polygon_id in inward)


def test_non_planar_deviation() -> None:
    d = 0.07
    p = _poly("np", [[0, 0, d], [1, 0, -d], [1, 1, d], [0, 1, -d]], "RoofSurface")
    c = check_polygon(p)
    assert c.planarity_m == pytest.approx(d, abs=1e-12)
    assert c.non_planar
    assert not check_polygon(p, options=CheckOptions(planarity_tolerance_m=0.1)).non_planar


def test_degenerate_polygons() -> None:
    few = check_polygon(_poly("few", [[0, 0, 0], [1, 0, 0]]))
    assert few.too_few_vertices and few.zero_area and few.normal is None
    line = check_polygon(_poly("line", [[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]))
    assert line.zero_area and not line.too_few_vertices
    bowtie = check_polygon(_poly("bow", [[0, 0, 0], [1, 1, 0], [1, 0, 0], [0, 1, 0]]))
    assert bowtie.self_intersecting and "self_intersecting" in bowtie.problems
    square = check_polygon(_poly("sq", [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]))
    assert square.ok and square.vertices == 4 and square.area_m2 == pytest.approx(1.0)
    unclosed = check_polygon(_poly("open", [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], closed=False))
    assert unclosed.unclosed_rings == ("open_r",) and "unclosed_ring" in unclosed.problems


def test_hole_area_and_self_intersecting_hole() -> None:
    outer = np.array([[0, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0], [0, 0, 0]], float)
    hole = np.array([[1, 1, 0], [1, 2, 0], [2, 2, 0], [2, 1, 0], [1, 1, 0]], float)
    p = Polygon("h", Ring("o", outer), (Ring("i", hole),))
    c = check_polygon(p)
    assert c.ok and c.area_m2 == pytest.approx(15.0)
    bad_hole = np.array([[1, 1, 0], [2, 2, 0], [2, 1, 0], [1, 2, 0], [1, 1, 0]], float)
    assert check_polygon(Polygon("h2", Ring("o", outer), (Ring("i", bad_hole),))).self_intersecting


def test_real_sample_walls_outward() -> None:
    """The Bavarian building (closed LoD2 shell): every wall normal points out."""
    from db.citygml import read_model

    _, (b,) = read_model(DATA / "bavaria-1-building-citygml2-lod2.gml")
    checks = check_building(b)
    walls = [c for c in checks if c.surface_class == "WallSurface"]
    assert len(walls) == 63 and all(c.normal_outward for c in walls)
    assert all(c.ok for c in checks)


def test_party_wall_modelled_twice_not_judged() -> None:
    """Two boxes side by side in one building: the shared wall appears once per box, facing
    opposite ways; neither copy can be judged, every other wall is outward (one flipped: found)."""
    a = _prism([(0, 0), (4, 0), (4, 4), (0, 4)], 5.0)
    b = _prism([(4, 0), (8, 0), (8, 4), (4, 4)], 5.0, flip={2})
    rename = [
        Polygon(f"b_{p.id}", p.exterior, surface_class=p.surface_class, in_solid=True) for p in b.polygons
    ]
    both = Building(id="AB", polygons=a.polygons + tuple(rename))
    result = {c.polygon_id: c.normal_outward for c in check_building(both)}
    assert result["w1"] is None and result["b_w3"] is None  # x = 4: the party wall, twice
    assert result["b_w2"] is False  # flipped outer wall
    assert all(v is True for k, v in result.items() if k.startswith(("w", "b_w")) and k not in
               ("w1", "b_w3", "b_w2"))  # fmt: skip

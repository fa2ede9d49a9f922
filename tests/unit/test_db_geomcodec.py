"""Geometry encoding for PostGIS: EWKB round trip (bit-exact), planes against `fit_plane`, open
rings closed and flagged, degenerate polygons without geometry, footprints valid."""

from __future__ import annotations

import numpy as np
import shapely

from db.geomcodec import (
    encode_envelope,
    encode_footprints,
    encode_polygons,
    polygon_rings_from_wkb,
)
from workers.pipeline.geometry.citymodel import Building, Polygon, Ring
from workers.pipeline.geometry.polygons import fit_plane


def _rect(rng: np.random.Generator, k: int, closed: bool = True, hole: bool = False) -> Polygon:
    """A random planar rectangle (with an optional hole) far from the origin (UTM-like)."""
    origin = np.array([691000.0, 5334000.0, 500.0]) + rng.uniform(-1000, 1000, 3)
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    v = np.cross(u, rng.normal(size=3))
    v /= np.linalg.norm(v)
    w, h = rng.uniform(2, 30, 2)
    ext = np.array([origin, origin + w * u, origin + w * u + h * v, origin + h * v, origin])
    interiors = ()
    if hole:
        c = origin + 0.5 * w * u + 0.5 * h * v
        ring = np.array([c, c + 0.2 * h * v, c + 0.2 * h * v + 0.2 * w * u, c + 0.2 * w * u, c])
        interiors = (Ring(f"r{k}_1", ring),)
    if not closed:
        ext = ext[:-1]
    return Polygon(f"p{k}", Ring(f"r{k}_0", ext), interiors)


def test_ewkb_round_trip_and_planes() -> None:
    rng = np.random.default_rng(7)
    polys = [_rect(rng, k, hole=k % 3 == 0) for k in range(40)]
    enc = encode_polygons(polys, 25832)
    for k, p in enumerate(polys):
        rings = polygon_rings_from_wkb(bytes.fromhex(enc.ewkb[k]))
        assert len(rings) == len(p.rings)
        for got, r in zip(rings, p.rings, strict=True):
            np.testing.assert_array_equal(got, r.coords)  # bit-exact
        g = shapely.from_wkb(enc.ewkb[k])
        assert shapely.get_srid(g) == 25832 and shapely.has_z(g)
        plane = fit_plane(p)
        np.testing.assert_allclose(enc.normal[k], plane.normal, atol=1e-9)
        # offsets of ~5e6 m: the two normals agree to ~1e-11, so compare relatively
        assert abs(enc.offset[k] - plane.offset) < 1e-10 * abs(plane.offset) + 1e-6
        assert abs(enc.area[k] - plane.area) < 1e-6 * plane.area
        assert enc.planarity[k] < 1e-6
        assert enc.min_vertices[k] == 4
        assert enc.ring_closed[k] == [True] * len(p.rings)


def test_open_ring_closed_and_flagged_degenerate_dropped() -> None:
    rng = np.random.default_rng(3)
    open_poly = _rect(rng, 0, closed=False)
    tiny = Polygon("tiny", Ring("t0", np.array([[0.0, 0, 0], [1, 0, 0], [0, 0, 0]])))
    bent = _rect(rng, 2)
    c = bent.exterior.coords.copy()
    c[2] += 0.3 * np.cross(c[1] - c[0], c[3] - c[0]) / np.linalg.norm(np.cross(c[1] - c[0], c[3] - c[0]))
    bent = Polygon("bent", Ring("b0", c))
    enc = encode_polygons([open_poly, tiny, bent], 0)
    assert enc.ring_closed[0] == [False]
    (ring,) = polygon_rings_from_wkb(bytes.fromhex(enc.ewkb[0]))
    np.testing.assert_array_equal(ring[:-1], open_poly.exterior.coords)
    np.testing.assert_array_equal(ring[-1], ring[0])
    assert enc.ewkb[1] is None and enc.min_vertices[1] == 2
    assert 0.05 < enc.planarity[2] < 0.3
    assert enc.planarity[0] < 1e-6


def test_footprint_union_of_ground_surfaces_is_valid() -> None:
    # two ground squares sharing an edge (a union must merge them) and a wall
    def sq(x0: float, pid: str) -> Polygon:
        pts = np.array([[x0, 0, 0], [x0, 10, 0], [x0 + 10, 10, 0], [x0 + 10, 0, 0], [x0, 0, 0]], float)
        return Polygon(pid, Ring(pid + "_r", pts), surface_class="GroundSurface")

    wall = Polygon(
        "w",
        Ring("w_r", np.array([[0, 0, 0], [20, 0, 0], [20, 0, 5], [0, 0, 5], [0, 0, 0]], float)),
        surface_class="WallSurface",
    )
    b = Building("B", (sq(0, "g1"), sq(10, "g2"), wall))
    enc = encode_polygons(list(b.iter_polygons()), 25833)
    normals = {p.id: enc.normal[k] for k, p in enumerate(b.iter_polygons())}
    (fp,) = encode_footprints([b], normals, 25833)
    g = shapely.from_wkb(fp)
    assert g.geom_type == "MultiPolygon" and g.is_valid and len(g.geoms) == 1
    assert abs(g.area - 200.0) < 1e-9 and shapely.get_srid(g) == 25833
    env = shapely.from_wkb(encode_envelope(*b.bounds(), 25833))
    assert shapely.get_coordinates(env, include_z=True)[2].tolist() == [20.0, 10.0, 5.0]

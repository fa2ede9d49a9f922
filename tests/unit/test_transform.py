"""Model coordinates from one CRS into another, checked against what geodesy says independently
of pyproj: UTM zones 32 and 33 are mirror images about 12° E, where both are 3° from their
central meridian; and round trips."""

from __future__ import annotations

import numpy as np
import pytest

from db.citygml.reader import read_model
from tests.conftest import sample
from workers.pipeline.geometry.transform import CrsTransform, CrsTransformError, transform_building


def test_the_zone_boundary_is_a_mirror_between_utm_32_and_33() -> None:
    """On the meridian 12° E, 3° west of zone 33's central meridian and 3° east of zone 32's, the
    transverse Mercator projection is symmetric: E32 + E33 = 1,000 km and N32 = N33."""
    geographic = np.column_stack([np.full(3, 12.0), [50.5, 52.0, 54.0], np.zeros(3)])  # lon, lat
    x33 = CrsTransform("EPSG:4258", "EPSG:25833").points(geographic)
    x32 = CrsTransform("EPSG:4258", "EPSG:25832").points(geographic)
    assert np.allclose(x33[:, 0] + x32[:, 0], 1_000_000.0, atol=1e-3)
    assert np.allclose(x33[:, 1], x32[:, 1], atol=1e-3)
    # the model transform maps a zone-33 point on that meridian onto its mirror, heights kept
    pts = np.column_stack([x33[:, 0], x33[:, 1], [34.5, 60.0, 112.25]])
    moved = CrsTransform("EPSG:25833", "EPSG:25832").points(pts)
    assert np.allclose(moved[:, 0], 1_000_000.0 - pts[:, 0], atol=1e-3)
    assert np.allclose(moved[:, 1], pts[:, 1], atol=1e-3)
    assert np.array_equal(moved[:, 2], pts[:, 2])


def test_a_round_trip_returns_to_the_millimetre() -> None:
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(380_000, 400_000, 50), rng.uniform(5_810_000, 5_830_000, 50),
                           rng.uniform(30, 80, 50)])
    there = CrsTransform("EPSG:25833", "EPSG:25832").points(pts)
    back = CrsTransform("EPSG:25832", "EPSG:25833").points(there)
    assert np.max(np.abs(back - pts)) < 1e-3
    assert np.min(np.linalg.norm(there[:, :2] - pts[:, :2], axis=1)) > 1_000  # it did move


def test_a_building_moves_whole_with_its_parts_and_keeps_its_ids() -> None:
    _, buildings = read_model(sample("berlin-61-buildings-citygml1-lod2.gml"))
    b = buildings[0]
    t = CrsTransform("EPSG:25833", "EPSG:25832")
    moved = transform_building(b, t)
    assert moved.srs_name == "EPSG:25832" and all(p.srs_name == "EPSG:25832" for p in moved.iter_buildings())
    assert [p.id for p in moved.iter_polygons()] == [p.id for p in b.iter_polygons()]
    for p, q in zip(b.iter_polygons(), moved.iter_polygons(), strict=True):
        for r, s in zip(p.rings, q.rings, strict=True):
            assert r.id == s.id and r.coords.shape == s.coords.shape
            assert np.allclose(s.coords, t.points(r.coords))
            assert np.array_equal(s.coords[:, 2], r.coords[:, 2])
    # distances between vertices are kept to the UTM scale difference (< 0.1 %)
    p, q = next(iter(b.iter_polygons())), next(iter(moved.iter_polygons()))
    d0 = np.linalg.norm(np.diff(p.exterior.coords[:, :2], axis=0), axis=1)
    d1 = np.linalg.norm(np.diff(q.exterior.coords[:, :2], axis=0), axis=1)
    assert np.allclose(d1, d0, rtol=1e-3)


def test_a_change_of_height_system_is_refused_naming_both() -> None:
    with pytest.raises(CrsTransformError, match=r"5783.*7837"):
        CrsTransform("urn:ogc:def:crs,crs:EPSG:6.12:25833,crs:EPSG:6.12:5783",
                     "urn:ogc:def:crs,crs:EPSG:6.12:25832,crs:EPSG:6.12:7837")


def test_the_same_horizontal_crs_is_the_identity() -> None:
    t = CrsTransform("EPSG:25833", "urn:ogc:def:crs,crs:EPSG:6.12:25833,crs:EPSG:6.12:5783")
    pts = np.array([[390_000.0, 5_820_000.0, 40.0]])
    assert t.identity and np.array_equal(t.points(pts), pts)

"""Ground-truth thermal field: determinism, features where the options put them, anomalies."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from workers.pipeline.geometry.polygons import fit_plane, open_ring, surface_axes
from workers.pipeline.synth import SynthError, ThermalOptions, ThermalScene, gable_house, procedural_block
from workers.pipeline.synth.thermal import ROOF, WALL


def polygon_points(poly, n: int, rng: np.random.Generator) -> np.ndarray:
    """`n` random points on a polygon's plane inside its bounding box in (s, t) (may fall outside
    a non-rectangular polygon: fine for evaluating the field)."""
    plane = fit_plane(poly)
    s, t = surface_axes(plane.normal, open_ring(poly.exterior.coords))
    st = (open_ring(poly.exterior.coords) - plane.centroid) @ np.stack([s, t], axis=1)
    a = rng.uniform(st[:, 0].min(), st[:, 0].max(), n)
    b = rng.uniform(st[:, 1].min(), st[:, 1].max(), n)
    return plane.centroid + a[:, None] * s + b[:, None] * t


@pytest.fixture(scope="module")
def block():
    return procedural_block(8, seed=11)


def test_deterministic_and_subset_independent(block):
    full = ThermalScene(block, seed=5)
    again = ThermalScene(block, seed=5)
    sub = ThermalScene(block[2:5], seed=5)
    other = ThermalScene(block, seed=6)
    rng = np.random.default_rng(0)
    poly = block[3].polygons[1]
    X = polygon_points(poly, 500, rng)
    T = full.surface_temperature(poly.id, X)
    assert np.array_equal(T, again.surface_temperature(poly.id, X))
    assert np.allclose(T, sub.surface_temperature(poly.id, X), atol=1e-3)  # float32 local frames
    assert not np.allclose(T, other.surface_temperature(poly.id, X), atol=0.1)
    idx = full.polygon_index(poly.id)
    assert np.array_equal(T, full.surface_temperature(idx, X))
    kept = [a.id for a in full.anomalies if a.building_id in sub.building_ids]
    assert [a.id for a in sub.anomalies] == kept


def test_walls_warmer_than_roofs(block):
    th = ThermalScene(block, seed=1)
    rng = np.random.default_rng(1)
    walls, roofs = [], []
    for b in block:
        for poly in b.polygons:
            k = th.polygon_index(poly.id)
            T = th.surface_temperature(k, polygon_points(poly, 200, rng)).mean()
            (walls if th.p_class[k] == WALL else roofs if th.p_class[k] == ROOF else []).append(T)
    assert np.mean(walls) - np.mean(roofs) > 3.0


def test_windows_colder_frames_warmer_slabs_warmer():
    o = ThermalOptions(
        texture_amplitude_k=0.0, leaks_per_building=0.0, corner_delta_k=0.0, pipe_probability=0.0
    )
    house = gable_house("h", 20.0, 10.0, 9.5, 13.0, np.zeros(3), storeys=3)
    th = ThermalScene([house], seed=3, options=o)
    wall = next(p for p in house.polygons if p.id == "h-wall-s")  # along x, normal -y
    k = th.polygon_index(wall.id)
    base = th.p_base[k]
    storey, pitch = th.b_storey[0], th.b_spacing[0]
    assert th.p_win_rows[k] >= 2 and th.p_win_cols[k] >= 4
    # window centres of the first column, each storey: s along the wall (here +x from the centroid)
    s_axis = th.p_s[k]
    s0 = th.p_win_s0[k] + 0.5 * pitch
    centroid = th.p_origin[k]
    for r in range(th.p_win_rows[k]):
        h = r * storey + o.window_sill_m + 0.5 * o.window_height_m
        X = centroid + s0 * s_axis
        X = np.array([X[0], X[1], h])
        T_pane = th.surface_temperature(k, X[None])[0]
        assert T_pane < base - 2.0
        X_frame = X + (0.5 * o.window_width_m - 0.5 * o.frame_width_m) * s_axis
        assert th.surface_temperature(k, X_frame[None])[0] > base + 0.9 * o.frame_delta_k
        # between windows at the same height: the wall itself
        X_wall = X + 0.5 * pitch * s_axis
        assert abs(th.surface_temperature(k, X_wall[None])[0] - base) < 0.05
    # floor slab line of the second storey: warmer than half a storey above it
    X_slab = np.array([*(centroid + (s0 + 0.5 * pitch) * s_axis)[:2], storey])
    X_mid = X_slab + np.array([0, 0, 0.45 * storey - o.window_sill_m])
    assert th.surface_temperature(k, X_slab[None])[0] - th.surface_temperature(k, X_mid[None])[0] > 0.7


def test_corners_warmer():
    o = ThermalOptions(texture_amplitude_k=0.0, leaks_per_building=0.0, pipe_probability=0.0)
    house = gable_house("h", 20.0, 10.0, 9.5, 13.0, np.zeros(3), storeys=3)
    th = ThermalScene([house], seed=3, options=o)
    k = th.polygon_index("h-wall-s")
    assert th.p_corner[k].all()  # both vertical edges of the south wall are building corners
    between = th.p_origin[k] + (th.p_win_s0[k] + th.b_spacing[0]) * th.p_s[k]  # between two windows
    middle = np.array([[between[0], between[1], 2.0]])
    corner = np.array([[0.05, 0.0, 2.0]])  # 5 cm from the south-west corner
    diff = th.surface_temperature(k, corner)[0] - th.surface_temperature(k, middle)[0]
    expect = o.corner_delta_k * np.exp(-0.5 * (0.05 / o.corner_width_m) ** 2)
    assert abs(diff - expect) < 0.05


def test_anomalies_are_where_recorded(block):
    o = ThermalOptions(leaks_per_building=2.0)
    th = ThermalScene(block, seed=8, options=o)
    clean = ThermalScene(block, seed=8, options=replace(o, leaks_per_building=0.0))
    assert len(th.anomalies) >= 8
    for a in th.anomalies:
        assert 2.0 <= a.peak_k <= 5.0 and a.sigma_m > 0
        k = th.polygon_index(a.polygon_id)
        assert th.polygon_building[k] == a.building_id
        plane = fit_plane(next(p for b in block for p in b.iter_polygons() if p.id == a.polygon_id))
        assert abs(plane.normal @ a.center - plane.offset) < 1e-6  # on the polygon's plane
        at = th.surface_temperature(k, a.center[None])[0] - clean.surface_temperature(k, a.center[None])[0]
        assert abs(at - a.peak_k) < 0.01
        # at 2σ the excess has fallen to peak / e²
        s = th.p_s[k]
        at2 = th.surface_temperature(k, (a.center + 2 * a.sigma_m * s)[None])[0]
        at2 -= clean.surface_temperature(k, (a.center + 2 * a.sigma_m * s)[None])[0]
        assert abs(at2 - a.peak_k * np.exp(-2.0)) < 0.01


def test_ground_and_sky():
    th = ThermalScene(procedural_block(2, seed=1), seed=2)
    g = th.ground_temperature(np.array([[691000.0, 5334000.0, 0.0], [691003.0, 5334001.0, 0.0]]))
    assert np.all(np.abs(g - th.options.ground_k) < 2 * th.options.ground_amplitude_k)
    sky = th.sky_temperature(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]))
    assert np.allclose(sky, [th.options.sky_zenith_k, th.options.sky_horizon_k])


def test_bad_input_names_the_problem(block):
    th = ThermalScene(block, seed=1)
    with pytest.raises(SynthError, match="polygon id"):
        th.surface_temperature("nope", np.zeros((1, 3)))
    with pytest.raises(SynthError, match="polygon_ids"):
        ThermalScene(block[:1], polygon_ids=["missing"])
    with pytest.raises(SynthError, match="out of range"):
        th.temperature(np.zeros((1, 3)), np.array([10**6]))

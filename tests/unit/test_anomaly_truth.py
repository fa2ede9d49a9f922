"""Truth of the synthetic anomalies: leak half-maximum outlines, the window rectangles of every
wall, their place in the truth file, and a field left exactly as it was."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import shapely

from workers.pipeline.synth import (
    ErrorOptions,
    SynthOptions,
    SynthTruth,
    ThermalOptions,
    ThermalScene,
    gable_house,
    procedural_block,
    synthesize,
)
from workers.pipeline.synth.anomaly import HALF_MAX_SIGMAS, Anomaly, Window, plane_frame
from workers.pipeline.synth.thermal import WALL


@pytest.fixture(scope="module")
def block():
    return procedural_block(8, seed=11)


def polygons(buildings) -> dict:
    return {p.id: p for b in buildings for p in b.iter_polygons()}


def test_field_unchanged_by_the_truth(block):
    """Temperatures computed with the field before its truth was exposed (float32 K, seed 5,
    3 leaks per building; the last three at leak centres): the field must stay the same."""
    th = ThermalScene(block, seed=5, options=ThermalOptions(leaks_per_building=3))
    rng = np.random.default_rng(0)
    poly = block[2].polygons[0]
    frame = plane_frame(poly)
    x0, y0, x1, y1 = frame.shape.bounds
    X = frame.to_world(np.stack([rng.uniform(x0, x1, 6), rng.uniform(y0, y1, 6)], axis=1))
    X = np.vstack([X, *(a.center[None] for a in th.anomalies[:3])])
    P = [th.polygon_index(poly.id)] * 6 + [th.polygon_index(a.polygon_id) for a in th.anomalies[:3]]
    T = th.temperature(X, np.array(P))
    expect = [
        273.9718, 273.6376, 273.9996, 274.1382, 273.7101, 274.0709, 278.9244, 278.1913, 279.4482
    ]  # fmt: skip
    assert np.allclose(T, expect, atol=2e-3)


def test_leak_outline_is_the_half_maximum_contour(block):
    o = ThermalOptions(leaks_per_building=3.0)
    th = ThermalScene(block, seed=8, options=o)
    clean = ThermalScene(block, seed=8, options=replace(o, leaks_per_building=0.0))
    polys = polygons(block)
    assert len(th.anomalies) >= 15
    clipped = 0
    for a in th.anomalies:
        ring = a.outline
        assert ring.shape[1] == 3 and len(ring) >= 4 and np.array_equal(ring[0], ring[-1])
        frame = plane_frame(polys[a.polygon_id])
        n = np.cross(frame.s_axis, frame.t_axis)
        assert np.abs((ring - frame.origin) @ n).max() < 1e-6  # on the polygon's plane
        st = frame.to_plane(ring)
        assert shapely.Polygon(st).exterior.is_ccw  # wound like the polygon
        assert abs(shapely.Polygon(st).area - a.area_m2) < 1e-9
        assert frame.shape.buffer(1e-6).contains(shapely.Polygon(st))  # clipped to the polygon
        r = np.linalg.norm(ring - a.center, axis=1)
        disc = np.abs(r - a.half_max_radius_m) < 1e-6  # vertices on the circle (not the clip)
        assert disc.sum() >= 0.5 * len(ring)
        k = th.polygon_index(a.polygon_id)
        excess = th.surface_temperature(k, ring[disc]) - clean.surface_temperature(k, ring[disc])
        assert np.allclose(excess, 0.5 * a.peak_k, atol=0.01)  # half the maximum on the contour
        full = np.pi * a.half_max_radius_m**2
        assert a.area_m2 <= full * 1.0001
        clipped += a.area_m2 < 0.99 * full
        assert a.delta_k == a.peak_k
        assert a.half_max_radius_m == pytest.approx(a.sigma_m * np.sqrt(2 * np.log(2)))
    assert abs(HALF_MAX_SIGMAS - 1.17741) < 1e-5
    assert clipped < len(th.anomalies)  # most leaks sit well inside their polygon


def test_leak_outline_clipped_at_the_polygon_edge():
    house = gable_house("h", 12.0, 8.0, 6.0, 9.0, np.zeros(3))
    wall = next(p for p in house.polygons if p.id == "h-wall-s")
    leak = Anomaly("leak-h-0", "h", wall.id, "WallSurface", np.array([0.3, 0.0, 3.0]), 0.5, 3.0)
    out = leak.with_outline(wall)
    r = HALF_MAX_SIGMAS * 0.5
    # the disc reaches 0.289 m past the wall's end at x = 0: the segment beyond is cut off
    seg = r**2 * np.arccos(0.3 / r) - 0.3 * np.sqrt(r**2 - 0.3**2)
    assert out.area_m2 == pytest.approx(np.pi * r**2 - seg, rel=2e-3)
    assert out.outline[:, 0].min() >= -1e-9


def test_windows_are_where_the_field_has_them(block):
    """Window contribution (field minus the field without panes and frames) is non-zero
    exactly inside the truth rectangles; panes are colder than the wall around them (no leaks:
    a warm blob on a pane is a leak, not a window)."""
    o = ThermalOptions(leaks_per_building=0.0)
    th = ThermalScene(block, seed=4, options=o)
    bare = ThermalScene(block, seed=4, options=replace(o, window_delta_k=0.0, frame_delta_k=0.0))
    polys = polygons(block)
    wins = th.windows
    assert len(wins) >= 40
    walls = {pid for k, pid in enumerate(th.polygon_ids) if th.p_class[k] == WALL}
    assert {w.polygon_id for w in wins} <= walls
    rng = np.random.default_rng(2)
    by_wall: dict[str, list[Window]] = {}
    for w in wins:
        by_wall.setdefault(w.polygon_id, []).append(w)
        assert np.array_equal(w.outline[0], w.outline[-1]) and len(w.outline) == 5
        assert w.width_m == pytest.approx(o.window_width_m) and w.height_m >= o.window_height_m - 1e-9
        assert np.allclose(w.center, w.outline[:4].mean(axis=0)) and w.delta_k == o.window_delta_k
    checked = 0
    for pid, ws in by_wall.items():
        frame = plane_frame(polys[pid])
        rects = [shapely.Polygon(frame.to_plane(w.outline)) for w in ws]
        assert all(r.exterior.is_ccw for r in rects)
        union = shapely.union_all(rects)
        x0, y0, x1, y1 = frame.shape.bounds
        st = np.stack([rng.uniform(x0, x1, 4000), rng.uniform(y0, y1, 4000)], axis=1)
        X = frame.to_world(st)
        d = th.surface_temperature(pid, X) - bare.surface_temperature(pid, X)
        inside = shapely.contains_xy(union, st[:, 0], st[:, 1])
        edge = shapely.distance(union.boundary, shapely.points(st)) < 1e-3
        assert np.array_equal((d != 0)[~edge], inside[~edge])
        for w, rect in zip(ws, rects, strict=True):  # pane (inset by the frame) vs. a ring outside
            pane = rect.buffer(-(o.frame_width_m + 0.02))
            ring = rect.buffer(0.4).difference(rect.buffer(0.1)).intersection(frame.shape)
            ins = _sample(pane, 200, rng)
            out = _sample(ring, 200, rng)
            if len(out) < 50:
                continue
            T_in = th.surface_temperature(pid, frame.to_world(ins)).mean()
            T_out = th.surface_temperature(pid, frame.to_world(out)).mean()
            assert T_in < T_out - 1.5, w.id
            checked += 1
    assert checked >= 30


def _sample(geom: shapely.Geometry, n: int, rng: np.random.Generator) -> np.ndarray:
    """Up to `n` random points `(M, 2)` inside `geom`."""
    x0, y0, x1, y1 = geom.bounds
    p = np.stack([rng.uniform(x0, x1, 4 * n), rng.uniform(y0, y1, 4 * n)], axis=1)
    return p[shapely.contains_xy(geom, p[:, 0], p[:, 1])][:n]


def test_no_windows_without_features(block):
    th = ThermalScene(block, seed=4, options=ThermalOptions(features=False))
    assert th.windows == () and th.anomalies == ()


def test_truth_file_holds_outlines_and_windows():
    res = synthesize(
        procedural_block(6, seed=1),
        SynthOptions(n_frames=3, seed=1, buildings=3, errors=ErrorOptions(enabled=False),
                     thermal=ThermalOptions(leaks_per_building=2)),
    )  # fmt: skip
    truth = res.truth
    assert truth.windows == res.thermal.windows and len(truth.windows) > 20
    assert truth.anomalies and all(a.outline is not None for a in truth.anomalies)
    d = json.loads(json.dumps(truth.to_dict()))
    assert d["format"] == "citytherm-synth-truth/1"
    assert {"outline", "area_m2", "delta_k", "half_max_radius_m"} <= set(d["anomalies"][0])
    back = SynthTruth.from_dict(d)
    for a, b in zip(truth.anomalies, back.anomalies, strict=True):
        assert np.allclose(a.outline, b.outline) and a.area_m2 == b.area_m2 and a.peak_k == b.peak_k
    for a, b in zip(truth.windows, back.windows, strict=True):
        assert a.id == b.id and np.allclose(a.outline, b.outline, atol=1e-6)
        assert np.allclose(a.center, b.center, atol=1e-6) and a.height_m == b.height_m
    # a truth file written before outlines and windows existed still loads
    old = json.loads(json.dumps(d))
    del old["windows"]
    for a in old["anomalies"]:
        for key in ("outline", "area_m2", "delta_k", "half_max_radius_m"):
            del a[key]
    back = SynthTruth.from_dict(old)
    assert back.windows == () and all(a.outline is None and np.isnan(a.area_m2) for a in back.anomalies)
    polys = polygons(res.buildings)
    for a, b in zip(truth.anomalies, back.anomalies, strict=True):
        again = b.with_outline(polys[b.polygon_id])
        assert np.allclose(again.outline, a.outline) and again.area_m2 == pytest.approx(a.area_m2)

"""Occluders the model lacks (`workers.pipeline.synth.occluders`): placement outside the
buildings on the facades' side of a drive, rendering in front of the model, the truth file."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from db.synth_files import load_truth, save_truth
from workers.pipeline.synth import (
    OCCLUDER,
    OccluderOptions,
    SynthOptions,
    default_camera,
    place_occluders,
    procedural_block,
    synthesize,
)
from workers.pipeline.synth.occluders import CAR_HOOD, TREE_CROWN


def _street() -> tuple[np.ndarray, list[shapely.Geometry]]:
    """A straight 200 m street along x with a 10 m deep row of houses 11 m to its left (+y)."""
    path = np.array([[0.0, 0.0], [200.0, 0.0]])
    houses = [shapely.box(x, 11.0, x + 15.0, 21.0) for x in range(0, 200, 20)]
    return path, houses


def test_placement_on_the_building_side_outside_footprints() -> None:
    path, houses = _street()
    o = OccluderOptions(trees_per_100m=4.0, cars_per_100m=6.0)
    occ = place_occluders(path, houses, 50.0, o, seed=3)
    kinds = [it["kind"] for it in occ.items]
    assert 4 <= kinds.count("tree") <= 12 and 6 <= kinds.count("car") <= 18, kinds
    blocked = shapely.union_all(houses)
    for it in occ.items:
        x, y, _ = it["center"]
        assert y > 0, it  # the side of the houses
        r = it["size"][0] if it["kind"] == "tree" else 0.9  # crown radius, half a car's width
        assert shapely.Point(x, y).distance(blocked) >= r + o.clearance_m - 1e-6, it
    # every triangle's vertices: trees up to their crowns' tops, cars on the ground, none inside a house
    v = occ.vertices[occ.triangles.ravel()]
    assert v[:, 2].min() == pytest.approx(50.0) and v[:, 2].max() < 50.0 + 8.0 + 0.8 * 2.8 + 1e-6
    inside = shapely.contains_xy(blocked, v[:, 0], v[:, 1])
    assert not inside.any()
    # temperatures per triangle follow the options: leaves scattered around tree_k, hoods warm
    crown = occ.temperature[occ.kind == TREE_CROWN]
    assert abs(float(np.mean(crown)) - o.tree_k) < 0.3 and 0.5 < float(np.std(crown)) < 1.1
    assert np.all(occ.temperature[occ.kind == CAR_HOOD] == np.float32(o.car_hood_k))
    # deterministic
    again = place_occluders(path, houses, 50.0, o, seed=3)
    assert np.array_equal(again.vertices, occ.vertices) and again.items == occ.items


def test_flight_trees_scatter_outside_footprints() -> None:
    path, houses = _street()
    occ = place_occluders(path, houses, 0.0, OccluderOptions(trees_per_hectare=20.0), seed=1, drive=False)
    assert occ.items and all(it["kind"] == "tree" for it in occ.items)
    blocked = shapely.union_all(houses)
    assert all(shapely.Point(*it["center"][:2]).distance(blocked) > 0.5 for it in occ.items)


def test_occluders_hide_the_model_in_the_frames(tmp_path) -> None:
    """Rendered with occluders, the pixels labelled OCCLUDER show the occluders' temperatures and
    the same pixels of the same pose without occluders see the model or the ground: the trees
    and cars stand in front of what the model holds; everything else is unchanged."""
    blds = procedural_block(6, seed=1)
    cam = default_camera(160, 128)
    kw = dict(platform="drive", n_frames=30, seed=1, buildings=3, camera=cam)
    with_occ = synthesize(blds, SynthOptions(**kw, occluders=OccluderOptions(trees_per_100m=8.0)))
    without = synthesize(blds, SynthOptions(**kw))
    assert with_occ.truth.occluders and not without.truth.occluders
    seen = 0
    for i in range(0, 30, 3):
        pose = with_occ.truth.poses[i]
        lab, depth = with_occ.renderer.labels(pose)
        lab0, depth0 = without.renderer.labels(pose)
        occ = lab == OCCLUDER
        seen += int(occ.sum())
        assert np.all(depth[occ] < depth0[occ])  # in front of the model, the ground or the sky
        assert np.array_equal(lab[~occ], lab0[~occ])
        T = with_occ.renderer.radiance(pose)
        T0 = without.renderer.radiance(pose)
        inner = occ & np.roll(occ, 1, 0) & np.roll(occ, -1, 0) & np.roll(occ, 1, 1) & np.roll(occ, -1, 1)
        if inner.any():  # away from the outlines: the occluders' own temperatures
            assert np.all((T[inner] > 268.0) & (T[inner] < 284.0))
        far = ~occ
        for ax in (0, 1):
            far &= ~np.roll(occ, 1, ax) & ~np.roll(occ, -1, ax)
        # elsewhere the same image; a few edge pixels whose sub-pixel rays meet a trunk thinner
        # than a pixel between the pixel centres may differ
        same = np.abs(T[far] - T0[far]) <= 1e-4
        assert np.count_nonzero(~same) <= 0.001 * same.size
    assert seen > 200  # the drive sees its trees
    p = tmp_path / "truth.json"
    save_truth(with_occ.truth, p)
    assert load_truth(p).occluders == with_occ.truth.occluders

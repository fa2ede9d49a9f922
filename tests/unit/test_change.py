"""Change between surveys, the pure part (`workers.pipeline.change`): two textures of one polygon
with a known ΔT, packed by the real atlas at different resolutions, give back that ΔT where both
observed and nothing where one is missing."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest

from tests.unit.texture_scene import box_building
from workers.pipeline.change import (
    DELTA_RADIOMETRY,
    ChangeError,
    ChangeOptions,
    SurfaceTexture,
    kelvin,
    normalised_delta,
    sample_tile,
    surface_change,
)
from workers.pipeline.geometry.citymodel import ParameterizedTexture, Polygon
from workers.pipeline.geometry.manifest import Radiometry
from workers.pipeline.texture.atlas import build_atlas
from workers.pipeline.texture.texel import TexelGrid, TexelOptions, texel_grid

DELTA_K = 1.7
WALL = box_building("B", 0, 0, 12, 8, 7, holes=True).polygons[0]  # 12 m x 7 m with two holes


def truth(points: np.ndarray) -> np.ndarray:
    """Survey A's temperature field, kelvin: smooth in x (along the wall) and z (up)."""
    return 275.0 + 0.05 * points[:, 0] + 0.15 * np.sin(points[:, 2])


def textured(
    poly: Polygon,
    res: float,
    offset: float,
    keep: Callable[[np.ndarray], np.ndarray],
    radiometry: Radiometry,
    name: str,
) -> tuple[SurfaceTexture, TexelGrid]:
    """The polygon textured at `res` texels/m with `truth + offset` where `keep(points)` holds,
    packed by `build_atlas` beside another surface (so the rectangle is not at the tile origin)."""
    grid = texel_grid(poly, "B", TexelOptions(resolution_px_per_m=res))
    rows, cols = grid.masked_indices()
    pts = grid.centres(rows, cols)
    value = np.full(grid.shape, np.nan, np.float32)
    kept = keep(pts)
    value[rows[kept], cols[kept]] = truth(pts[kept]) + offset - (273.15 if radiometry.unit == "degC" else 0.0)
    roof = box_building("B", 0, 0, 12, 8, 7).polygons[4]
    rgrid = texel_grid(roof, "B", TexelOptions(resolution_px_per_m=res))
    tiles, app = build_atlas(
        name, [roof, poly], [rgrid, grid], [np.full(rgrid.shape, 270.0, np.float32), value], radiometry, "t"
    )
    (target,) = [t for sd in app.surface_data if isinstance(sd, ParameterizedTexture) for t in sd.targets
                 if t.polygon_id == poly.id]  # fmt: skip
    uri = next(sd.image_uri for sd in app.surface_data if any(t is target for t in sd.targets))
    dn = next(t.dn for t in tiles if t.name == uri)
    return SurfaceTexture(dn, target.ring_coords[poly.exterior.id], radiometry, res), grid


def test_known_delta_is_recovered_where_both_observed_at_different_resolutions() -> None:
    rad = Radiometry("K", 0.01, 0.0)
    # A at 10 texels/m without its left 3 m; B at 4 texels/m (degC) without its top 2 m
    a, _ = textured(WALL, 10.0, 0.0, lambda p: p[:, 0] > 3.0, rad, "A")
    b, _ = textured(WALL, 4.0, DELTA_K, lambda p: p[:, 2] < 5.0, Radiometry("degC", 0.01, -100.0), "B")
    ch = surface_change(WALL, "B", a, b)
    assert ch is not None
    assert ch.grid.size == pytest.approx(0.1)  # the finer of the two
    rows, cols = ch.grid.masked_indices()
    pts = ch.grid.centres(rows, cols)
    d = ch.delta[rows, cols]
    both = np.isfinite(d)
    err = np.abs(d[both] - DELTA_K)
    assert err.max() < 0.05, err.max()
    assert np.abs(ch.value_a[rows, cols][both] - truth(pts[both])).max() < 0.05
    # nothing where one survey is missing (half a coarse texel of margin at the borders)
    assert not both[pts[:, 0] < 3.0 - 0.05].any()
    assert not both[pts[:, 2] > 5.0 + 0.125].any()
    inner = (pts[:, 0] > 3.2) & (pts[:, 2] < 4.8)
    assert both[inner].mean() > 0.98  # and nearly everything where both are
    assert np.isnan(ch.delta[~ch.grid.mask]).all()
    fig = ch.figures()
    assert fig["delta_median_k"] == pytest.approx(DELTA_K, abs=0.02)
    assert fig["delta_p05_k"] <= fig["delta_median_k"] <= fig["delta_p95_k"]
    assert 0.4 < fig["observed_both_share"] < 0.6
    # the ΔT encodes in the change tiles' radiometry to the millikelvin
    back = DELTA_RADIOMETRY.physical(DELTA_RADIOMETRY.dn(d[both]))
    assert np.abs(back - d[both]).max() < 0.001


def test_nearest_sampling_and_unobserved_neighbours() -> None:
    dn = np.array([[0, 100, 200], [0, 300, 400]], np.uint16)
    rad = Radiometry("K", 1.0, 0.0)
    uv = np.array([[1.5, 0.5], [0.6, 0.0], [0.4, 0.0], [2.0, 1.0], [5.0, 0.0]])
    v = sample_tile(dn, uv, rad)
    assert v[0] == pytest.approx(250.0)  # four observed neighbours: bilinear
    assert v[1] == 100.0  # a neighbour unobserved: the nearest, observed
    assert np.isnan(v[2])  # the nearest unobserved: nothing
    assert v[3] == 400.0 and np.isnan(v[4])
    assert sample_tile(dn, uv[:1], rad, "nearest")[0] in (100.0, 200.0, 300.0, 400.0)


def test_same_resolution_is_exact_and_foreign_coordinates_are_refused() -> None:
    rad = Radiometry("K", 0.001, 250.0)
    a, _ = textured(WALL, 5.0, 0.0, lambda p: np.ones(len(p), bool), rad, "A")
    b, _ = textured(WALL, 5.0, -0.4, lambda p: np.ones(len(p), bool), rad, "B")
    ch = surface_change(WALL, "B", a, b, ChangeOptions(sampling="nearest"))
    d = ch.delta[np.isfinite(ch.delta)]
    assert ch.observed_both_share > 0.99 and np.abs(d + 0.4).max() < 0.0015
    other = box_building("B", 0, 0, 15, 8, 7, holes=True).polygons[0]  # a wider wall: another model
    with pytest.raises(ChangeError, match=r"polygon B_w0: job A.s texture coordinates stretch"):
        surface_change(other, "B", a, b)
    ring = WALL.exterior.coords.copy()
    ring[2, 2] += 1.0  # one corner 1 m higher: no affine image of the textured wall
    moved = Polygon(WALL.id, replace(WALL.exterior, coords=ring), WALL.interiors, "WallSurface")
    with pytest.raises(ChangeError, match=r"polygon B_w0: job A's texture coordinates are .* px off"):
        surface_change(moved, "B", a, b)
    with pytest.raises(ChangeError, match="counts"):
        kelvin(1.0, "counts")


def test_normalisation_by_air_temperature() -> None:
    assert normalised_delta(276.0, 278.0, 268.15, 270.15) == pytest.approx(0.0)
    assert normalised_delta(276.0, 278.0, None, 270.15) is None
    assert normalised_delta(float("nan"), 278.0, 268.15, 270.15) is None

"""Texel grids: size, centres on the plane, raster convention, holes, roofs."""

from __future__ import annotations

import numpy as np
import pytest

from tests.unit.texture_scene import box_building
from workers.pipeline.geometry.polygons import fit_plane
from workers.pipeline.texture.texel import TexelError, TexelOptions, texel_grid


def test_wall_grid_size_centres_and_raster_convention():
    b = box_building("B", 0, 0, 10, 8, 6, holes=True)
    wall = b.polygons[0]  # south wall y = 0, two 1.5 x 1.5 m holes
    g = texel_grid(wall, "B", TexelOptions(resolution_px_per_m=10))
    assert g is not None
    assert g.shape == (60, 100)
    assert g.size == pytest.approx(0.1)
    # texels inside: wall area minus the holes, within one texel row along the boundaries
    plane = fit_plane(wall)
    assert plane.area == pytest.approx(60 - 2 * 2.25)
    assert abs(g.n_texels * g.size**2 - plane.area) < 0.5
    rows, cols = g.masked_indices()
    pts = g.centres(rows, cols)
    assert np.max(np.abs(pts @ plane.normal - plane.offset)) < 1e-9
    # s along the wall (x), t up: row 0 is the top
    assert np.allclose(g.s_axis, [1, 0, 0]) and np.allclose(g.t_axis, [0, 0, 1])
    top = g.centres(np.array([0]), np.array([0]))[0]
    assert top == pytest.approx([0.05, 0.0, 5.95])
    xy = g.raster_xy(pts)
    assert np.allclose(xy, np.stack([cols + 0.5, rows + 0.5], axis=1))
    # the holes are not inside: centre of the first hole (x = 2.75, z = 1.75)
    hx, hz = 2.75, 1.75
    i, j = int((6 - hz) / 0.1), int(hx / 0.1)
    assert not g.mask[i, j]
    assert g.mask[int((6 - 4.0) / 0.1), j]


def test_roof_axes_follow_the_longest_edge_and_points_round_trip():
    b = box_building("B", 0, 0, 4, 12, 6)
    roof = b.polygons[4]
    g = texel_grid(roof, "B", TexelOptions(resolution_px_per_m=5))
    assert g is not None
    assert abs(abs(g.s_axis[1]) - 1) < 1e-9  # longest edge runs north-south
    assert g.normal == pytest.approx([0, 0, 1])
    assert g.n_texels == 20 * 60
    xy = np.array([[0.0, 0.0], [3.3, 7.25], [20.0, 60.0]])
    assert np.allclose(g.raster_xy(g.points_at(xy)), xy)


def test_large_surfaces_get_coarser_texels():
    b = box_building("B", 0, 0, 300, 10, 5)
    g = texel_grid(b.polygons[0], "B", TexelOptions(resolution_px_per_m=10, max_side=1000))
    assert g is not None and max(g.shape) <= 1000
    assert g.size == pytest.approx(0.3)


def test_bad_resolution_is_refused():
    with pytest.raises(TexelError, match="resolution_px_per_m"):
        TexelOptions(resolution_px_per_m=0)

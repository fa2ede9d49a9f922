"""Atlas: packing without overlap, gutters, tile size limit, texture coordinates, DN encoding."""

from __future__ import annotations

import numpy as np
import pytest

from tests.unit.texture_scene import box_building, field
from workers.pipeline.geometry.manifest import Radiometry
from workers.pipeline.texture.atlas import AtlasError, AtlasOptions, build_atlas, pack
from workers.pipeline.texture.texel import TexelOptions, texel_grid


def test_packing_never_overlaps_keeps_the_gutter_and_the_size_limit():
    rng = np.random.default_rng(2)
    shapes = [tuple(int(x) for x in rng.integers(1, 300, size=2)) for _ in range(120)]
    opts = AtlasOptions(max_size=1024, gutter=3)
    places, tiles = pack(shapes, opts)
    assert len(tiles) > 1
    for h, w in tiles:
        assert h <= 1024 and w <= 1024
    for t in range(len(tiles)):
        occ = np.zeros(tiles[t], np.int32)
        for (h, w), p in zip(shapes, places, strict=True):
            if p.tile != t:
                continue
            g = opts.gutter
            assert p.row - g >= 0 and p.col - g >= 0
            assert p.row + h + g <= tiles[t][0] and p.col + w + g <= tiles[t][1]
            occ[p.row - g : p.row + h + g, p.col - g : p.col + w + g] += 1
        assert occ.max() <= 1  # rectangles with their gutters are disjoint


def test_a_surface_larger_than_a_tile_is_refused():
    with pytest.raises(AtlasError, match="exceeds the tile size"):
        pack([(5000, 10)], AtlasOptions())


def test_texture_coordinates_map_every_vertex_to_its_texel_and_tiles_encode_the_radiometry():
    b = box_building("B", 0, 0, 10, 7, 6, holes=True)
    polys, grids, values = [], [], []
    for p in b.polygons[:5]:
        g = texel_grid(p, "B", TexelOptions(resolution_px_per_m=10))
        r, c = g.masked_indices()
        v = np.full(g.shape, np.nan, np.float32)
        v[r, c] = field(g.centres(r, c))
        polys.append(p)
        grids.append(g)
        values.append(v)
    values[3][:] = np.nan  # an unobserved wall: left out of the atlas
    values[0][0, 0] = 0.0  # an observed 0 K is written as DN 1, not "not observed"
    rad = Radiometry(unit="K", scale=0.01, offset=0.0)
    tiles, app = build_atlas("B", polys, grids, values, rad, "thermal-ir", AtlasOptions(gutter=2))
    assert app is not None and app.theme == "thermal-ir"
    (tex,) = app.surface_data
    (tile,) = tiles
    assert tex.image_uri == tile.name == "textures/B_0.png"
    assert tile.dn.dtype == np.uint16
    H, W = tile.dn.shape
    by_id = {t.polygon_id: t for t in tex.targets}
    assert set(by_id) == {p.id for k, p in enumerate(polys) if k != 3}
    for k, p in enumerate(polys):
        if k == 3:
            continue
        g = grids[k]
        for ring in p.rings:
            st = by_id[p.id].ring_coords[ring.id]
            assert st.shape == (len(ring.coords), 2)
            assert np.all((st >= 0) & (st <= 1))
            # back to tile raster coordinates, then to the texel holding the vertex
            X, Y = st[:, 0] * W, (1 - st[:, 1]) * H
            inward = g.raster_xy(ring.coords).mean(axis=0) - g.raster_xy(ring.coords)
            inward /= np.maximum(np.linalg.norm(inward, axis=1, keepdims=True), 1e-9)
            col = np.floor(X + 0.01 * inward[:, 0]).astype(int)
            row = np.floor(Y + 0.01 * inward[:, 1]).astype(int)
            # the texel's world centre is within one texel diagonal of the vertex
            x0 = np.round(X - g.raster_xy(ring.coords)[:, 0]).astype(int)
            y0 = np.round(Y - g.raster_xy(ring.coords)[:, 1]).astype(int)
            centres = g.centres(row - y0, col - x0)
            assert np.all(np.linalg.norm(centres - ring.coords, axis=1) <= g.size * np.sqrt(0.5) + 1e-9)
        # every observed texel sits in the tile where the coordinates put it, with its DN
        r, c = np.nonzero(np.isfinite(values[k]))
        st = by_id[p.id].ring_coords[p.exterior.id]
        xy0 = g.raster_xy(p.exterior.coords[:1])[0]
        col0 = round(float(st[0, 0] * W - xy0[0]))
        row0 = round(float((1 - st[0, 1]) * H - xy0[1]))
        assert np.array_equal(tile.dn[row0 + r, col0 + c], rad.dn(values[k][r, c]))
        assert tile.dn[row0 + r, col0 + c].min() >= 1
    assert tile.dn.min() == 0  # gutters and holes stay "not observed"
    assert (tile.dn == 1).sum() >= 1


def test_no_observation_gives_no_appearance():
    b = box_building("B", 0, 0, 4, 4, 3)
    g = texel_grid(b.polygons[0], "B", TexelOptions())
    tiles, app = build_atlas(
        "B", [b.polygons[0]], [g], [np.full(g.shape, np.nan, np.float32)], Radiometry(), "t"
    )
    assert tiles == () and app is None


def test_gutter_filling_copies_edge_values_outwards_and_keeps_the_texels():
    b = box_building("B", 0, 0, 4, 4, 3)
    g = texel_grid(b.polygons[0], "B", TexelOptions(resolution_px_per_m=10))
    v = np.full(g.shape, 280.0, np.float32)
    rad = Radiometry()
    plain, _ = build_atlas("B", [b.polygons[0]], [g], [v], rad, "t", AtlasOptions(gutter=2))
    filled, _ = build_atlas(
        "B", [b.polygons[0]], [g], [v], rad, "t", AtlasOptions(gutter=2, fill_gutter=True)
    )
    a, f = plain[0].dn, filled[0].dn
    assert a.shape == f.shape
    assert (a == 0).sum() > 0 and (f == 0).sum() == 0  # the 2-texel gutter is filled
    assert np.array_equal(a[a > 0], f[a > 0])

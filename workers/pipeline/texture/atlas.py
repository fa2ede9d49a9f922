"""Texture atlas: packing a building's surface textures into tiles, with texture coordinates.

In: per surface a `TexelGrid` and its fused float32 texture `(H, W)` (NaN = not observed), the
sequence's `Radiometry`. Out: uint16 atlas tiles (`value = DN · scale + offset`, DN 0 = not
observed) of at most `max_size × max_size`, each surface's rectangle surrounded by a gutter, and
per ring vertex CityGML texture coordinates `(s, t)`: `s` to the right, `t` upwards, `(0, 0)` the
lower-left corner of the image, the centre of texel `(i, j)` of a `W × H` tile at
`((j + 0.5) / W, 1 − (i + 0.5) / H)`.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.citymodel import Appearance, ParameterizedTexture, Polygon, TextureTarget
from workers.pipeline.geometry.manifest import Radiometry
from workers.pipeline.results import TextureTile
from workers.pipeline.texture.texel import TexelGrid


class AtlasError(ValueError):
    """A surface texture that cannot be packed (larger than a tile)."""


@dataclass(frozen=True)
class AtlasOptions:
    """Options of the atlas stage.

    Attributes:
        max_size: largest tile side, texels.
        gutter: empty texels kept around every surface rectangle (also to the tile border).
        fill_gutter: copy the nearest observed value into unobserved texels within `gutter` of
            observed ones outside the polygon's mask, so that viewers filtering bilinearly see no
            dark seam. Off by default: DN 0 then means exactly "no observation".
    """

    max_size: int = 4096
    gutter: int = 2
    fill_gutter: bool = False


@dataclass(frozen=True)
class Placement:
    """Where one surface rectangle sits: tile index, top-left texel `(row, col)` of its content."""

    tile: int
    row: int
    col: int


def safe_name(text: str) -> str:
    """A file-name and NCName-safe version of an id (letters, digits, `_`, `-`, `.`); ids that
    had to be changed get a short hash of the original, so that distinct ids stay distinct.

    >>> safe_name("BLDG_0815"), safe_name("DEB/LOD2:1")
    ('BLDG_0815', 'DEB_LOD2_1_75fe53')
    """
    out = re.sub(r"[^A-Za-z0-9_.-]", "_", text)
    out = out if out[:1].isalpha() or out[:1] == "_" else f"_{out}"
    if out != text:
        out = f"{out}_{hashlib.sha1(text.encode('utf-8')).hexdigest()[:6]}"
    return out


def pack(
    shapes: Sequence[tuple[int, int]], options: AtlasOptions
) -> tuple[list[Placement], list[tuple[int, int]]]:
    """Shelf-pack rectangles `shapes` `(h, w)` into tiles.

    Returns one `Placement` per rectangle (content origin, gutter excluded) and the tile shapes
    `(H, W)`. Every rectangle keeps `gutter` free texels on each side, so contents of two
    rectangles are at least `2 · gutter` apart and `gutter` away from the tile border.
    """
    g = options.gutter
    limit = options.max_size
    boxes = [(h + 2 * g, w + 2 * g) for h, w in shapes]
    for k, (bh, bw) in enumerate(boxes):
        if bh > limit or bw > limit:
            raise AtlasError(f"surface texture {shapes[k]} with gutter {g} exceeds the tile size {limit}")
    if not boxes:
        return [], []
    area = sum(bh * bw for bh, bw in boxes)
    width = min(limit, max(max(bw for _, bw in boxes), math.ceil(math.sqrt(area * 1.15))))
    order = sorted(range(len(boxes)), key=lambda k: (-boxes[k][0], -boxes[k][1], k))
    placements: list[Placement | None] = [None] * len(boxes)
    tiles: list[list[int]] = []  # per tile: [used_height, used_width]
    tile = -1
    shelf_y = shelf_h = cursor_x = 0
    for k in order:
        bh, bw = boxes[k]
        if tile < 0 or cursor_x + bw > width:  # new shelf
            shelf_y += shelf_h
            shelf_h, cursor_x = 0, 0
            if tile < 0 or shelf_y + bh > limit:  # new tile
                tiles.append([0, 0])
                tile += 1
                shelf_y = 0
        placements[k] = Placement(tile=tile, row=shelf_y + g, col=cursor_x + g)
        cursor_x += bw
        shelf_h = max(shelf_h, bh)
        tiles[tile][0] = max(tiles[tile][0], shelf_y + bh)
        tiles[tile][1] = max(tiles[tile][1], cursor_x)
    return [p for p in placements if p is not None], [(h, w) for h, w in tiles]


def texture_coordinates(
    grid: TexelGrid, ring: np.ndarray, placement: Placement, tile_shape: tuple[int, int]
) -> np.ndarray:
    """CityGML texture coordinates `(N, 2)` `(s, t)` of ring vertices `ring (N, 3)` (world, closing
    vertex included) for a surface placed at `placement` in a tile of `tile_shape (H, W)`."""
    xy = grid.raster_xy(ring)
    H, W = tile_shape
    s = (placement.col + xy[:, 0]) / W
    t = 1.0 - (placement.row + xy[:, 1]) / H
    return np.stack([s, t], axis=1)


def _fill_gutter(dn: np.ndarray, gutter: int) -> np.ndarray:
    """Grow observed DNs (> 0) into zero texels by up to `gutter` texels (grey dilation)."""
    import cv2

    out = dn.copy()
    kernel = np.ones((3, 3), np.uint8)
    for _ in range(gutter):
        grown = cv2.dilate(out, kernel)
        empty = out == 0
        out[empty] = grown[empty]
    return out


def build_atlas(
    building_id: str,
    polygons: Sequence[Polygon],
    grids: Sequence[TexelGrid],
    values: Sequence[np.ndarray],
    radiometry: Radiometry,
    theme: str,
    options: AtlasOptions = AtlasOptions(),
) -> tuple[tuple[TextureTile, ...], Appearance | None]:
    """Pack the observed surfaces of one building into tiles and describe them as an appearance.

    Args:
        building_id: top-level building id (names tiles `textures/<id>_<k>.png`).
        polygons, grids, values: per surface its polygon, texel grid and fused texture
            `(H, W)` float32 (NaN = not observed); surfaces with no observed texel are left out.
        radiometry: DN encoding of the tiles.
        theme: the appearance's theme.

    Returns the tiles and an `Appearance` with one `ParameterizedTexture` per tile (None when no
    surface was observed).
    """
    keep = [k for k, v in enumerate(values) if np.isfinite(v).any()]
    if not keep:
        return (), None
    placements, tile_shapes = pack([values[k].shape for k in keep], options)
    base = safe_name(building_id)
    tiles_dn = [np.zeros(shape, np.uint16) for shape in tile_shapes]
    targets: list[list[TextureTarget]] = [[] for _ in tile_shapes]
    for k, pl in zip(keep, placements, strict=True):
        v = values[k]
        h, w = v.shape
        dn = radiometry.dn(v)
        if options.fill_gutter and options.gutter > 0:
            g = options.gutter
            pad = np.zeros((h + 2 * g, w + 2 * g), np.uint16)
            pad[g:-g, g:-g] = dn
            pad = _fill_gutter(pad, g)
            pad[g:-g, g:-g][grids[k].mask] = dn[grids[k].mask]
            tiles_dn[pl.tile][pl.row - g : pl.row + h + g, pl.col - g : pl.col + w + g] = pad
        else:
            tiles_dn[pl.tile][pl.row : pl.row + h, pl.col : pl.col + w] = dn
        poly = polygons[k]
        coords = {r.id: texture_coordinates(grids[k], r.coords, pl, tile_shapes[pl.tile]) for r in poly.rings}
        targets[pl.tile].append(TextureTarget(polygon_id=poly.id, ring_coords=coords))
    tiles = tuple(TextureTile(name=f"textures/{base}_{i}.png", dn=dn) for i, dn in enumerate(tiles_dn))
    data = tuple(
        ParameterizedTexture(id=f"tex_{base}_{i}", image_uri=tile.name, targets=tuple(targets[i]))
        for i, tile in enumerate(tiles)
    )
    return tiles, Appearance(theme=theme, surface_data=data, id=f"app_{base}_{safe_name(theme)}")

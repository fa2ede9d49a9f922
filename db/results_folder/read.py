"""Reading a results folder back: each textured polygon's texture on its texel grid.

In: a results folder written by `citytherm run` (`textured.gml`, `textures/*.png`,
`report.json`). Out: per textured polygon its `TexelGrid` (recomputed from the polygon with
the texel options the job wrote into `report.json`: grids are deterministic) and its float32
texture `(H, W)` (NaN = DN 0), cut out of the atlas tile where the texture coordinates place it.
Used by the demo, the bench and tests to compare results with a synthetic scene's ground truth.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from db.citygml.reader import read_model
from workers.pipeline.geometry.citymodel import Building, ParameterizedTexture, Polygon
from workers.pipeline.geometry.manifest import Radiometry
from workers.pipeline.options import options_from_dict
from workers.pipeline.texture.texel import TexelGrid, TexelOptions, texel_grid


class ResultsReadError(ValueError):
    """A results folder that does not read back (names the file)."""


@dataclass(frozen=True, eq=False)
class SurfaceTextureFile:
    """One textured polygon of a results folder."""

    building: Building
    polygon: Polygon
    grid: TexelGrid
    value: np.ndarray


def _tile(out_dir: Path, uri: str, cache: dict[str, np.ndarray]) -> np.ndarray:
    if uri not in cache:
        dn = cv2.imread(str(out_dir / uri), cv2.IMREAD_UNCHANGED)
        if dn is None or dn.dtype != np.uint16 or dn.ndim != 2:
            raise ResultsReadError(f"{uri}: not a single-channel 16-bit PNG")
        cache[uri] = dn
    return cache[uri]


def texel_options(report: dict) -> TexelOptions:
    """The texel-grid options a job wrote into its `report.json` (`texel`; older reports give
    only `resolution_px_per_m`, the other options were the defaults then)."""
    try:
        if "texel" in report:
            return options_from_dict(TexelOptions, report["texel"])
        return TexelOptions(resolution_px_per_m=float(report["resolution_px_per_m"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ResultsReadError(f"report.json: texel options: {exc}") from exc


def iter_surface_textures(
    out_dir: str | Path, radiometry: Radiometry, theme: str | None = None
) -> Iterator[SurfaceTextureFile]:
    """Yield every textured polygon of the results folder `out_dir` with its texture.

    `theme` defaults to the job's (`report.json`); the texel grids are laid with the options the
    report gives (`texel_options`), never with defaults.
    """
    out = Path(out_dir)
    try:
        rep = json.loads((out / "report.json").read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ResultsReadError(f"{out / 'report.json'}: {exc}") from exc
    theme = theme or rep["theme"]
    opts = texel_options(rep)
    _, buildings = read_model(out / "textured.gml")
    cache: dict[str, np.ndarray] = {}
    for b in buildings:
        owner = {p.id: part.id for part in b.iter_buildings() for p in part.polygons}
        polys = {p.id: p for p in b.iter_polygons()}
        for app in b.appearances:
            if app.theme != theme:
                continue
            for tex in app.surface_data:
                if not isinstance(tex, ParameterizedTexture):
                    continue
                dn = _tile(out, tex.image_uri, cache)
                H, W = dn.shape
                for target in tex.targets:
                    poly = polys.get(target.polygon_id)
                    if poly is None:
                        raise ResultsReadError(f"textured.gml: target #{target.polygon_id} is not a polygon")
                    grid = texel_grid(poly, owner[poly.id], opts)
                    if grid is None:
                        continue
                    st = target.ring_coords[poly.exterior.id]
                    xy = grid.raster_xy(poly.exterior.coords)
                    col = np.median(st[:, 0] * W - xy[:, 0])
                    row = np.median((1 - st[:, 1]) * H - xy[:, 1])
                    r0, c0 = round(float(row)), round(float(col))
                    h, w = grid.shape
                    block = dn[r0 : r0 + h, c0 : c0 + w]
                    if block.shape != (h, w):
                        raise ResultsReadError(f"{tex.image_uri}: polygon {poly.id} falls outside the tile")
                    value = radiometry.physical(block)
                    value[block == 0] = np.nan
                    yield SurfaceTextureFile(building=b, polygon=poly, grid=grid, value=value)

"""Export a textured model (`ThermalSource`) as a 3D Tiles 1.1 tileset with GLB content.

In: a `ThermalSource` (results folder or database export folder), an output folder, the
`TilesOptions`. Out: `OUT/tileset.json` and `OUT/content/<level>/<x>_<y>.glb`, written into a
temporary folder beside `OUT` and renamed into place at the end (an export that fails leaves no
half tileset; an existing `OUT` is replaced).

Two passes over `textured.gml` (streamed, so memory follows the largest leaf, not the model):
1. every building's bounding-box centre, to ECEF and into the root's east-north-up frame (origin:
   the middle of the centres' horizontal extent, at the lowest centre's height); the quadtree of
   `tiling`;
2. every building gathered per leaf; as soon as a leaf's last building has come, the leaf is
   triangulated (`mesh.building_mesh`) and its GLB written (`content.tile_content`), in this
   process or by a pool of `TilesOptions.workers` processes (`leaves.LeafWriter`).
The display colour range is `TilesOptions.display_range`, else the job's: the lowest 5th and
highest 95th percentile of the surfaces' temperatures, rounded outwards to whole degrees Celsius
(without figures: 263.15-303.15 K, i.e. -10..30 °C).
"""

from __future__ import annotations

import json
import math
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from db.tiles3d.content import SurfaceFigures
from db.tiles3d.frames import EcefTransform, ecef_from_enu, ecef_transform
from db.tiles3d.images import DisplayScale
from db.tiles3d.leaves import LeafDone, LeafJob, LeafWriter, leaf_source
from db.tiles3d.source import ThermalSource
from db.tiles3d.tiling import TileNode, quadtree, tileset_document
from workers.pipeline.geometry.citymodel import Building

__all__ = ["TilesOptions", "TilesetSummary", "display_scale", "export_3dtiles"]

DEFAULT_RANGE_K = (263.15, 303.15)


@dataclass(frozen=True)
class TilesOptions:
    """Options of `export_3dtiles`.

    Attributes:
        max_buildings: most buildings in one leaf tile (one GLB).
        max_depth: deepest quadtree level.
        error_per_side: geometric error of an inner tile per metre of its side.
        display_range: `(lo, hi)` of the display colour map in the value unit (kelvin); None:
            the job's range (module docstring).
        geoid_undulation_m: added to every height before the transformation to ECEF (metres;
            for models in normal heights whose geoid grid PROJ lacks; see `frames`).
        workers: processes writing leaf tiles (`leaves.LeafWriter`); 1: this process only.
    """

    max_buildings: int = 50
    max_depth: int = 12
    error_per_side: float = 1.0 / 8.0
    display_range: tuple[float, float] | None = None
    geoid_undulation_m: float | None = None
    workers: int = 1


@dataclass(frozen=True)
class TilesetSummary:
    """What an export wrote."""

    path: Path
    buildings: int
    tiles: int
    surfaces: int
    triangles: int
    images: int
    bytes: int
    seconds: float
    exact_heights: bool
    display: DisplayScale
    unit: str = "K"


def display_scale(figures: dict[str, SurfaceFigures] | None, unit: str) -> DisplayScale:
    """The job's display range (module docstring)."""
    lo = min((f.p05 for f in (figures or {}).values() if math.isfinite(f.p05)), default=math.nan)
    hi = max((f.p95 for f in (figures or {}).values() if math.isfinite(f.p95)), default=math.nan)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return DisplayScale(*DEFAULT_RANGE_K) if unit == "K" else DisplayScale(0.0, 65535.0)
    if unit == "K":  # whole kelvin outwards, measured from 0 °C so that the legend reads well
        lo = math.floor(lo - 273.15) + 273.15
        hi = math.ceil(hi - 273.15) + 273.15
    return DisplayScale(lo, max(hi, lo + 1.0))


def _centres(source: ThermalSource) -> tuple[list[str], np.ndarray]:
    """Pass 1: ids and bounding-box centres `(N, 3)` (model CRS) of the buildings with polygons."""
    ids, centres = [], []
    for b in source.buildings():
        rings = [r.coords for p in b.iter_polygons() for r in p.rings if len(r.coords)]
        if not rings:
            continue
        pts = np.concatenate(rings)
        ids.append(b.id)
        centres.append(0.5 * (pts.min(axis=0) + pts.max(axis=0)))
    return ids, np.array(centres, dtype=np.float64).reshape(-1, 3)


def export_3dtiles(
    source: ThermalSource,
    out_dir: str | Path,
    options: TilesOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> TilesetSummary:
    """Write the tileset of `source` into `out_dir` (module docstring); `progress(done, total)`
    is called after each building of pass 2."""
    opts = options or TilesOptions()
    t0 = time.perf_counter()
    out = Path(out_dir)
    ecef = ecef_transform(source.srs_name, opts.geoid_undulation_m)
    ids, centres = _centres(source)
    if not ids:
        raise ValueError(f"{source.gml}: no building with polygons: nothing to export")
    lo_m, hi_m = centres.min(axis=0), centres.max(axis=0)
    origin_model = np.array([0.5 * (lo_m[0] + hi_m[0]), 0.5 * (lo_m[1] + hi_m[1]), lo_m[2]])
    ecef_from_root = ecef_from_enu(ecef.points(origin_model[None])[0])
    root_from_ecef = np.linalg.inv(ecef_from_root)
    enu = ecef.points(centres) @ root_from_ecef[:3, :3].T + root_from_ecef[:3, 3]
    root = quadtree(enu[:, :2], opts.max_buildings, opts.max_depth)
    leaves = root.leaves()
    leaf_of: dict[str, TileNode] = {}
    for leaf in leaves:
        leaf.centre = np.zeros(3) if leaf is root else enu[leaf.members].mean(axis=0)
        for i in leaf.members:
            leaf_of[ids[i]] = leaf
    display = (
        DisplayScale(*opts.display_range)
        if opts.display_range is not None
        else display_scale(dict(source.figures), source.values.unit)
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}-", dir=out.parent))
    pending: dict[int, list[Building]] = {}
    counts = dict(tiles=0, surfaces=0, triangles=0, images=0, bytes=0)
    by_key = {id(leaf): leaf for leaf in leaves}

    def finish(d: LeafDone) -> None:
        leaf = by_key[d.key]
        assert leaf.centre is not None
        leaf.content = f"content/{leaf.name}.glb"
        leaf.bounds = (d.lo + leaf.centre, d.hi + leaf.centre)
        counts["tiles"] += 1
        for k in ("surfaces", "triangles", "images", "bytes"):
            counts[k] += getattr(d, k)

    try:
        with LeafWriter(opts.workers) as writer:
            done = 0
            for b in source.buildings():
                leaf = leaf_of.get(b.id)
                if leaf is None:
                    continue
                got = pending.setdefault(id(leaf), [])
                got.append(b)
                done += 1
                if progress is not None:
                    progress(done, len(ids))
                if len(got) == len(leaf.members):
                    mine = tuple(pending.pop(id(leaf)))
                    job = _leaf_job(tmp, leaf, mine, source, opts, ecef_from_root, display)
                    for d in writer.submit(job):
                        finish(d)
            for d in writer.drain():
                finish(d)
        if pending:
            raise ValueError(f"{source.gml}: buildings changed between the two passes")
        doc = tileset_document(root, ecef_from_root, opts.error_per_side, _extras(source, ecef, display))
        (tmp / "tileset.json").write_text(json.dumps(doc, indent=1, allow_nan=False), encoding="utf-8")
        if out.exists():
            shutil.rmtree(out)
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return TilesetSummary(
        path=out / "tileset.json",
        buildings=len(ids),
        seconds=time.perf_counter() - t0,
        exact_heights=ecef.exact or opts.geoid_undulation_m is not None,
        display=display,
        unit=source.values.unit,
        **counts,
    )


def _leaf_job(
    tmp: Path,
    leaf: TileNode,
    buildings: tuple[Building, ...],
    source: ThermalSource,
    opts: TilesOptions,
    ecef_from_root: np.ndarray,
    display: DisplayScale,
) -> LeafJob:
    """The job of one leaf: its GLB in the frame `ecef_from_root` · translation(leaf centre)."""
    assert leaf.centre is not None
    ecef_from_leaf = ecef_from_root.copy()
    ecef_from_leaf[:3, 3] = ecef_from_root[:3, :3] @ leaf.centre + ecef_from_root[:3, 3]
    return LeafJob(
        key=id(leaf),
        path=tmp / f"content/{leaf.name}.glb",
        buildings=buildings,
        source=leaf_source(source, buildings),
        geoid_undulation_m=opts.geoid_undulation_m,
        local_from_ecef=np.linalg.inv(ecef_from_leaf),
        display=display,
    )


def _extras(source: ThermalSource, e: EcefTransform, display: DisplayScale) -> dict:
    """`asset.extras.citytherm` of the tileset: theme, CRS, heights, value and display scales."""
    return {
        "citytherm": {
            "format": "citytherm-3dtiles/1",
            "source": source.label,
            "theme": source.theme,
            "crs": source.srs_name,
            "ecef_operation": e.operation,
            "heights_exact": bool(e.exact),
            "geoid_undulation_m": e.geoid_undulation_m,
            "value": {
                "unit": source.values.unit,
                "dn_scale": source.values.scale,
                "dn_offset": source.values.offset,
                "texture": "EXT_structural_metadata property texture 'temperature' (channels r = low, "
                "g = high byte of the DN)",
            },
            "display": {
                "colormap": display.colormap,
                "range": [display.lo, display.hi],
                "unit": source.values.unit,
                "index": "colour index i in 1..255 shows lo + (i - 1) / 254 * (hi - lo); black: not observed",
            },
        }
    }

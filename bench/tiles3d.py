"""3D Tiles export benchmark (issue 17): buildings/s of `db.tiles3d.export_3dtiles` on the replicated
NRW model with a thermal texture on every polygon.

The input is made first (not timed): `bench/citygml_io.make_replicated_model` writes `--copies`
shifted copies of the NRW LoD2 tile (109 buildings + 55 parts each; 101 copies = 11,009 buildings,
as the issue's "11,000-building model"), then every building gets a job-like appearance: one
16-bit atlas per building (`--atlas` px square, smooth values around 280 K) with each polygon's
texture coordinates in a cell of it, written as a results-like folder (`textured.gml`,
`textures/`, `tiles3d-source.json`). Then the export runs in this process, timed: buildings/s
over the whole export (both passes, triangulation, ECEF, PNG encoding, GLB and tileset writing),
tiles, triangles, MB written, peak RSS.

Usage: `python bench/tiles3d.py [--copies 101] [--quick] [--atlas 128] [--workers N] [--keep DIR]`
prints JSON (`--quick`: 5 copies, 545 buildings; `--workers`: processes writing tiles, default 1:
on a 2-core machine the main process's CityGML parsing already takes one core). The machine is
shared: `loadavg` is printed with the figures, which drop when other processes take the cores.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))
NRW = REPO / "tests" / "data" / "nrw-tile-5659-citygml1-lod2.gml"

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from db.citygml import open_model, write_citygml  # noqa: E402
from db.tiles3d import TilesOptions, export_3dtiles, folder_source  # noqa: E402
from db.tiles3d.source import write_source_file  # noqa: E402
from workers.pipeline.geometry.citymodel import (  # noqa: E402
    Appearance,
    Building,
    ParameterizedTexture,
    TextureTarget,
)
from workers.pipeline.geometry.manifest import Radiometry  # noqa: E402
from workers.pipeline.geometry.polygons import fit_plane, open_ring, surface_axes, to_plane_2d  # noqa: E402


def _textured(b: Building, folder: Path, atlas: int, rng: np.random.Generator) -> Building:
    """`b` with a `thermal-ir` appearance: one atlas, each polygon in a cell of it."""
    polys = [p for p in b.iter_polygons() if fit_plane(p) is not None]
    cells = max(1, math.ceil(math.sqrt(len(polys))))
    cell = atlas / cells
    targets = []
    for k, p in enumerate(polys):
        plane = fit_plane(p)
        s_ax, t_ax = surface_axes(plane.normal, p.exterior.coords)  # type: ignore[union-attr]
        st = {r.id: to_plane_2d(r.coords, plane.centroid, s_ax, t_ax) for r in p.rings}  # type: ignore[union-attr]
        ext = open_ring(st[p.exterior.id])
        lo, span = ext.min(axis=0), np.maximum(ext.max(axis=0) - ext.min(axis=0), 1e-6)
        cx, cy = (k % cells) * cell, (k // cells) * cell
        coords = {}
        for rid, xy in st.items():
            uv = (xy - lo) / span * (cell - 2) + 1
            coords[rid] = np.c_[(cx + uv[:, 0]) / atlas, 1.0 - (cy + (cell - uv[:, 1])) / atlas]
        targets.append(TextureTarget(p.id, coords))
    uri = f"textures/{b.id}_0.png"
    yy, xx = np.mgrid[0:atlas, 0:atlas]
    dn = 28000 + 300 * np.sin(xx / 9.0 + rng.uniform(0, 6)) + 200 * np.cos(yy / 7.0)
    dn = dn + rng.normal(0, 20, xx.shape)
    cv2.imwrite(str(folder / uri), np.clip(dn, 1, 65535).astype(np.uint16))
    tex = ParameterizedTexture(f"tex_{b.id}", uri, tuple(targets))
    return replace(b, appearances=(*b.appearances, Appearance("thermal-ir", (tex,), id=f"app_{b.id}")))


def make_input(work: Path, copies: int, atlas: int) -> tuple[Path, int, float]:
    """The textured results-like folder; (folder, buildings, seconds)."""
    from citygml_io import make_replicated_model

    t0 = time.perf_counter()
    model = make_replicated_model(NRW, work / "model.gml", copies)
    folder = work / "results"
    (folder / "textures").mkdir(parents=True)
    header, buildings, _ = open_model(model, huge_tree=True)
    rng = np.random.default_rng(5)
    n = write_citygml(folder / "textured.gml", (_textured(b, folder, atlas, rng) for b in buildings),
                      srs_name=header.srs_name)  # fmt: skip
    write_source_file(folder, "thermal-ir", Radiometry("K", 0.01, 0.0), {})
    model.unlink()
    return folder, n, time.perf_counter() - t0


def _peak_rss_mb(who: int = resource.RUSAGE_SELF) -> float:
    """Peak RSS (MB) of this process, or of its largest waited-for child."""
    return resource.getrusage(who).ru_maxrss / 1024.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--copies", type=int, default=101, help="copies of the NRW tile (101: 11,009 buildings)")
    ap.add_argument("--quick", action="store_true", help="5 copies (545 buildings)")
    ap.add_argument("--atlas", type=int, default=128, help="atlas side per building, px")
    ap.add_argument("--keep", type=Path, default=None, help="keep input and tileset in this folder")
    ap.add_argument("--workers", type=int, default=1, help="processes writing tiles")
    args = ap.parse_args()
    copies = 5 if args.quick else args.copies
    work = Path(tempfile.mkdtemp(prefix="bench-tiles3d-")) if args.keep is None else args.keep
    work.mkdir(parents=True, exist_ok=True)
    try:
        folder, n, prep_s = make_input(work, copies, args.atlas)
        out = work / "tiles"
        rss0 = _peak_rss_mb()
        s = export_3dtiles(folder_source(folder), out, TilesOptions(workers=args.workers))
        fig = {
            "bench": "tiles3d",
            "command": " ".join(["python", "bench/tiles3d.py", *sys.argv[1:]]),
            "buildings": s.buildings,
            "copies": copies,
            "export_s": round(s.seconds, 2),
            "buildings_per_s": round(s.buildings / s.seconds, 1),
            "tiles": s.tiles,
            "surfaces": s.surfaces,
            "triangles": s.triangles,
            "textures": s.images,
            "mb_written": round(s.bytes / 1e6, 1),
            "input_prep_s": round(prep_s, 1),
            "peak_rss_mb_before_export": round(rss0, 1),
            "peak_rss_mb": round(_peak_rss_mb(), 1),
            "peak_rss_mb_largest_worker": round(_peak_rss_mb(resource.RUSAGE_CHILDREN), 1),
            "workers": args.workers,
            "cpus": os.cpu_count(),
            "loadavg": [round(v, 2) for v in os.getloadavg()],
        }
        assert n == s.buildings, (n, s.buildings)
        print(json.dumps(fig, indent=1))
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()

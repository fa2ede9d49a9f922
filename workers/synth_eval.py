"""Compare a results folder with a synthetic scene's ground truth (demo and bench).

In: a results folder of `citytherm run` and the `SynthResult` that made its package.
Out: texture figures (RMSE in kelvin — all observed texels, near and away from sharp edges —,
median misregistration in texels, coverage of the texels the frames can see) and, when poses
were refined, the refined poses' errors against the true poses.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from db.results_folder.read import iter_surface_textures, surface_resolutions
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.synth import SynthResult
from workers.pipeline.texture.quality import summarize, surface_errors, truth_raster, visible_texels
from workers.pipeline.texture.texel import TexelGrid, TexelOptions, texel_grid


def below_ground(
    grid: TexelGrid, ground_z: float | Callable[[np.ndarray], np.ndarray], top: float = np.inf
) -> np.ndarray:
    """`(H, W)` bool: texel centres below the synthetic ground (hidden in that world): the plane
    `ground_z`, or a height function `xy (N, 2) -> (N,)` m (`SynthTruth.ground_height`) whose
    values never exceed `top` m (`Ground.top`: centres above it are not looked up)."""
    r, c = np.indices(grid.shape)
    X = grid.centres(r.ravel(), c.ravel())
    if not callable(ground_z):
        return (X[:, 2] < ground_z).reshape(grid.shape)
    out = np.zeros(len(X), bool)
    low = np.flatnonzero(X[:, 2] < top)
    out[low] = X[low, 2] < ground_z(X[low, :2])
    return out.reshape(grid.shape)


def texture_accuracy(out_dir: str | Path, res: SynthResult) -> dict[str, float]:
    """Texture figures of the results folder against the truth of `res` (true poses decide
    which texels the frames can see; texels below the synthetic ground plane are left out)."""
    out = Path(out_dir)
    rep = json.loads((out / "report.json").read_text(encoding="utf-8"))
    processed = {b["id"] for b in rep["buildings"]}
    got = {s.polygon.id: s for s in iter_surface_textures(out, res.manifest.radiometry)}
    caster = RayCaster(res.mesh)
    gz = res.truth.ground_z if res.truth.ground is None else res.truth.ground_height
    top = np.inf if res.truth.ground is None else res.truth.ground.top
    opts = TexelOptions(resolution_px_per_m=float(rep["resolution_px_per_m"]))
    per_surface = surface_resolutions(rep)
    errors = []
    for b in res.buildings:
        if b.id not in processed:
            continue
        for part in b.iter_buildings():
            for poly in part.polygons:
                r = per_surface.get(poly.id, opts.resolution_px_per_m)
                grid = texel_grid(poly, part.id, replace(opts, resolution_px_per_m=r))
                if grid is None:
                    continue
                below = below_ground(grid, gz, top)
                if callable(gz):  # a terrain: its texels below it are never seen (as the plane's)
                    vis = visible_texels(grid, res.manifest.camera, res.truth.poses, caster) & ~below
                else:
                    vis = visible_texels(grid, res.manifest.camera, res.truth.poses, caster, ground_z=gz)
                if not vis.any() and poly.id not in got:
                    continue
                truth = truth_raster(grid, lambda X, pid=poly.id: res.thermal.surface_temperature(pid, X))
                value = (
                    got[poly.id].value.copy() if poly.id in got else np.full(grid.shape, np.nan, np.float32)
                )
                value[below] = np.nan
                errors.append(surface_errors(grid, value, truth, vis))
    return summarize(errors)


def orientation_accuracy(out_dir: str | Path, res: SynthResult) -> dict[str, Any]:
    """Position errors (m) of prior and refined poses against the true poses, medians."""
    doc = json.loads((Path(out_dir) / "orientation.json").read_text(encoding="utf-8"))
    prior, refined = [], []
    for f in doc["frames"]:
        true_c = res.truth.poses[f["index"]].center
        prior.append(float(np.linalg.norm(np.array(f["prior"]["center"]) - true_c)))
        for r in f["refined"]:
            if r["status"] == "refined":
                refined.append(float(np.linalg.norm(np.array(r["center"]) - true_c)))
    return {
        "prior_position_error_median_m": float(np.median(prior)) if prior else None,
        "refined_position_error_median_m": float(np.median(refined)) if refined else None,
        "refined_entries": len(refined),
    }

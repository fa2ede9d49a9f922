"""Orientation methods side by side (issue 19, item 1): the orient stage with `--orientation
edges`, `sfm` and `both` on synthetic drives with the default GNSS/INS error model, one with the
generator's textured facades (windows, slab lines, corner peaks) and one with thermally
homogeneous facades (`ThermalOptions(facade_details=False)`, no per-building or per-polygon
temperature spread, a fine random texture of `facade_noise_k`): the model's edges inside and
between facades leave no trace there, the roof line and the texture stay.

Per scene: the calibrate stage once (as `citytherm run`), then the orient stage per method on the
calibrated priors. Per method: frames oriented (the edge path's confirmed frames, the
reconstruction's registered ones, their union for `both`) as a share of all frames; per (frame,
building) pair whose true pose sees the building's edge points, the reprojection RMS of those
points (`quality.reprojection_rms`, every 0.5 m along the polygon edges) at the stage's pose
(the calibrated prior where it left the frame) against the true pose: share below 1 px, median;
the reconstruction's figures (`report.json` `sequence_orientation.reconstruction`); CPU and wall
seconds of the stage.

Usage: `python bench/orientation.py --methods [--frames 60] [--seed 1]` or
`python bench/orientation_methods.py [--frames 60] [--seed 1] [--scenes textured,homogeneous]`.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from workers import job
from workers.pipeline.geometry.georef import prior_poses
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.orientation.building import CoregisterOptions
from workers.pipeline.orientation.quality import edge_points
from workers.pipeline.orientation.quality import reprojection_rms as quality_rms
from workers.pipeline.synth import ErrorOptions, SynthOptions, ThermalOptions, procedural_block, synthesize
from workers.pipeline.units import UnitOptions

METHODS = ("edges", "sfm", "both")

#: homogeneous facades: no windows, slabs, corners, pipes; one temperature for every wall
HOMOGENEOUS = ThermalOptions(
    facade_details=False,
    building_sigma_k=0.0,
    surface_sigma_k=0.0,
    facade_noise_k=1.0,
    facade_noise_cell_m=0.15,
)


def drive(frames: int, seed: int, homogeneous: bool):  # -> (SynthResult, list of images)
    """A drive around a procedural block with the default error model."""
    thermal = HOMOGENEOUS if homogeneous else ThermalOptions()
    res = synthesize(
        procedural_block(6, seed=seed),
        SynthOptions(
            platform="drive", n_frames=frames, seed=seed, buildings=3, errors=ErrorOptions(), thermal=thermal
        ),
    )
    return res, [res.frames.load(i) for i in range(frames)]


def pair_errors(res, poses: dict[int, Pose] | list[Pose]) -> np.ndarray:
    """Reprojection RMS (px) of every (frame, building) pair whose true pose sees the building's
    edge points, `poses` against the truth."""
    cam, T = res.manifest.camera, res.truth.poses
    out = []
    for b in res.buildings:
        pts = edge_points(b)
        for i, t in enumerate(T):
            if np.isfinite(quality_rms(cam, pts, t, t, min_points=4)):
                out.append(quality_rms(cam, pts, poses[i], t, min_points=4))
    return np.asarray(out, dtype=np.float64)


def figures(e: np.ndarray) -> dict:
    """Pairs, share below 1 px, median px of pair errors `e` (NaN: not counted)."""
    e = e[np.isfinite(e)]
    if not len(e):
        return {"pairs": 0}
    return {
        "pairs": len(e),
        "pairs_below_1px": round(float(np.mean(e < 1.0)), 3),
        "median_px": round(float(np.median(e)), 3),
    }


def scene_figures(frames: int, seed: int, homogeneous: bool) -> dict:
    """Calibrate once, orient per method (module docstring)."""
    from bench.orientation import ingested

    res, imgs = drive(frames, seed, homogeneous)
    priors = prior_poses(res.manifest, None)
    base = job.RunOptions(unit=UnitOptions(refine=CoregisterOptions()))
    ing = ingested(res, imgs, priors, base)
    caster = job.scene_caster(ing)
    calibrated = job.calibrate(ing, base, caster)
    out: dict = {
        "frames": frames,
        "calibration_accepted": calibrated.accepted,
        "priors": figures(pair_errors(res, priors)),
        "calibrated_priors": figures(pair_errors(res, list(calibrated.priors))),
    }
    for method in METHODS:
        c0, w0 = time.process_time(), time.perf_counter()
        oriented = job.orient(ing, calibrated, replace(base, orientation=method), caster=caster)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        so = oriented.orientation
        poses = so.poses if so is not None else dict(enumerate(calibrated.priors))
        n_or = len(so.covariance) if so is not None else 0
        out[method] = {
            "frames_oriented": round(n_or / frames, 3),
            **figures(pair_errors(res, poses)),
            "reconstruction": oriented.report.get("reconstruction"),
            "reason": oriented.report.get("reason"),
            "cpu_s": round(cpu, 1),
            "wall_s": round(wall, 1),
        }
    return out


def bars(scenes: dict) -> dict:
    """The issue's bars on the scenes measured (module docstring of `bench/orientation.py`)."""
    out: dict = {}
    for name, s in scenes.items():
        e, f, b = s["edges"], s["sfm"], s["both"]
        if e["frames_oriented"] < 0.8:
            out[f"{name}: sfm frames registered >= 0.95 (edges < 0.8)"] = f["frames_oriented"] >= 0.95
            out[f"{name}: sfm pairs below 1 px >= 0.90"] = (f.get("pairs_below_1px") or 0) >= 0.90
        out[f"{name}: both never worse"] = (b.get("pairs_below_1px") or 0) >= max(
            e.get("pairs_below_1px") or 0, f.get("pairs_below_1px") or 0
        ) - 0.01 and b["frames_oriented"] >= max(e["frames_oriented"], f["frames_oriented"])
    return out


def method_figures(frames: int, seed: int, scenes: list[str]) -> dict:
    """Every scene of `scenes` (`textured`, `homogeneous`) and the bars."""
    out = {name: scene_figures(frames, seed, homogeneous=name == "homogeneous") for name in scenes}
    return {"scenes": out, "bars": bars(out)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--scenes", default="textured,homogeneous")
    a = ap.parse_args()
    t0 = time.perf_counter()
    out = {"bench": "orientation_methods", **method_figures(a.frames, a.seed, a.scenes.split(","))}
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

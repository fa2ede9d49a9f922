"""The paper's table 1 on synthetic scenes (issue 19, item 4): the orientation of a TIR drive
without and with model knowledge, on a scene with textured facades, one with thermally
homogeneous facades and one with occluders the model lacks (street trees and parked cars,
`synth.occluders`, rendered in the frames but absent from the building model).

Per scene (a drive around a procedural block with the default GNSS/INS error model, the same
seed and trajectory in all three), per orientation:

- `gnss_ins`: the recorded GNSS/INS poses through the nominal mounting (`prior_poses`);
- `relative_no_model`: the sequence's own reconstruction (method 1: LK tracks, pycolmap bundle
  adjustment) placed on the GNSS/INS by a 7-parameter similarity, **no model**: the facade-plane
  coregistration switched off (`ReconstructionOptions.min_plane_points` beyond reach), from the
  uncalibrated priors;
- with model knowledge, as `citytherm run` orients (the calibrate stage against the model's
  edges, then the orient stage): `calibrated` (the calibrated priors alone), `edges`,
  `sfm` (the reconstruction coregistered to the facade planes), `both`.

Figures per orientation: frames oriented (share of all frames: the method's registered or
confirmed frames; priors count all), the empirical σ of the pose against the truth over all
frames — RMS of the camera centre error per axis and in 3D (m) and of the rotation error angle
(degrees) —, and per (frame, building) pair whose true pose sees the building's edge points
the reprojection RMS of those points (share below 1 px, median px).

Usage: `python bench/orientation_table1.py [--frames 40] [--seed 1]
[--scenes textured,homogeneous,occluders]` (prints JSON).
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

from bench.orientation import ingested
from bench.orientation_methods import HOMOGENEOUS, figures, pair_errors
from workers import job
from workers.pipeline.geometry.georef import prior_poses
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.orientation.building import CoregisterOptions
from workers.pipeline.reconstruction.options import ReconstructionOptions
from workers.pipeline.reconstruction.orient import orient_reconstruction
from workers.pipeline.synth import (
    ErrorOptions,
    OccluderOptions,
    SynthOptions,
    SynthResult,
    ThermalOptions,
    procedural_block,
    synthesize,
)
from workers.pipeline.units import UnitOptions

SCENES = ("textured", "homogeneous", "occluders")
#: the reconstruction without model knowledge: no facade plane is ever used
NO_MODEL = ReconstructionOptions(min_plane_points=10**9)


def drive(scene: str, frames: int, seed: int) -> SynthResult:
    """The scene's drive (module docstring): textured (the generator's facades), homogeneous
    (`bench.orientation_methods.HOMOGENEOUS`) or occluders (textured, with trees and cars)."""
    thermal = HOMOGENEOUS if scene == "homogeneous" else ThermalOptions()
    return synthesize(
        procedural_block(6, seed=seed),
        SynthOptions(
            platform="drive", n_frames=frames, seed=seed, buildings=3, errors=ErrorOptions(), thermal=thermal,
            occluders=OccluderOptions() if scene == "occluders" else None,
        ),
    )  # fmt: skip


def pose_sigma(res: SynthResult, poses: dict[int, Pose] | list[Pose]) -> dict:
    """Empirical σ of `poses` (every frame) against the truth: RMS of the centre error per axis
    (x, y, z; m), in 3D (m), in 3D after removing the mean error (m: the scatter a relative
    orientation fixes, without the common shift only model knowledge or ground control fixes),
    and of the rotation error angle (degrees)."""
    dc, ang = [], []
    for i, t in enumerate(res.truth.poses):
        p = poses[i]
        dc.append(np.asarray(p.center) - t.center)
        R = np.asarray(p.R_world_from_cam).T @ t.R_world_from_cam
        ang.append(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))
    d = np.asarray(dc)
    scatter = d - d.mean(axis=0)
    return {
        "sigma_xyz_m": [round(float(v), 3) for v in np.sqrt(np.mean(d**2, axis=0))],
        "sigma_3d_m": round(float(np.sqrt(np.mean(np.sum(d**2, axis=1)))), 3),
        "sigma_3d_m_without_mean": round(float(np.sqrt(np.mean(np.sum(scatter**2, axis=1)))), 3),
        "sigma_rotation_deg": round(float(np.sqrt(np.mean(np.square(ang)))), 3),
    }


def row(res: SynthResult, poses: dict[int, Pose] | list[Pose], oriented: int, cpu: float | None) -> dict:
    """One orientation's figures (module docstring)."""
    out = {
        "frames_oriented": round(oriented / len(res.truth.poses), 3),
        **pose_sigma(res, poses),
        **figures(pair_errors(res, poses)),
    }
    if cpu is not None:
        out["cpu_s"] = round(cpu, 1)
    return out


def scene_table(scene: str, frames: int, seed: int) -> dict:
    """Every orientation of one scene (module docstring)."""
    res = drive(scene, frames, seed)
    imgs = [res.frames.load(i) for i in range(frames)]
    priors = prior_poses(res.manifest, None)
    base = job.RunOptions(unit=UnitOptions(refine=CoregisterOptions()))
    ing = ingested(res, imgs, priors, base)
    caster = job.scene_caster(ing)
    out: dict = {"occluders": len(res.truth.occluders), "gnss_ins": row(res, priors, frames, None)}

    c0 = time.process_time()
    idx = ing.frame_indices
    ro = orient_reconstruction(
        res.manifest.camera, caster, idx, ing.frames, dict(zip(idx, priors, strict=True)),
        dict(zip(idx, ing.times, strict=True)), res.manifest.accuracy, NO_MODEL,
    )  # fmt: skip
    out["relative_no_model"] = {
        **row(res, ro.poses, len(ro.registered), time.process_time() - c0),
        "runs": [{k: r.get(k) for k in ("frames", "registered", "reason", "sigma0_px")} for r in ro.runs],
    }

    c0 = time.process_time()
    calibrated = job.calibrate(ing, base, caster)
    cal_cpu = time.process_time() - c0
    cal = row(res, list(calibrated.priors), frames, cal_cpu)
    out["calibrated"] = {**cal, "accepted": calibrated.accepted}
    for method in ("edges", "sfm", "both"):
        c0 = time.process_time()
        oriented = job.orient(ing, calibrated, replace(base, orientation=method), caster=caster)
        so = oriented.orientation
        poses = so.poses if so is not None else dict(enumerate(calibrated.priors))
        n_or = len(so.covariance) if so is not None else 0
        out[method] = row(res, poses, n_or, time.process_time() - c0 + cal_cpu)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--scenes", default=",".join(SCENES))
    a = ap.parse_args()
    t0 = time.perf_counter()
    scenes = {s: scene_table(s, a.frames, a.seed) for s in a.scenes.split(",")}
    out = {"bench": "orientation_table1", "frames": a.frames, "seed": a.seed, "scenes": scenes}
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

"""Sequence orientation bench (issue 19, item 0): the calibrate and orient stages of
`citytherm run` on a close-range sequence of one facade and on drives, accepted calibration or not.

Scenes (synthetic, `citytherm synth`, frames held in memory):

- `facade`: a one-wall model (a single WallSurface, 20 × 12 m), a hand-held camera walking 10 m
  in front of it (`platform="terrestrial"`), priors = true poses + a common error (0.3 m, 0.6°)
  + per-frame noise of σ 0.5 m / 1° per axis (as on the real one-facade sequence of issue 19);
- `facade_rejected`: the same, the calibration rejected by hand (as on the real sequence of issue
  19: "too few frames see the model"; the synthetic walk's calibration is accepted);
- `facade_default_errors`: the same walk with the default GNSS/INS error model of the generator;
- `drive`: a drive around a procedural block with the default error model (the calibration is
  accepted there: the path `citytherm run` took before);
- `drive_uncalibrated`: the same drive with the calibration rejected by hand (the orient stage
  starts from the manifest's priors).

Per scene: whether the calibration was accepted, the `sequence_orientation` report (blocks,
frames oriented), and per frame the RMS reprojection error (px) against the true pose of model
points the true pose sees (the wall every metre; the cluster buildings' edges every 0.5 m):
share of frames below 1 px, median and 90th percentile, for the priors the stage started from,
for what the units got before this change (the calibrated priors when the calibration was
rejected: no orient stage; after an accepted one the orient stage with the start poses the
priors themselves, `start_smoothing_s=0`: no smoothed start, no second pass, the acceptance of
now) and after the orient stage. Stage times: CPU seconds (`time.process_time`, all
threads) and wall seconds of calibrate and orient.

Usage: `python bench/orientation_sequence.py [--quick] [--frames 40] [--seed 3]`, or through
`python bench/orientation.py --quick`.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from workers import job
from workers.pipeline.geometry.citymodel import Building, ModelHeader, Polygon, Ring
from workers.pipeline.geometry.georef import prior_poses
from workers.pipeline.geometry.manifest import Accuracy, MemoryFrames
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import apply_delta
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.building import CoregisterOptions
from workers.pipeline.orientation.calibration import SequenceCalibration
from workers.pipeline.orientation.quality import edge_points
from workers.pipeline.orientation.quality import reprojection_rms as quality_rms
from workers.pipeline.orientation.sequence import SequenceOrientationOptions, orient_sequence
from workers.pipeline.synth import ErrorOptions, SynthOptions, procedural_block, synthesize
from workers.pipeline.units import UnitOptions

FACADE_ACCURACY = Accuracy(position_m=np.full(3, 0.5), attitude_deg=np.full(3, 1.0))


def one_wall(width: float = 20.0, height: float = 12.0) -> Building:
    """A one-wall model: one vertical WallSurface in the plane y = 0 (normal −y), metres."""
    c = np.array([(0, 0, 0), (width, 0, 0), (width, 0, height), (0, 0, height), (0, 0, 0)], float)
    poly = Polygon(id="W1_w", exterior=Ring(id="W1_r", coords=c), surface_class="WallSurface")
    return Building(id="W1", polygons=(poly,))


def wall_points(width: float = 20.0, height: float = 12.0) -> np.ndarray:
    """`(273, 3)` points every metre on the one wall, corners included."""
    gx, gz = np.meshgrid(np.linspace(0, width, 21), np.linspace(0, height, 13))
    return np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], axis=1)


def noisy_priors(truth: list[Pose], seed: int) -> list[Pose]:
    """True poses + a common error (0.3 m, 0.6° per axis) + per-frame noise σ 0.5 m / 1° per axis
    (rotations about the camera axes, positions in world axes)."""
    rng = np.random.default_rng(seed)
    common = np.r_[np.radians([0.5, -0.6, 0.4]), [0.3, -0.2, 0.25]]
    return [
        apply_delta(T, common + np.r_[np.radians(rng.normal(0, 1.0, 3)), rng.normal(0, 0.5, 3)])
        for T in truth
    ]


def ingested(res, images: dict[int, np.ndarray], priors: list[Pose]) -> job.Ingested:
    """The ingest stage's result for a synthetic sequence, frames in memory, `priors` given."""
    m = res.manifest
    return job.Ingested(
        city_gml=Path("<synthetic>"),
        package_dir=Path("<memory>"),
        header=ModelHeader("2.0"),
        manifest=m,
        frames=MemoryFrames(images),
        priors=tuple(priors),
        buildings=tuple(res.buildings),
        n_model_buildings=len(res.buildings),
        radiometry=m.radiometry,
    )


def frame_errors(res, points: np.ndarray, poses) -> np.ndarray:
    """Per frame the RMS reprojection error (px) of `points` `(N, 3)` that the true pose sees
    (NaN where it sees fewer than 4), `poses` against the true poses."""
    cam, T = res.manifest.camera, res.truth.poses
    return np.array([quality_rms(cam, points, poses[i], T[i], min_points=4) for i in range(len(T))])


def figures(e: np.ndarray) -> dict:
    """Share of frames below 1 px, median and 90th percentile (px) of per-frame errors `e`."""
    e = e[np.isfinite(e)]
    if not len(e):
        return {"frames": 0}
    return {
        "frames": len(e),
        "share_below_1px": round(float(np.mean(e < 1.0)), 3),
        "median_px": round(float(np.median(e)), 3),
        "p90_px": round(float(np.percentile(e, 90)), 3),
    }


def run_scene(
    res,
    images,
    priors: list[Pose],
    points: np.ndarray,
    accuracy: Accuracy | None,
    reject_calibration: bool = False,
) -> dict:
    """Calibrate (or reject the calibration by hand) and orient as `citytherm run` does; figures."""
    ing = ingested(res, images, priors)
    opts = job.RunOptions(unit=UnitOptions(refine=CoregisterOptions()))
    caster = job.scene_caster(ing)
    c0, w0 = time.process_time(), time.perf_counter()
    if reject_calibration:
        cal = SequenceCalibration(theta=np.zeros(10), reason="rejected by the bench")
        calibrated = job.Calibrated(cal, tuple(priors), accuracy or res.manifest.accuracy)
    else:
        calibrated = job.calibrate(ing, opts, caster)
        if accuracy is not None and not calibrated.accepted:
            calibrated = job.Calibrated(calibrated.calibration, calibrated.priors, accuracy)
    c1, w1 = time.process_time(), time.perf_counter()
    oriented = job.orient(ing, calibrated, opts, caster=caster)
    c2, w2 = time.process_time(), time.perf_counter()
    after = oriented.orientation.poses if oriented.orientation is not None else calibrated.priors
    report = {k: v for k, v in oriented.report.items() if k != "blocks"}
    report["blocks"] = [
        {
            k: b[k]
            for k in (
                "frames",
                "accepted",
                "reason",
                "frames_anchored",
                "frames_confirmed_by_planes",
                "frames_inconsistent_with_priors",
                "frames_undetermined",
                "frames_taken",
                "sigma0",
                "tracks",
            )
        }
        for b in oriented.report.get("blocks", [])
    ]
    n = len(images)
    return {
        "frames": n,
        "calibration_accepted": calibrated.accepted,
        "calibration_reason": calibrated.calibration.reason if calibrated.calibration else None,
        "sequence_orientation": report,
        "priors": figures(frame_errors(res, points, priors)),
        "before_this_change": figures(frame_errors(res, points, before_change(ing, calibrated, caster))),
        "calibrated_priors": figures(frame_errors(res, points, calibrated.priors)),
        "after_orient_stage": figures(frame_errors(res, points, after)),
        "calibrate_cpu_s": round(c1 - c0, 2),
        "calibrate_wall_s": round(w1 - w0, 2),
        "orient_cpu_s": round(c2 - c1, 2),
        "orient_wall_s": round(w2 - w1, 2),
        "orient_cpu_ms_per_frame": round(1000 * (c2 - c1) / n, 1),
    }


def before_change(ing: job.Ingested, calibrated: job.Calibrated, caster: RayCaster | None) -> dict[int, Pose]:
    """The poses the units started from before issue 19's item 0: the calibrated priors when the
    calibration was rejected, else the orient stage without the smoothed start (module docstring)."""
    if not calibrated.accepted or caster is None:
        return dict(enumerate(calibrated.priors))
    frames, m = ing.frame_indices, ing.manifest
    so = orient_sequence(
        m.camera,
        caster,
        frames,
        ing.frames,
        dict(zip(frames, calibrated.priors, strict=True)),
        dict(zip(frames, ing.times, strict=True)),
        calibrated.accuracy,
        SequenceOrientationOptions(start_smoothing_s=0.0),
    )
    return so.poses


def facade(frames: int, seed: int, default_errors: bool, reject_calibration: bool = False) -> dict:
    """The one-facade walk (module docstring)."""
    res = synthesize(
        [one_wall()],
        SynthOptions(platform="terrestrial", n_frames=frames, seed=seed, buildings=1, frame_interval_s=0.4),
    )
    images = {i: res.frames.load(i) for i in range(frames)}
    if default_errors:
        return run_scene(res, images, prior_poses(res.manifest, None), wall_points(), None)
    priors = noisy_priors(list(res.truth.poses), seed)
    return run_scene(res, images, priors, wall_points(), FACADE_ACCURACY, reject_calibration)


def drive(frames: int, seed: int, reject_calibration: bool) -> dict:
    """A drive around a procedural block with the default error model (module docstring)."""
    res = synthesize(
        procedural_block(6, seed=1),
        SynthOptions(platform="drive", n_frames=frames, seed=seed, buildings=2, errors=ErrorOptions()),
    )
    images = {i: res.frames.load(i) for i in range(frames)}
    pts = np.concatenate([edge_points(b) for b in res.buildings if b.id in res.truth.cluster])
    return run_scene(res, images, prior_poses(res.manifest, None), pts, None, reject_calibration)


def sequence_figures(frames: int, seed: int, quick: bool) -> dict:
    """Every scene of the module docstring (`quick`: the facade with 0.5 m / 1°, calibration
    accepted and rejected, and the drive)."""
    out: dict = {"facade": facade(frames, seed, default_errors=False)}
    out["facade_rejected"] = facade(frames, seed, default_errors=False, reject_calibration=True)
    out["drive"] = drive(24 if quick else frames, 1, reject_calibration=False)
    if not quick:
        out["facade_default_errors"] = facade(frames, seed, default_errors=True)
        out["drive_uncalibrated"] = drive(frames, 1, reject_calibration=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="the facade (0.5 m / 1°) and a 24-frame drive only")
    a = ap.parse_args()
    t0 = time.perf_counter()
    out = {"bench": "orientation_sequence", "frames": a.frames, "seed": a.seed, "quick": a.quick}
    out.update(sequence_figures(a.frames, a.seed, a.quick))
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

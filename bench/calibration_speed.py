"""Calibration speed and accuracy (issue 18's bar "calibration ≤ 5 s whatever the sequence length"):
the calibrate stage of `citytherm run` (`workers.job.scene_caster` + `workers.job.calibrate`, the
shipped path, as `workers.run.run_job` times it) on the synthetic drive and flight of
`bench/pipeline_speed.py` (NRW LoD2 tile, default GNSS/INS errors). Prints one JSON document.

Per sequence (each calibrated in a fresh process of this script, `--child`, after the ingest):
the stage's CPU seconds (`resource.getrusage`, this process, all threads) and wall seconds, the
calibration's result (`SequenceCalibration.to_dict`), and its accuracy against the synthetic
truth: the estimated mounting (`orientation.mounting.calibrated_mounting`) and time delay
against the true ones, and the position (m) / rotation (deg) error of the calibrated priors
against the true poses over every frame (RMS, 95th percentile; the priors' alongside).

Usage: `.venv/bin/python bench/calibration_speed.py [--frames 300] [--flight-frames 60]
[--skip drive,flight] [--repeat 1] [--keep DIR]`. Packages are written to `--keep` (reused
there when present). CPU seconds are the steady figure on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from pipeline_speed import NRW_TILE, scene, write  # noqa: E402

from db.synth_files import load_truth  # noqa: E402
from workers.pipeline.geometry.pose import Pose  # noqa: E402
from workers.pipeline.geometry.pose_increments import pose_delta  # noqa: E402


def _cpu_s() -> float:
    """CPU seconds (user + system) of this process so far, all threads."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _errors(truth: list[Pose], poses: list[Pose]) -> dict[str, float]:
    """Position (m) and rotation (deg) error of `poses` against `truth`: RMS and 95th percentile."""
    d = np.array([pose_delta(t, p) for t, p in zip(truth, poses, strict=True)])
    pos, rot = np.linalg.norm(d[:, 3:], axis=1), np.degrees(np.linalg.norm(d[:, :3], axis=1))
    return {"position_rms_m": round(float(np.sqrt(np.mean(pos**2))), 4),
            "position_p95_m": round(float(np.percentile(pos, 95)), 4),
            "rotation_rms_deg": round(float(np.sqrt(np.mean(rot**2))), 4),
            "rotation_p95_deg": round(float(np.percentile(rot, 95)), 4)}


def child(pkg: Path, truth_path: Path, repeat: int) -> dict:
    """Ingest `pkg`, then the calibrate stage `repeat` times (fresh caster each time): CPU and
    wall seconds of each, the result and its accuracy against the truth (of the last run)."""
    from workers.job import calibrate, ingest, scene_caster
    from workers.pipeline.orientation.mounting import calibrated_mounting, wrap_deg
    from workers.run_options import RunOptions

    options = RunOptions()
    ingested = ingest(NRW_TILE, pkg, options)
    cpu, wall = [], []
    for _ in range(repeat):
        c0, t0 = _cpu_s(), time.perf_counter()
        caster = scene_caster(ingested)
        calibrated = calibrate(ingested, options, caster)
        cpu.append(round(_cpu_s() - c0, 2))
        wall.append(round(time.perf_counter() - t0, 2))
    truth = load_truth(truth_path)
    cal = calibrated.calibration
    true_poses = [truth.poses[i] for i in ingested.frame_indices]
    out: dict = {"frames": len(ingested.frame_indices), "buildings": len(ingested.buildings),
                 "calibrate_cpu_s": cpu, "calibrate_wall_s": wall,
                 "calibration": cal.to_dict() if cal is not None else None,
                 "priors_error": _errors(true_poses, list(ingested.priors)),
                 "calibrated_error": _errors(true_poses, list(calibrated.priors))}
    if cal is not None and cal.accepted:
        est = calibrated_mounting(ingested.manifest.mounting, cal)
        tm = truth.true_mounting
        out["truth"] = {
            "boresight_error_deg": wrap_deg(np.asarray(est.boresight_deg) - tm.boresight_deg)
            .round(4).tolist(),
            "lever_arm_error_m": (np.asarray(est.lever_arm_m) - tm.lever_arm_m).round(4).tolist(),
            "time_delay_error_s": round(cal.time_delay_s - truth.time_delay_s, 5),
        }
    return out


def run(pkg: Path, truth_path: Path, repeat: int) -> dict:
    """`child` in a fresh process of this script."""
    cmd = [sys.executable, __file__, "--child", str(pkg), str(truth_path), str(repeat)]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="frames of the drive")
    ap.add_argument("--flight-frames", type=int, default=60)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=1, help="calibrations per sequence (one process)")
    ap.add_argument("--skip", default="", help="comma-separated parts to skip: drive, flight")
    ap.add_argument("--keep", type=Path, help="write (or reuse) the packages here")
    ap.add_argument("--child", nargs=3, metavar=("PKG", "TRUTH", "REPEAT"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        pkg, truth_path, repeat = a.child
        print(json.dumps(child(Path(pkg), Path(truth_path), int(repeat))))
        return
    skip = {x.strip() for x in a.skip.split(",") if x.strip()}
    out: dict = {"bench": "calibration_speed", "load_avg_before": [round(x, 2) for x in os.getloadavg()],
                 "options": {k: v for k, v in vars(a).items() if k not in ("child", "keep")}}
    root = a.keep or Path(tempfile.mkdtemp(prefix="citytherm-calibration-speed-"))
    root.mkdir(parents=True, exist_ok=True)
    try:
        for name, platform, n in (("drive", "drive", a.frames), ("flight", "flight", a.flight_frames)):
            if name in skip:
                continue
            pkg = root / f"{name}-{n}"
            truth_path = pkg.with_name(pkg.name + ".truth.json")
            if not ((pkg / "sequence.json").is_file() and truth_path.is_file()):
                write(scene(platform, n, a.seed), pkg)
            out[name] = run(pkg, truth_path, a.repeat)
            print(json.dumps({name: out[name]}), file=sys.stderr, flush=True)
    finally:
        if a.keep is None:
            import shutil

            shutil.rmtree(root, ignore_errors=True)
    out["load_avg_after"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

"""Bundle adjustment bench (issue 18 item 3, issue 19 item 2): the numpy solver on replayed blocks of a
real drive, before/after, and against Ceres.

Two steps, both printing JSON:

1. `capture`: the ingest, calibrate and orient stages of `citytherm run` (`workers.job`) on a
   sequence package (a drive along the real NRW LoD2 tile of `tests/data/`, `citytherm synth`
   defaults: default GNSS/INS errors; rendered here when `--package` is not given), every
   `bundle_adjust` call of the orient stage recorded (inputs, result, CPU and wall seconds) to a
   pickle. `--code DIR` runs another checkout's `workers` (e.g. `git archive HEAD` of the code
   before a change: the "before" figures are then the recorded ones). Prints the orient stage's
   CPU and wall seconds and the adjustments' share.
2. `replay PICKLE`: every recorded block adjusted again with this checkout's `bundle_adjust`
   (CPU seconds `time.process_time`, wall seconds), the pose differences to the recorded result
   (position mm, rotation degrees, largest over the frames; the largest difference of a pose
   parameter over its σ), the ratio of the frames' position and rotation σ (covariance) to the
   recorded ones, and whether both are within noise (5 % of σ); with `--ceres K` also Ceres
   (`bundle_ceres.bundle_adjust_ceres`) on the first K blocks with its differences to the numpy
   solver (Python cost functions: minutes per 120-frame block).

Usage:
    .venv/bin/python bench/bundle.py capture [--package DIR] [--frames 300] [--seed 1] [--code DIR] --out P
    .venv/bin/python bench/bundle.py replay P [--ceres 1]
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
NRW_TILE = ROOT / "tests" / "data" / "nrw-tile-5659-citygml1-lod2.gml"


def _code_path(code: str | None) -> None:
    """Import `workers` from `code` (another checkout) or from this repository."""
    sys.path.insert(0, str(Path(code).resolve()) if code else str(ROOT))


def capture(package: Path, out: Path) -> dict[str, Any]:
    """Run ingest, calibrate, orient on `package`, recording every `bundle_adjust` call to `out`."""
    import workers.pipeline.orientation.block as block_mod
    from workers import job
    from workers.run_options import RunOptions

    calls: list[dict[str, Any]] = []
    images: dict[int, np.ndarray] = {}
    original = block_mod.bundle_adjust

    def recorded(camera, frames, imgs, start, prior, frame_info, common_info, tracks, wireframe, raycaster,
                 *rest):  # type: ignore[no-untyped-def]
        c0, w0 = time.process_time(), time.perf_counter()
        res = original(camera, frames, imgs, start, prior, frame_info, common_info, tracks, wireframe,
                       raycaster, *rest)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        for f in frames:
            images.setdefault(f, np.asarray(imgs[f]))
        calls.append(dict(camera=camera, frames=list(frames), start={f: start[f] for f in frames},
                          prior={f: prior[f] for f in frames}, frame_info=dict(frame_info),
                          common_info=common_info, tracks=tracks, wireframe=wireframe, mesh=raycaster.mesh,
                          rest=rest, result=res, cpu_s=cpu, wall_s=wall))
        return res

    block_mod.bundle_adjust = recorded
    opts = RunOptions()
    ing = job.ingest(NRW_TILE, package, opts)
    caster = job.scene_caster(ing)
    cal = job.calibrate(ing, opts, caster)
    c0, w0 = time.process_time(), time.perf_counter()
    job.orient(ing, cal, opts, caster=caster)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    block_mod.bundle_adjust = original
    with open(out, "wb") as fh:
        pickle.dump(dict(calls=calls, images=images), fh)
    return {
        "frames": len(ing.frame_indices),
        "calibration_accepted": cal.accepted,
        "orient_cpu_s": round(cpu, 2),
        "orient_wall_s": round(wall, 2),
        "bundle_adjust_cpu_s": round(sum(c["cpu_s"] for c in calls), 2),
        "bundle_adjust_wall_s": round(sum(c["wall_s"] for c in calls), 2),
        "blocks": [{"frames": len(c["frames"]), "cpu_s": round(c["cpu_s"], 2),
                    "wall_s": round(c["wall_s"], 2)} for c in calls],
    }


def differences(frames: list[int], a: Any, b: Any) -> dict[str, float]:
    """Largest pose difference of two `BundleResult`s over `frames` (position mm, rotation degrees)
    and the range of their frames' σ ratios (b / a, position and rotation)."""
    from workers.pipeline.geometry.pose_increments import pose_delta

    d = np.array([pose_delta(a.poses[f], b.poses[f]) for f in frames])
    sd = np.sqrt(np.array([np.diag(a.covariance[f]) for f in frames]))
    ratios = np.array([np.sqrt(np.diag(b.covariance[f])) for f in frames]) / sd
    over = float(np.nanmax(np.abs(d) / sd))
    return {
        "max_position_mm": round(float(np.max(np.linalg.norm(d[:, 3:], axis=1))) * 1e3, 4),
        "max_rotation_deg": round(float(np.degrees(np.max(np.linalg.norm(d[:, :3], axis=1)))), 6),
        "max_difference_over_sigma": round(over, 4),
        "sigma_ratio_min": round(float(np.nanmin(ratios)), 4),
        "sigma_ratio_max": round(float(np.nanmax(ratios)), 4),
        "sigma0": [round(a.sigma0, 4), round(b.sigma0, 4)],
        # within noise: every pose parameter within 5 % of its σ, every σ within 5 %
        "within_noise": bool(over <= 0.05 and np.nanmax(np.abs(ratios - 1)) <= 0.05),
    }


def _times(cpu0: float, wall0: float) -> dict[str, float]:
    """CPU and wall seconds since `cpu0` (`time.process_time`) and `wall0` (`time.perf_counter`)."""
    return {"cpu_s": round(time.process_time() - cpu0, 2), "wall_s": round(time.perf_counter() - wall0, 2)}


def replay(path: Path, ceres_blocks: int) -> dict[str, Any]:
    """Adjust every recorded block again (numpy; Ceres on the first `ceres_blocks`)."""
    from workers.pipeline.geometry.raycast import RayCaster
    from workers.pipeline.orientation.bundle import bundle_adjust

    with open(path, "rb") as fh:
        data = pickle.load(fh)
    out = []
    for k, c in enumerate(data["calls"]):
        images = data["images"] if "images" in data else c["images"]
        args = (c["camera"], c["frames"], images, c["start"], c["prior"], c["frame_info"], c["common_info"],
                c["tracks"], c["wireframe"], RayCaster(c["mesh"]), *c["rest"])
        c0, w0 = time.process_time(), time.perf_counter()
        res = bundle_adjust(*args)
        row: dict[str, Any] = {
            "frames": len(c["frames"]),
            "tracks": len(c["tracks"].point),
            "observations": int(np.isin(c["tracks"].frame, c["frames"]).sum()),
            "recorded": {"cpu_s": round(c["cpu_s"], 2), "wall_s": round(c["wall_s"], 2)},
            "numpy": _times(c0, w0),
            "numpy_vs_recorded": differences(c["frames"], c["result"], res),
        }
        if k < ceres_blocks:
            from workers.pipeline.orientation.bundle_ceres import bundle_adjust_ceres

            c0, w0 = time.process_time(), time.perf_counter()
            cer = bundle_adjust_ceres(*args)
            row["ceres"] = _times(c0, w0)
            row["ceres_vs_numpy"] = differences(c["frames"], res, cer)
        out.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    return {
        "pickle": str(path),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "cpu_count": os.cpu_count(),
        "blocks": out,
        "recorded_cpu_s": round(sum(r["recorded"]["cpu_s"] for r in out), 2),
        "numpy_cpu_s": round(sum(r["numpy"]["cpu_s"] for r in out), 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    cap = sub.add_parser("capture")
    cap.add_argument("--package", type=Path, help="sequence package (else rendered: citytherm synth)")
    cap.add_argument("--frames", type=int, default=300)
    cap.add_argument("--seed", type=int, default=1)
    cap.add_argument("--code", help="import workers from this checkout (the code before a change)")
    cap.add_argument("--out", type=Path, required=True)
    rep = sub.add_parser("replay")
    rep.add_argument("pickle", type=Path)
    rep.add_argument("--ceres", type=int, default=0, help="also Ceres on the first N blocks")
    args = ap.parse_args()
    if args.cmd == "capture":
        _code_path(args.code)
        package = args.package
        if package is None:
            package = args.out.with_suffix(".package")
            subprocess.run([str(ROOT / ".venv" / "bin" / "citytherm"), "synth", "--model", str(NRW_TILE),
                            "--frames", str(args.frames), "--seed", str(args.seed), "-o", str(package)],
                           check=True, stdout=subprocess.DEVNULL)
        result = capture(package, args.out)
    else:
        _code_path(None)
        result = replay(args.pickle, args.ceres)
    result["load_avg_1min"] = round(os.getloadavg()[0], 2)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()

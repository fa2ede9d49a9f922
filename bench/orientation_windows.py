"""Window length of the sequence orientation against accuracy and cost (issue 14: shorter windows
let two workers orient a 100-frame drive at once; do they keep the accuracy?).

The scene is `bench/service.py`'s: a synthetic drive past the bundled Berlin LoD2 model
(`synthesize` with the default GNSS/INS error model, written as a package). `citytherm run`'s
stages (`workers.job`: ingest, calibrate once) and then, per window variant `W/O` (frames per
window / overlap), the orient stage with `SequenceOrientationOptions(window_frames=W,
overlap_frames=O)` (the same `orient_sequence` the stage calls, windows one after the other),
plan, every unit in this process and the results folder. Per variant: the windows (frames, CPU
seconds each), the frames whose pose reprojects the cluster buildings' edges within 1 px of the
true pose (`bench/orientation_sequence.py`'s figure), the (frame, building) pairs within 1 px
(`bench/pipeline_speed.py`), the texture figures against the truth
(`workers.synth_eval.texture_accuracy`), and the units' CPU seconds. CPU seconds are
`time.process_time` of this process (library threads capped to 1 as a service worker's).

Usage: `python bench/orientation_windows.py [--frames 100] [--buildings 8] [--seed 1]
[--variants 120/30 70/30 60/20]` prints JSON; about 2 minutes per variant on a quiet core.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--buildings", type=int, default=8)
    ap.add_argument("--interval", type=float, default=0.3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--variants", nargs="+", default=["120/30", "70/30", "60/20"])
    a = ap.parse_args()

    from workers.pool import THREADS_VAR, cap_library_threads

    os.environ[THREADS_VAR] = "1"
    cap_library_threads()

    from bench.pipeline_speed import pairs_below_1px
    from db.citygml.reader import read_model
    from db.synth_files import write_synthetic_package
    from services.api.schemas import TextureInputs
    from workers import job
    from workers.pipeline.orientation.quality import edge_points, reprojection_rms
    from workers.pipeline.orientation.sequence import SequenceOrientationOptions, orient_sequence
    from workers.pipeline.synth import BUNDLED_MODEL, SynthOptions, synthesize
    from workers.synth_eval import texture_accuracy

    root = Path(tempfile.mkdtemp(prefix="citytherm-bench-windows-"))
    _, blds = read_model(BUNDLED_MODEL)
    drive = SynthOptions(n_frames=a.frames, seed=a.seed, buildings=a.buildings, frame_interval_s=a.interval,
                         model_path=str(BUNDLED_MODEL))  # fmt: skip
    res = synthesize(blds, drive)
    pkg = write_synthetic_package(res, root / "seq")
    options = TextureInputs(model=1, sequence="00000000-0000-0000-0000-000000000000").run_options()
    ing = job.ingest(BUNDLED_MODEL, pkg, options)
    caster = job.scene_caster(ing)
    c0 = time.process_time()
    cal = job.calibrate(ing, options, caster)
    out: dict = {"frames": a.frames, "seed": a.seed, "calibrate_cpu_s": round(time.process_time() - c0, 2),
                 "calibration_accepted": cal.accepted, "variants": {}}  # fmt: skip
    pts = np.concatenate([edge_points(b) for b in res.buildings if b.id in res.truth.cluster])
    frames, cam = ing.frame_indices, res.manifest.camera

    for v in a.variants:
        w, o = (int(x) for x in v.split("/"))
        windows: list[dict] = []

        def timed(fn, tasks, windows=windows):  # a WindowMap that notes each window's CPU seconds
            for t in tasks:
                c = time.process_time()
                r = fn(t)
                cpu = round(time.process_time() - c, 2)
                windows.append({"frames": [t.frames[0], t.frames[-1]], "cpu_s": cpu})
                yield r

        c0 = time.process_time()
        so_opts = SequenceOrientationOptions(window_frames=w, overlap_frames=o, min_window_frames=w)
        so = orient_sequence(cam, caster, frames, ing.frames, dict(zip(frames, cal.priors, strict=True)),
                             dict(zip(frames, ing.times, strict=True)), cal.accuracy, so_opts,
                             map_windows=timed)  # fmt: skip
        orient_cpu = time.process_time() - c0
        truth = res.truth.poses
        e = np.array([reprojection_rms(cam, pts, so.poses[i], T, min_points=4) for i, T in enumerate(truth)])
        e = e[np.isfinite(e)]
        oriented = job.Oriented(so, {"run": True, **so.to_dict("calibrated" if cal.accepted else "manifest")})
        planned = job.plan(ing, cal, oriented, options)
        c0 = time.process_time()
        done = [job.run_unit(u) for u in planned.units]
        units_cpu = time.process_time() - c0
        results = [r for r in done if not isinstance(r, job.UnitFailure)]
        failures = [r for r in done if isinstance(r, job.UnitFailure)]
        folder = root / f"out-{w}-{o}"
        job.finish(folder, ing, cal, oriented, planned, results, failures, options, {})
        tex = texture_accuracy(folder, res)
        out["variants"][v] = {
            "windows": windows,
            "orient_cpu_s": round(orient_cpu, 2),
            "frames_below_1px": round(float(np.mean(e < 1.0)), 3),
            "frame_error_median_px": round(float(np.median(e)), 3),
            "frame_error_p90_px": round(float(np.percentile(e, 90)), 3),
            "pairs": pairs_below_1px(folder, res),
            "texture": {k: round(float(tex[k]), 3) for k in ("rmse_k", "misregistration_median_texel")},
            "units": len(planned.units),
            "units_failed": len(failures),
            "units_cpu_s": round(units_cpu, 2),
        }
        print(f"[orientation windows] {v}: {json.dumps(out['variants'][v])}", file=sys.stderr, flush=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

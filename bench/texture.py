"""Texture extraction bench: accuracy and speed of `citytherm run` on a synthetic drive.

A drive of ~200 frames around ~8 buildings of the bundled Berlin model, error-free poses (the
package's priors are the true poses), 10 texels/m. Prints JSON:
- accuracy: texture RMSE against the ground-truth field over observed texels (also near and away
  from sharp edges of the field), median misregistration (phase correlation of each surface's
  texture against the truth on the same grid, texels), coverage of the texels the frames can see;
- speed: texture-stage frames per second per worker process (decode + visibility + sampling +
  fusion, per building-frame pair), end-to-end wall time of `run_job` with 1 and 2 workers.

Usage: `python bench/texture.py [--frames 200] [--buildings 8] [--workers 1,2] [--out DIR]`.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from db.citygml.reader import read_model
from db.synth_files import write_synthetic_package
from workers.job import RunOptions
from workers.pipeline.synth import BUNDLED_MODEL, ErrorOptions, SynthOptions, synthesize
from workers.run import run_job
from workers.synth_eval import texture_accuracy


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--buildings", type=int, default=8)
    ap.add_argument("--resolution", type=float, default=10.0)
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    root = a.out or Path(tempfile.mkdtemp(prefix="citytherm-bench-texture-"))
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    res = synthesize(
        read_model(BUNDLED_MODEL)[1],
        SynthOptions(
            n_frames=a.frames,
            seed=a.seed,
            buildings=a.buildings,
            errors=ErrorOptions(enabled=False),
            model_path=str(BUNDLED_MODEL),
        ),
    )
    pkg = write_synthetic_package(res, root / "seq")
    t_synth = time.perf_counter() - t0
    out: dict = {
        "bench": "texture",
        "frames": a.frames,
        "cluster_buildings": len(res.truth.cluster),
        "scene_buildings": len(res.buildings),
        "resolution_px_per_m": a.resolution,
        "camera": [res.manifest.camera.width, res.manifest.camera.height],
        "synth_s": round(t_synth, 1),
        "runs": {},
    }
    first: Path | None = None
    for w in [int(x) for x in a.workers.split(",")]:
        dest = root / f"run_w{w}"
        shutil.rmtree(dest, ignore_errors=True)
        t1 = time.perf_counter()
        c1 = os.times()
        summary = run_job(
            BUNDLED_MODEL,
            pkg,
            dest,
            RunOptions.build(resolution_px_per_m=a.resolution, workers=w, refine=False, display=False),
        )
        wall = time.perf_counter() - t1
        c2 = os.times()
        cpu = (c2.user - c1.user) + (c2.system - c1.system)  # this process (pool workers not counted)
        rep = json.loads((dest / "report.json").read_text())
        st = rep["unit_stage_timings_s"]
        pairs = sum(summary.units_frames.values())
        tex_s = st.get("decode", 0.0) + st.get("texture", 0.0)
        out["runs"][f"workers_{w}"] = {
            "wall_s": round(wall, 2),
            "cpu_s_main_process": round(cpu, 2),
            "load_average_1min": round(os.getloadavg()[0], 2),
            "stage_s": {k: round(v, 2) for k, v in summary.timings_s.items()},
            "buildings_processed": len(summary.results),
            "building_frame_pairs": pairs,
            "texture_stage_s": round(tex_s, 2),
            "texture_frames_per_s_per_process": round(pairs / tex_s, 1) if tex_s else None,
            "unit_stage_s": {k: round(v, 2) for k, v in st.items()},
        }
        first = first or dest
    runs = out["runs"]
    if "workers_1" in runs and "workers_2" in runs:
        out["speedup_2_workers"] = round(runs["workers_1"]["wall_s"] / runs["workers_2"]["wall_s"], 2)
    if first is not None:
        acc = texture_accuracy(first, res)
        out["accuracy"] = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in acc.items()}
        out["bars"] = {
            "rmse_k<=0.35": acc["rmse_k"] <= 0.35,
            "misregistration<=0.3": acc["misregistration_median_texel"] <= 0.3,
            "coverage>=0.95": acc["coverage"] >= 0.95,
            "fps>=20 (1 process)": (runs.get("workers_1", {}).get("texture_frames_per_s_per_process") or 0)
            >= 20,
        }
    out["results"] = str(root)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

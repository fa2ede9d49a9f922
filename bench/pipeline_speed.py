"""Pipeline speed (issue 18's bars): `citytherm run` (`workers.run.run_job`, the shipped path) on
synthetic drives and a flight over the real NRW LoD2 tile (`tests/data/`), default GNSS/INS
errors, refinement on. Prints one JSON document.

Runs (each in a fresh process of this script, `--child`, so that peak RSS and CPU are its own;
the CPU seconds and peak RSS of the run's process and every pool process it starts are sampled
with psutil every `--sample-s` s; per-stage CPU seconds are the CPU used between the stages'
starts, pool start-up included):

1. `drive`: a `--frames` (300) frame drive at the default 640 × 512 px around 5 buildings:
   end-to-end frames/s (bar ≥ 10 on 2 cores, `--workers 2`), per-stage wall and CPU seconds,
   calibration seconds (bar ≤ 5 s), the texture stage's frames/s per process (building-frames /
   `report.json` `unit_stage_timings_s.texture`, bar ≥ 100), and accuracy against the synthetic
   truth: the share of (frame, building) pairs of `orientation.json` whose pose reprojects the
   building's vertices within 1 px of the true pose, and the texture RMSE (`workers.synth_eval`).
2. `cost`: cost per frame at `--cost-frames` (300 and 3,000) frames at low resolution
   (`--low-res` 96 × 80; later laps of the loop reuse the first lap's images at their own times
   and poses, as `bench/long_drive.py` does): CPU ms per frame, the ratio long/short (bar: within
   ± 20 %), peak RSS.
3. `flight`: a `--flight-frames` (60) frame flight over the tile (default errors): frames/s end to
   end (bar ≥ 1) and the same accuracy figures.

Usage: `.venv/bin/python bench/pipeline_speed.py [--frames 300] [--cost-frames 300,3000]
[--flight-frames 60] [--workers 2] [--quick] [--skip drive,cost,flight] [--keep DIR]`;
`--quick` is 60 frames, cost at 100 and 400, a 20-frame flight. The machine's load averages
are recorded: wall figures on a shared machine are upper bounds, CPU seconds the steadier figure.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import psutil

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from db.citygml.reader import read_model  # noqa: E402
from db.synth_files import write_synthetic_package  # noqa: E402
from workers.pipeline.geometry.pose import Pose  # noqa: E402
from workers.pipeline.orientation.quality import reprojection_rms  # noqa: E402
from workers.pipeline.synth import SynthOptions, synthesize  # noqa: E402
from workers.pipeline.synth.render import default_camera  # noqa: E402
from workers.pipeline.synth.scene import SynthResult  # noqa: E402

NRW_TILE = REPO / "tests" / "data" / "nrw-tile-5659-citygml1-lod2.gml"
MB = 1024.0**2
BARS = {"frames_per_s": 10.0, "cost_ratio": 0.2, "flight_frames_per_s": 1.0, "texture_fps": 100.0}
BARS["calibrate_s"] = 5.0


# -- the scenes --------------------------------------------------------------------------------
def scene(
    platform: str, frames: int, seed: int, width: int | None = None, height: int | None = None
) -> SynthResult:
    """A synthetic sequence over the NRW tile with the default error model."""
    _, buildings = read_model(NRW_TILE)
    camera = default_camera(width, height) if width and height else None
    opts = SynthOptions(
        platform=platform,  # type: ignore[arg-type]
        n_frames=frames,
        seed=seed,
        camera=camera,
        model_path=str(NRW_TILE),
    )
    return synthesize(buildings, opts)


def write(res: SynthResult, out: Path, unique: int | None = None) -> tuple[Path, float]:
    """Write the package (`unique`: render only the first lap, `long_drive.looped_frames`);
    returns it and the seconds it took (0: a package written before in `--keep` is reused)."""
    if (out / "sequence.json").is_file() and len(list((out / "frames").iterdir())) == len(res.truth.poses):
        return out, 0.0
    t0 = time.perf_counter()
    frames = None
    if unique is not None:
        from long_drive import lap_frames, looped_frames

        frames = looped_frames(res, lap_frames(res, min(unique, len(res.truth.poses))))
    pkg = write_synthetic_package(res, out, out.with_name(out.name + ".truth.json"), frames=frames)
    return pkg, time.perf_counter() - t0


# -- one run, in a child process -----------------------------------------------------------------
class Sampler:
    """CPU seconds and RSS of this process and its descendants, sampled (psutil)."""

    def __init__(self, period_s: float) -> None:
        self.me = psutil.Process()
        self.cpu: dict[int, float] = {}
        self.rss: dict[int, int] = {}
        self.period_s = period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def sample(self) -> float:
        """Sample now; total CPU seconds seen so far (exited processes at their last sample)."""
        for p in [self.me, *self.me.children(recursive=True)]:
            try:
                with p.oneshot():
                    t, rss = p.cpu_times(), p.memory_info().rss
            except psutil.Error:
                continue
            self.cpu[p.pid] = max(self.cpu.get(p.pid, 0.0), t.user + t.system)
            self.rss[p.pid] = max(self.rss.get(p.pid, 0), rss)
        return sum(self.cpu.values())

    def _loop(self) -> None:
        while not self._stop.wait(self.period_s):
            self.sample()

    def __enter__(self) -> Sampler:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()
        self._thread.join()
        self.sample()


def child(pkg: Path, out: Path, workers: int, sample_s: float) -> dict:
    """`run_job` on `pkg` with refinement (default options, `workers` processes): timings."""
    from workers.run import run_job
    from workers.run_options import RunOptions

    marks: list[tuple[str, float, float]] = []
    with Sampler(sample_s) as sampler:

        def progress(stage: str, done: int, total: int) -> None:
            if not marks or marks[-1][0] != stage:
                marks.append((stage, time.perf_counter(), sampler.sample()))

        t0, c0 = time.perf_counter(), sampler.sample()
        summary = run_job(NRW_TILE, pkg, out, RunOptions(workers=workers), progress)
        t1, c1 = time.perf_counter(), sampler.sample()
    ends = [*marks[1:], ("end", t1, c1)]
    stage_cpu = {m[0]: round(e[2] - m[2], 2) for m, e in zip(marks, ends, strict=True)}
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    frames = summary.n_frames
    unit_s = report.get("unit_stage_timings_s", {})
    building_frames = sum(summary.units_frames.values())
    texture_s = float(unit_s.get("texture", 0.0))
    me = psutil.Process().pid
    others = [v for k, v in sampler.rss.items() if k != me]
    return {
        "frames": frames,
        "workers": workers,
        "wall_s": round(t1 - t0, 2),
        "cpu_s": round(c1 - c0, 2),
        "frames_per_s": round(frames / (t1 - t0), 2),
        "frames_per_cpu_s": round(frames / max(c1 - c0, 1e-9), 2),
        "cpu_ms_per_frame": round(1000 * (c1 - c0) / frames, 2),
        "stage_wall_s": {k: round(v, 2) for k, v in summary.timings_s.items()},
        "stage_cpu_s": stage_cpu,
        "calibrate_s": round(summary.timings_s.get("calibrate", 0.0), 2),
        "units": len(summary.units_frames),
        "building_frames": building_frames,
        "unit_stage_timings_s": {k: round(float(v), 2) for k, v in unit_s.items()},
        "texture_building_frames_per_s": round(building_frames / texture_s, 1) if texture_s else None,
        "orientation_blocks": len((summary.orientation or {}).get("blocks", [])),
        "peak_rss_parent_mb": round(sampler.rss.get(me, 0) / MB, 1),
        "peak_rss_largest_other_mb": round(max(others, default=0) / MB, 1),
        "processes_seen": len(sampler.rss),
    }


def run(pkg: Path, out: Path, workers: int, sample_s: float) -> dict:
    """`child` in a fresh process of this script."""
    cmd = [sys.executable, __file__, "--child", str(pkg), str(out), str(workers), str(sample_s)]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


# -- accuracy ------------------------------------------------------------------------------------
def _vertices(building: Any) -> np.ndarray:
    """`(N, 3)` distinct polygon vertices of a building and its parts (model CRS)."""
    rings = [p.exterior.coords for part in building.iter_buildings() for p in part.polygons]
    return np.unique(np.concatenate(rings), axis=0)


def pairs_below_1px(out: Path, res: SynthResult) -> dict:
    """Share of the (frame, building) entries of `orientation.json` (refined, or the prior kept)
    whose pose reprojects the building's vertices within 1 px of the true pose. The run reads the
    whole tile, so an entry may name a building the scene did not render (seed 3): its vertices
    come from the tile (`outside_scene` counts those entries)."""
    doc = json.loads((out / "orientation.json").read_text(encoding="utf-8"))
    vertices = {b.id: _vertices(b) for b in res.buildings}
    entries = [r["building"] for f in doc["frames"] for r in f["refined"]]
    missing = set(entries) - vertices.keys()
    if missing:
        _, tile = read_model(NRW_TILE)
        vertices |= {b.id: _vertices(b) for b in tile if b.id in missing}
    outside = sum(b in missing for b in entries)
    cam, errors, refined = res.manifest.camera, [], []
    for f in doc["frames"]:
        truth = res.truth.poses[f["index"]]
        for r in f["refined"]:
            pose = Pose(np.array(r["rotation"], float), np.array(r["center"], float))
            e = reprojection_rms(cam, vertices[r["building"]], pose, truth, min_points=4)
            if np.isfinite(e):
                errors.append(e)
                refined.append(r["status"] == "refined")
    e, ok = np.array(errors), np.array(refined, bool)
    return {
        "pairs": len(e),
        "share_below_1px": round(float(np.mean(e < 1.0)), 3) if len(e) else None,
        "refined_share": round(float(np.mean(ok)), 3) if len(e) else None,
        "median_px": round(float(np.median(e)), 3) if len(e) else None,
        "outside_scene": outside,
    }


def accuracy(out: Path, res: SynthResult) -> dict:
    """Pairs within 1 px and texture figures (`workers.synth_eval.texture_accuracy`)."""
    from workers.synth_eval import texture_accuracy

    tex = texture_accuracy(out, res)
    return {"pairs": pairs_below_1px(out, res), "texture": {k: tex[k] for k in sorted(tex)}}


# -- the bench -------------------------------------------------------------------------------------
def drive(root: Path, a: argparse.Namespace) -> dict:
    res = scene("drive", a.frames, a.seed)
    pkg, gen_s = write(res, root / "drive")
    out = root / "drive-out"
    fig = run(pkg, out, a.workers, a.sample_s)
    return {"generate_s": round(gen_s, 1), **fig, "accuracy": accuracy(out, res)}


def cost(root: Path, a: argparse.Namespace) -> dict:
    runs = []
    for n in a.cost_frames:
        res = scene("drive", n, a.seed, *a.low_res)
        pkg, gen_s = write(res, root / f"cost-{n}", unique=a.unique)
        fig = run(pkg, root / f"cost-{n}-out", a.workers, a.sample_s)
        runs.append({"generate_s": round(gen_s, 1), **fig})
    first, last = runs[0]["cpu_ms_per_frame"], runs[-1]["cpu_ms_per_frame"]
    return {
        "resolution": f"{a.low_res[0]}x{a.low_res[1]}",
        "runs": runs,
        "cpu_ms_per_frame_ratio": round(last / first, 3),
        "wall_ms_per_frame": [round(1000 * r["wall_s"] / r["frames"], 2) for r in runs],
    }


def flight(root: Path, a: argparse.Namespace) -> dict:
    res = scene("flight", a.flight_frames, a.seed)
    pkg, gen_s = write(res, root / "flight")
    out = root / "flight-out"
    fig = run(pkg, out, a.workers, a.sample_s)
    return {"generate_s": round(gen_s, 1), "buildings_in_scene": len(res.buildings), **fig,
            "accuracy": accuracy(out, res)}  # fmt: skip


def bars(out: dict) -> dict:
    """The issue's bars on what ran."""
    b: dict[str, Any] = {}
    if "drive" in out:
        d = out["drive"]
        b["end_to_end_frames_per_s>=10"] = d["frames_per_s"] >= BARS["frames_per_s"]
        b["calibrate_s<=5"] = d["calibrate_s"] <= BARS["calibrate_s"]
        tex = d["texture_building_frames_per_s"]
        b["texture_frames_per_s_per_process>=100"] = tex is not None and tex >= BARS["texture_fps"]
    if "cost" in out:
        b["cost_per_frame_flat_20pc"] = abs(out["cost"]["cpu_ms_per_frame_ratio"] - 1.0) <= BARS["cost_ratio"]
    if "flight" in out:
        b["flight_frames_per_s>=1"] = out["flight"]["frames_per_s"] >= BARS["flight_frames_per_s"]
    return b


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="frames of the drive")
    ap.add_argument("--cost-frames", default="300,3000", help="frame counts of the cost-per-frame runs")
    ap.add_argument("--flight-frames", type=int, default=60)
    ap.add_argument("--low-res", default="96x80", help="resolution of the cost runs")
    ap.add_argument("--unique", type=int, default=1000, help="cost runs: at most this many frames rendered")
    ap.add_argument("--workers", type=int, default=2, help="citytherm run --workers")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--sample-s", type=float, default=0.1)
    ap.add_argument("--skip", default="", help="comma-separated parts to skip: drive, cost, flight")
    ap.add_argument("--quick", action="store_true", help="60-frame drive, cost at 100, 400; 20-frame flight")
    ap.add_argument("--keep", type=Path, help="keep packages and results here")
    ap.add_argument("--child", nargs=4, metavar=("PKG", "OUT", "WORKERS", "SAMPLE_S"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        pkg, out, workers, sample_s = a.child
        print(json.dumps(child(Path(pkg), Path(out), int(workers), float(sample_s))))
        return
    if a.quick:
        a.frames, a.cost_frames, a.flight_frames = 60, "100,400", 20
    a.cost_frames = [int(x) for x in a.cost_frames.split(",") if x]
    a.low_res = [int(x) for x in a.low_res.lower().split("x")]
    skip = {x.strip() for x in a.skip.split(",") if x.strip()}
    out: dict[str, Any] = {
        "bench": "pipeline_speed",
        "machine": {"cpu_count": os.cpu_count(), "load_avg_before": [round(x, 2) for x in os.getloadavg()]},
        "options": {k: v for k, v in vars(a).items() if k not in ("child", "keep")},
    }
    root = a.keep or Path(tempfile.mkdtemp(prefix="citytherm-pipeline-speed-"))
    root.mkdir(parents=True, exist_ok=True)
    try:
        for name, part in (("drive", drive), ("cost", cost), ("flight", flight)):
            if name not in skip:
                print(f"[pipeline_speed {time.strftime('%H:%M:%S')}] {name}", file=sys.stderr, flush=True)
                out[name] = part(root, a)
                print(json.dumps({name: out[name]}), file=sys.stderr, flush=True)  # long runs: as they end
    finally:
        if a.keep is None:
            import shutil

            shutil.rmtree(root, ignore_errors=True)
    out["machine"]["load_avg_after"] = [round(x, 2) for x in os.getloadavg()]
    out["bars"] = bars(out)
    print(json.dumps(out, indent=1, default=str))


if __name__ == "__main__":
    main()

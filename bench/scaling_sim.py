"""A city-scale drive on 1, 4 and 16 worker machines (issue 18 item 6): the real stages on a
sample, the rest by measured cost. Prints one JSON document.

1. **Sample** (`measure`): a `--frames` (300) frame synthetic drive over the real NRW LoD2 tile
   (`tests/data/`, default GNSS/INS errors, as `bench/pipeline_speed.py` makes it) runs through
   the shipped job stages of `workers/job.py` one after the other in this process with one
   library thread (what a Celery worker process gets when each core runs one worker): ingest,
   calibrate, orient (its windows through a timing `map_windows`: the CPU seconds of every
   window task), plan, every building unit (`run_unit`), finish. Each stage's and each task's
   CPU seconds (`time.process_time`; on one thread the same as its seconds on a free core).
2. **Simulated run** (`simulate`): the job as the service runs it (`docs/scaling.md`): prepare
   (ingest + calibrate) in one task, then the orientation windows as tasks on every worker
   process, then merge + plan in the prepare task, then one task per building unit (queued
   costliest first, `workers.service_job.dispatch_order`), then finish. Tasks go to whichever
   worker process is free first (prefetch 1), each costing its measured CPU seconds times
   `1 + --service-overhead` (the service's measured overhead over `citytherm run`, 6.5 % in
   `bench/service.py`). A drive of `--hours` (1) at 10 frames/s is the sample repeated along the
   city (each 300-frame stretch sees its own buildings): its windows are those the shipped
   planner (`orientation.sequence.windows`) cuts from 36,000 time stamps, each costing the
   sample's CPU seconds per window frame; its units the sample's, repeated; ingest, merge + plan
   and finish scale with the frames; the calibration is bounded (measured once). The
   projection for 1, 4 and 16 machines of `--cores` (2) cores, one worker process per core:
   the simulated makespan, beside the arithmetic one (serial stages + parallel CPU seconds /
   workers) that `docs/scaling.md` gave before.
3. **Check** (`--check`, default on): the simulation of the sample itself on one machine
   against the same sample run for real by `citytherm run --workers 2` (`workers.run.run_job`,
   in a fresh process): the simulated and the measured wall seconds and their ratio. A real
   2-process run on a loaded machine is slower than its CPU seconds say: the load is recorded,
   and the real run's CPU seconds against the sample's (`cpu_ratio_real_to_sample`: pool
   start-up, imports and library threads the one-thread sample does not pay).

Usage: `.venv/bin/python bench/scaling_sim.py [--frames 300] [--hours 1] [--machines 1,4,16]
[--cores 2] [--no-check] [--keep DIR]`.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_v] = "1"  # one library thread, as a worker process per core has (before numpy loads)

import argparse  # noqa: E402
import heapq  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Iterable, Iterator  # noqa: E402
from dataclasses import asdict, dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from pipeline_speed import NRW_TILE, scene, write  # noqa: E402

FRAME_RATE_HZ = 10.0


@dataclass
class Sample:
    """CPU seconds of the real stages on the sample (one library thread).

    Attributes:
        frames: frames of the sample drive.
        ingest_s, calibrate_s, plan_s, finish_s: the serial stages' CPU seconds.
        orient_serial_s: the orient stage's CPU seconds outside its window tasks (planning the
            windows, the scene wireframe, merging).
        windows: `(frames, cpu_s)` per window task.
        units: `(building-frames, cpu_s)` per building unit.
        buildings: buildings in the units.
    """

    frames: int
    ingest_s: float = 0.0
    calibrate_s: float = 0.0
    orient_serial_s: float = 0.0
    plan_s: float = 0.0
    finish_s: float = 0.0
    windows: list[tuple[int, float]] = field(default_factory=list)
    units: list[tuple[int, float]] = field(default_factory=list)
    buildings: int = 0


def measure(pkg: Path, out: Path) -> Sample:
    """Run the shipped job stages (`workers/job.py`) on the package `pkg` one after the other in
    this process; CPU seconds per stage, per window task and per unit (`Sample`)."""
    from db.sequence_package import open_package
    from workers.job import (
        UnitFailure,
        calibrate,
        finish,
        ingest,
        orient,
        plan,
        run_unit,
        scene_caster,
    )
    from workers.run_options import RunOptions

    options = RunOptions(workers=1)
    clock = time.process_time
    windows: list[tuple[int, float]] = []

    def timed_map(fn: Callable[[Any], Any], items: Iterable[Any]) -> Iterator[Any]:
        for task in items:
            c0 = clock()
            result = fn(task)
            windows.append((len(task.frames), clock() - c0))
            yield result

    with open_package(pkg) as p:
        c0 = clock()
        ingested = ingest(NRW_TILE, p.root, options)
        sample = Sample(frames=len(ingested.manifest.frames), ingest_s=clock() - c0)
        c0 = clock()
        caster = scene_caster(ingested)
        calibrated = calibrate(ingested, options, caster)
        sample.calibrate_s = clock() - c0
        c0 = clock()
        oriented = orient(ingested, calibrated, options, caster=caster, map_windows=timed_map)
        sample.orient_serial_s = clock() - c0 - sum(w[1] for w in windows)
        sample.windows = windows
        c0 = clock()
        planned = plan(ingested, calibrated, oriented, options)
        sample.plan_s = clock() - c0
        results, failures = [], []
        for unit in planned.units:
            c0 = clock()
            r = run_unit(unit)
            sample.units.append((len(unit.frames), clock() - c0))
            (failures if isinstance(r, UnitFailure) else results).append(r)
        sample.buildings = len(planned.units)
        c0 = clock()
        out.mkdir(parents=True, exist_ok=True)
        finish(out, ingested, calibrated, oriented, planned, results, failures, options, {})
        sample.finish_s = clock() - c0
    return sample


def makespan(ready_at: float, slots: list[float], costs: list[float]) -> tuple[float, list[float]]:
    """List scheduling: tasks of `costs` seconds, in the given order, each to the worker process
    free first (none before `ready_at`); the time the last ends and the processes' free times."""
    heap = [max(s, ready_at) for s in slots]
    heapq.heapify(heap)
    end = ready_at
    for c in costs:
        t = heapq.heappop(heap) + c
        end = max(end, t)
        heapq.heappush(heap, t)
    return end, sorted(heap)


def simulate(sample: Sample, frames: int, workers: int, overhead: float) -> dict[str, float]:
    """The service's run of a drive of `frames` frames built from `sample` (module docstring) on
    `workers` worker processes, one core each: wall seconds per phase and in all, and the
    arithmetic projection (serial + parallel CPU seconds / workers)."""
    from workers.pipeline.orientation.sequence import windows as cut_windows
    from workers.pipeline.orientation.sequence_windows import SequenceOrientationOptions

    scale = frames / sample.frames
    k = 1.0 + overhead
    per_window_frame = sum(c for _, c in sample.windows) / max(sum(n for n, _ in sample.windows), 1)
    cut = cut_windows(np.arange(frames) / FRAME_RATE_HZ, SequenceOrientationOptions())
    window_costs = [k * per_window_frame * (b - a) for a, b in cut]
    reps = max(round(scale), 1)
    unit_costs = sorted((k * c for _ in range(reps) for _, c in sample.units), reverse=True)

    prepare = k * (sample.ingest_s * scale + sample.calibrate_s)
    slots = [0.0] * workers
    t_windows, slots = makespan(prepare, slots, window_costs)
    t_plan = t_windows + k * (sample.orient_serial_s + sample.plan_s) * scale  # in the prepare task
    t_units, _ = makespan(t_plan, [t_plan] * workers, unit_costs)
    total = t_units + k * sample.finish_s * scale
    serial = prepare + k * (sample.orient_serial_s + sample.plan_s + sample.finish_s) * scale
    arithmetic = serial + (sum(window_costs) + sum(unit_costs)) / workers
    return {
        "workers": workers,
        "windows": len(window_costs),
        "units": len(unit_costs),
        "prepare_s": round(prepare, 1),
        "windows_end_s": round(t_windows, 1),
        "units_start_s": round(t_plan, 1),
        "units_end_s": round(t_units, 1),
        "wall_s": round(total, 1),
        "wall_h": round(total / 3600.0, 3),
        "arithmetic_s": round(arithmetic, 1),
        "cpu_s": round(serial + sum(window_costs) + sum(unit_costs), 1),
        "efficiency": round((serial + sum(window_costs) + sum(unit_costs)) / (total * workers), 3),
    }


def real_run(pkg: Path, out: Path, workers: int) -> dict[str, Any]:
    """`citytherm run --workers N` on the sample in a fresh process (`bench/pipeline_speed.py
    --child`): its wall and CPU seconds and stage wall times."""
    cmd = [sys.executable, str(REPO / "bench" / "pipeline_speed.py"), "--child", str(pkg), str(out),
           str(workers), "0.2"]  # fmt: skip
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    done = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr[-3000:]}")
    fig = json.loads(done.stdout.strip().splitlines()[-1])
    return {k: fig[k] for k in ("wall_s", "cpu_s", "stage_wall_s", "units")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="frames of the sample drive")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--hours", type=float, default=1.0, help="hours of drive to project (10 frames/s)")
    ap.add_argument("--machines", default="1,4,16")
    ap.add_argument("--cores", type=int, default=2, help="cores (worker processes) per machine")
    ap.add_argument("--service-overhead", type=float, default=0.065,
                    help="the service's overhead over citytherm run (bench/service.py)")
    ap.add_argument("--no-check", action="store_true", help="skip the real 2-process run of the sample")
    ap.add_argument("--keep", type=Path, default=None, help="keep the package and results here")
    args = ap.parse_args()

    tmp = None
    root = args.keep
    if root is None:
        tmp = tempfile.TemporaryDirectory(prefix="ct-scaling-")
        root = Path(tmp.name)
    root.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    pkg, _ = write(scene("drive", args.frames, args.seed), root / "drive")
    sample = measure(pkg, root / "sample-out")
    frames = round(args.hours * 3600 * FRAME_RATE_HZ)
    doc: dict[str, Any] = {
        "bench": "scaling_sim",
        "machine": {"cpu_count": os.cpu_count(), "load_avg_before": [round(x, 2) for x in load_before]},
        "options": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "sample": {
            **{k: (round(v, 2) if isinstance(v, float) else v) for k, v in asdict(sample).items()
               if k not in ("windows", "units")},
            "windows": [(n, round(c, 2)) for n, c in sample.windows],
            "units": len(sample.units),
            "unit_cpu_s": round(sum(c for _, c in sample.units), 2),
            "unit_cpu_s_max": round(max((c for _, c in sample.units), default=0.0), 2),
            "cpu_s": round(sample.ingest_s + sample.calibrate_s + sample.orient_serial_s + sample.plan_s
                           + sample.finish_s + sum(c for _, c in sample.windows)
                           + sum(c for _, c in sample.units), 2),
        },
        "projection": {
            "frames": frames,
            "machines": {m: simulate(sample, frames, int(m) * args.cores, args.service_overhead)
                         for m in args.machines.split(",")},
        },
    }
    if not args.no_check:
        sim = simulate(sample, sample.frames, args.cores, 0.0)
        real = real_run(pkg, root / "real-out", args.cores)
        doc["check"] = {
            "simulated": sim,
            "citytherm_run": real,
            "ratio_real_to_simulated": round(real["wall_s"] / sim["wall_s"], 3),
            "cpu_ratio_real_to_sample": round(real["cpu_s"] / sim["cpu_s"], 3),
        }
    doc["machine"]["load_avg_after"] = [round(x, 2) for x in os.getloadavg()]
    print(json.dumps(doc, indent=1))
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()

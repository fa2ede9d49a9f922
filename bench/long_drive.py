"""Memory and cost per frame of `citytherm run` against sequence length (issue 18, item 5).

Generates a long synthetic drive at low resolution (default 96 × 80 px, the default camera's
45° field of view) looping around a cluster of the real NRW LoD2 tile (`tests/data/`,
default GNSS/INS errors), then runs `citytherm run` on it as a subprocess and samples, every
`--sample-s` seconds, the resident set size of every process of the run (the CLI process, the
forkserver and the pool workers: `psutil`). Prints JSON per run: frames, refinement, peak RSS of
the parent and of the largest other process (MB), wall and CPU seconds (parent and all pool
workers: `RUSAGE_CHILDREN` difference or the sampled CPU times, the larger), both per frame,
and the stage wall times of the run's `report.json`. Bar: RSS < 2 GB per process and flat (not
growing with the frame count).

Frames: the generator is lazy (`SynthFrames` renders on indexing) and `write_package` streams
its iterable, so the package is written frame by frame and never held. Rendering costs ~30 ms
per frame even at 96 × 80 (ray casting), so only the first lap (`lap_frames`, at most
`--unique`) is rendered and later laps reuse the image of the same lap position: every frame
keeps its own time stamp and recorded (erroneous) INS pose, and with refinement off the units
project and sample every frame at its own pose, so the work per frame is that of a rendered
drive (the image content is a near copy; the accuracy of such long runs is not measured here).

Usage: `.venv/bin/python bench/long_drive.py [--frames 1000,4000] [--refine-frames 1000]
[--workers 2] [--keep DIR]`.
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
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from db.citygml.reader import read_model
from db.synth_files import write_synthetic_package
from workers.pipeline.synth import SynthOptions, synthesize
from workers.pipeline.synth.render import default_camera
from workers.pipeline.synth.scene import SynthResult

REPO = Path(__file__).resolve().parents[1]
NRW_TILE = REPO / "tests" / "data" / "nrw-tile-5659-citygml1-lod2.gml"
VENV_BIN = Path(sys.executable).parent
MB = 1024.0**2


def lap_frames(result: SynthResult, limit: int) -> int:
    """Frames per lap of the drive loop: the first local minimum (< 2 m) of the distance of the
    true projection centre to that of frame 0, after frame 20; `limit` when none is found first."""
    centres = np.array([p.center for p in result.truth.poses[: limit + 1]])
    d = np.linalg.norm(centres - centres[0], axis=1)
    for j in range(21, len(d) - 1):
        if d[j] < 2.0 and d[j] <= d[j - 1] and d[j] <= d[j + 1]:
            return j
    return min(limit, len(d))


def looped_frames(result: SynthResult, lap: int) -> Iterator[np.ndarray]:
    """The frames in order: the first `lap` rendered, later ones the image of frame `i mod lap`
    (held: `lap` uint16 images, a few MB at low resolution)."""
    held: list[np.ndarray] = []
    for i in range(len(result.frames)):
        if i < lap:
            held.append(result.frames[i].copy())
        yield held[i % lap]


def build_package(out: Path, n_frames: int, seed: int, width: int, height: int, unique: int) -> dict:
    """Write a `n_frames` drive around 5 buildings of the NRW tile to `out`; returns its figures."""
    _, buildings = read_model(NRW_TILE)
    t0 = time.perf_counter()
    opts = SynthOptions(
        platform="drive",
        n_frames=n_frames,
        seed=seed,
        buildings=5,
        camera=default_camera(width, height),
        model_path=str(NRW_TILE),
    )
    result = synthesize(buildings, opts)
    lap = lap_frames(result, min(unique, n_frames))
    write_synthetic_package(
        result, out, out.with_name(out.name + ".truth.json"), frames=looped_frames(result, lap)
    )
    return {
        "frames": n_frames,
        "rendered_frames": min(lap, n_frames),
        "resolution": f"{width}x{height}",
        "generate_s": round(time.perf_counter() - t0, 1),
    }


def tree_usage(root: psutil.Process) -> dict[int, tuple[int, float]]:
    """RSS (bytes) and CPU seconds (user + system) of `root` and all its descendants, by pid
    (processes that vanish are skipped)."""
    out: dict[int, tuple[int, float]] = {}
    try:
        procs = [root, *root.children(recursive=True)]
    except psutil.Error:
        return out
    for p in procs:
        try:
            with p.oneshot():
                t = p.cpu_times()
                out[p.pid] = (p.memory_info().rss, t.user + t.system)
        except psutil.Error:
            pass
    return out


def run_job(pkg: Path, out: Path, workers: int, refine: bool, sample_s: float) -> dict:
    """Run `citytherm run` on `pkg`, sampling the RSS of its processes; figures of the run."""
    cmd = [
        str(VENV_BIN / "citytherm"),
        "run",
        str(NRW_TILE),
        str(pkg),
        "-o",
        str(out),
        "--workers",
        str(workers),
    ]
    if not refine:
        cmd.append("--no-refine")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    root = psutil.Process(proc.pid)
    peak: dict[int, int] = {}
    cpu_seen: dict[int, float] = {}  # last CPU seconds seen per process
    peak_total = 0
    while proc.poll() is None:
        usage = tree_usage(root)
        for pid, (rss, cpu_s) in usage.items():
            peak[pid] = max(peak.get(pid, 0), rss)
            cpu_seen[pid] = max(cpu_seen.get(pid, 0.0), cpu_s)
        peak_total = max(peak_total, sum(rss for rss, _ in usage.values()))
        time.sleep(sample_s)
    wall = time.perf_counter() - t0
    err = proc.stderr.read() if proc.stderr else ""
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {err[-2000:]}")
    # waited-for descendants (`RUSAGE_CHILDREN`) or the sampled CPU times, whichever is larger:
    # pool workers reaped by the forkserver may miss the former, the last interval the latter
    cpu = max((after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime), sum(cpu_seen.values()))
    n = len(json.loads((pkg / "sequence.json").read_text(encoding="utf-8"))["frames"])
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    others = [v for pid, v in peak.items() if pid != proc.pid]
    return {
        "command": " ".join(cmd),
        "frames": n,
        "refine": refine,
        "workers": workers,
        "wall_s": round(wall, 1),
        "cpu_s": round(cpu, 1),
        "ms_per_frame_wall": round(1000 * wall / n, 2),
        "ms_per_frame_cpu": round(1000 * cpu / n, 2),
        "peak_rss_parent_mb": round(peak.get(proc.pid, 0) / MB, 1),
        "peak_rss_largest_child_mb": round(max(others, default=0) / MB, 1),
        "peak_rss_sum_mb": round(peak_total / MB, 1),
        "processes_seen": len(peak),
        "ru_maxrss_children_so_far_mb": round(after.ru_maxrss / 1024.0, 1),  # kB on Linux
        "stage_wall_s": {k: round(v, 2) for k, v in report.get("timings_s", {}).items()},
        "buildings_processed": report.get("buildings_processed"),
        "unit_stage_s": {k: round(v, 2) for k, v in report.get("unit_stage_timings_s", {}).items()},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", default="1000,4000", help="comma-separated frame counts")
    ap.add_argument("--refine-frames", default="1000", help="frame counts also run with refinement ('' none)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--height", type=int, default=80)
    ap.add_argument("--unique", type=int, default=1000, help="at most this many frames rendered (one lap)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--sample-s", type=float, default=0.2)
    ap.add_argument("--keep", type=Path, help="keep packages and results here")
    args = ap.parse_args()
    counts = [int(x) for x in args.frames.split(",") if x]
    refine_counts = {int(x) for x in args.refine_frames.split(",") if x}

    runs: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for n in counts:
            pkg = work / f"drive{n}"
            gen = build_package(pkg, n, args.seed, args.width, args.height, args.unique)
            for refine in (False, True) if n in refine_counts else (False,):
                fig = run_job(
                    pkg, work / f"out{n}{'r' if refine else ''}", args.workers, refine, args.sample_s
                )
                runs.append({**fig, "package": gen})
                print(json.dumps(runs[-1]), file=sys.stderr, flush=True)  # progress
    out = {
        "cpu_count": os.cpu_count(),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "bar_rss_mb": 2048,
        "runs": runs,
        "bar_met": all(max(r["peak_rss_parent_mb"], r["peak_rss_largest_child_mb"]) < 2048 for r in runs),
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

"""Where `citytherm run` spends its time (issue 18, item 1): a py-spy profile per stage.

Builds (or reuses) a synthetic drive along the real NRW LoD2 tile (`tests/data/`, default
GNSS/INS errors, 640 × 512 px, `citytherm synth` defaults), runs `citytherm run` with refinement
under `py-spy record --format raw --subprocesses` (pool workers included), and prints JSON: per
stage (ingest, calibrate, orient, plan, units, finish, other = start-up and imports) the sampled
seconds and the top functions by self time (the leaf frame of a sample) and by total time (any
frame of a sample), each with seconds and share of the stage; and the stage wall times of the
run's `report.json`.

Stages are told apart by the `workers.job` function on the sampled stack (`calibrate`, `orient`,
`run_unit`, ...). py-spy leaves out threads blocked in a wait, and this script the progress
display's polling thread, so a stage's sampled seconds are its busy seconds over all processes:
its CPU seconds on a quiet machine, nearer its wall seconds on a loaded one (a thread waiting for
a core counts as busy); shares within a stage hold either way. Native threads of BLAS/OpenCV are
not sampled: they count once, under the calling frame.

Usage: `.venv/bin/python bench/profile_job.py [--frames 100] [--workers 1] [--rate 50]
[--package DIR] [--keep DIR]`.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

REPO = Path(__file__).resolve().parents[1]
NRW_TILE = REPO / "tests" / "data" / "nrw-tile-5659-citygml1-lod2.gml"
VENV_BIN = Path(sys.executable).parent

#: `workers.job` stage functions, innermost match wins (`run_unit` may run under `finish`'s
#: split-half; `calibrate` is also called without refinement)
STAGES = ("run_unit", "finish", "plan", "orient", "calibrate", "ingest")
STAGE_NAME = {"run_unit": "units"}
#: leaf functions of threads that wait (sampled as active by py-spy while they poll)
WAITS = frozenset({"Condition.wait", "Event.wait", "wait", "select", "poll"})
_FRAME = re.compile(r"^(?P<func>.+?) \((?P<file>.+?)(?::(?P<line>\d+))?\)$")


@dataclass
class StageProfile:
    """Sample counts of one stage: all samples, per function as leaf (self) and anywhere (total)."""

    samples: int = 0
    self_: Counter[str] = field(default_factory=Counter)
    total: Counter[str] = field(default_factory=Counter)


def parse_frame(frame: str) -> tuple[str, str]:
    """`"func (path/file.py:123)"` -> `("func", "path/file.py")`; unparsable frames as they are."""
    m = _FRAME.match(frame.strip())
    if not m:
        return frame.strip(), ""
    return m["func"], m["file"]


def short_file(path: str) -> str:
    """A source path made relative to the repository (site-packages are already short)."""
    return path.removeprefix(str(REPO) + "/")


def stage_of(frames: list[tuple[str, str]]) -> tuple[str, int]:
    """The stage of a stack (root first) and the position of its stage frame: the innermost
    `workers/job.py` stage function on it; `("other", -1)` when there is none."""
    for k in range(len(frames) - 1, -1, -1):
        func, file = frames[k]
        if file.endswith("workers/job.py") and func in STAGES:
            return STAGE_NAME.get(func, func), k
    return "other", -1


def parse_raw(path: Path) -> dict[str, StageProfile]:
    """Read py-spy's raw (collapsed-stack) output: lines `frame;frame;... count`, root first,
    optionally headed by `process N:"cmd"` and thread frames; per stage the sample counts."""
    stages: dict[str, StageProfile] = {}
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            continue
        n = int(count)
        parts = [p for p in stack.split(";") if p and not p.startswith(("process ", "thread "))]
        frames = [parse_frame(p) for p in parts]
        if not frames or frames[-1][0] in WAITS:
            continue  # an idle thread (the progress display's refresh thread)
        stage, at = stage_of(frames)
        sp = stages.setdefault(stage, StageProfile())
        sp.samples += n
        names = [f"{func} ({short_file(file)})" if file else func for func, file in frames]
        sp.self_[names[-1]] += n
        for name in set(names[at + 1 :]):  # below the stage function: not the common call chain
            sp.total[name] += n
    return stages


def top(counter: Counter[str], samples: int, rate: float, k: int) -> list[dict]:
    """The `k` largest entries of `counter`: function, seconds (samples / rate), share of the stage."""
    return [
        {"function": name, "s": round(c / rate, 2), "share": round(c / samples, 3)}
        for name, c in counter.most_common(k)
    ]


def summary(stages: dict[str, StageProfile], rate: float, k: int = 15) -> dict:
    """JSON-ready per-stage summary, stages in pipeline order."""
    order = ("other", "ingest", "calibrate", "orient", "plan", "units", "finish")
    all_samples = sum(s.samples for s in stages.values()) or 1
    out: dict = {}
    for name in sorted(stages, key=lambda s: order.index(s) if s in order else len(order)):
        sp = stages[name]
        out[name] = {
            "sampled_s": round(sp.samples / rate, 2),
            "share_of_run": round(sp.samples / all_samples, 3),
            "top_self": top(sp.self_, sp.samples, rate, k),
            "top_total": top(sp.total, sp.samples, rate, k),
        }
    return out


def make_package(out: Path, frames: int, seed: int) -> Path:
    """Render the bench drive: `frames` frames along the NRW tile, default errors (`citytherm synth`)."""
    cmd = [
        str(VENV_BIN / "citytherm"),
        "synth",
        "--model",
        str(NRW_TILE),
        "--frames",
        str(frames),
        "--seed",
        str(seed),
        "-o",
        str(out),
    ]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workers", type=int, default=1, help="citytherm run --workers")
    ap.add_argument("--rate", type=int, default=50, help="py-spy samples per second")
    ap.add_argument("--top", type=int, default=15)
    ap.add_argument("--package", type=Path, help="reuse this package (else rendered)")
    ap.add_argument("--keep", type=Path, help="keep the profile, package and results here")
    ap.add_argument("--raw", type=Path, help="only summarise this py-spy raw profile (no run)")
    args = ap.parse_args()
    if args.raw:
        print(json.dumps({"stages": summary(parse_raw(args.raw), args.rate, args.top)}, indent=1))
        return

    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        pkg = args.package or make_package(work / "drive", args.frames, args.seed)
        raw = work / "profile.raw"
        cmd = [
            str(VENV_BIN / "py-spy"),
            "record",
            "--format",
            "raw",
            "--subprocesses",
            "-r",
            str(args.rate),
            "-o",
            str(raw),
            "--",
            str(VENV_BIN / "citytherm"),
            "run",
            str(NRW_TILE),
            str(pkg),
            "-o",
            str(work / "out"),
            "--workers",
            str(args.workers),
        ]
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        report = json.loads((work / "out" / "report.json").read_text(encoding="utf-8"))
        n_frames = len(json.loads((pkg / "sequence.json").read_text(encoding="utf-8"))["frames"])
        out = {
            "command": " ".join(cmd),
            "frames": n_frames,
            "workers": args.workers,
            "cpu_count": os.cpu_count(),
            "load_avg_1min": round(os.getloadavg()[0], 2),
            "wall_s": round(wall, 1),
            "stage_wall_s": {k: round(v, 2) for k, v in report.get("timings_s", {}).items()},
            "stages": summary(parse_raw(raw), args.rate, args.top),
        }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

"""Texture-stage speed per process (issue 18, item 4; bar ≥ 100 frames/s per process).

Synthetic sequences with TRUE poses (no refinement mixes in) over real LoD2 geometry, every
building of the file in the rendered scene (`tests.reference.compare.make_case`): a drive and a
helicopter flight along the NRW tile 5659 (`tests/data/`) and along the bundled Berlin model.
The job's own stages plan the building units (`workers.job.ingest`, `calibrate`, `orient`,
`plan`, refinement off); this process then runs every unit's texture stage
(`workers.pipeline.units.texture_unit`: surface sight, texel grids, frame decoding through the
per-process frame cache, occlusion test, sampling, fusion) one unit after the other, as one
worker process of `citytherm run` does. Building the unit's ray caster (`unit_raycaster`, the
`scene` timing), atlas packing and the anomaly analysis are not part of the stage.

The figure, per case:

- `frames_per_cpu_s` (the bar): frames textured ÷ CPU seconds of the stage in this process,
  where a frame textured is one building-frame pair (one unit texturing one of its frames: what
  `texture_frame` does once; `bench/texture.py` counts the same) and the CPU seconds are
  `time.process_time()` over the `texture_unit` calls (all threads of the process, Open3D's ray
  casting included). `frames_per_wall_s`: the same pairs ÷ wall seconds (distorted by the
  machine's load, reported for reference).
- `sequence_frames_per_cpu_s`: distinct sequence frames ÷ the same CPU seconds (a flight's frame
  is textured by dozens of units).
- `cpu_s_by_part`: the stage's CPU seconds split into `sight`, `grid` and the per-frame `decode`
  and `texture` (the units' own timers, wall clock).

Each case is first run once untimed (warm: imports, Open3D, the camera's pixel rays), then the
per-process frame cache is emptied and the case timed, so that every frame is decoded once in
the timed run, as in a fresh worker (`--cold`: time the first run instead). Prints JSON.

Usage: `.venv/bin/python bench/texture_speed.py [--cases nrw-drive,nrw-flight,berlin-drive,
berlin-flight] [--frames 60,24] [--out DIR] [--cold] [--profile FILE]`.
`--profile FILE`: also write a cProfile of the timed runs (`pstats` file).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from db.sequence_package import _CACHED_BYTES, _FRAMES
from tests.reference.compare import SCENES, CaseSpec, make_case

CASES = ("nrw-drive", "nrw-flight", "berlin-drive", "berlin-flight")


def plan_case(case: Any) -> tuple[list[Any], int]:
    """The building units of a case as `citytherm run --no-refine` plans them, and the number of
    frames of its sequence."""
    from workers.job import RunOptions, calibrate, ingest, orient, plan

    opts = RunOptions.build(refine=False, workers=1, display=False)
    ing = ingest(case.model, case.package, opts)
    cal = calibrate(ing, opts)
    ori = orient(ing, cal, opts)
    return list(plan(ing, cal, ori, opts).units), len(ing.frame_indices)


def texture_units(units: list[Any], profiler: cProfile.Profile | None = None) -> dict[str, Any]:
    """Run the texture stage of every unit in this process; CPU and wall seconds of it, the
    building-frame pairs and distinct frames textured, CPU seconds by part."""
    from workers.pipeline.units import refine_unit, texture_unit, unit_raycaster, withheld_frames

    cpu = wall = 0.0
    pairs = 0
    frames: set[int] = set()
    parts: dict[str, float] = {}
    for unit in units:
        caster = unit_raycaster(unit)
        poses, records = refine_unit(unit, caster)
        withheld = withheld_frames(unit, poses, records)
        if profiler is not None:
            profiler.enable()
        c0, w0 = time.process_time(), time.perf_counter()
        tex = texture_unit(unit, poses, caster, withheld)
        cpu += time.process_time() - c0
        wall += time.perf_counter() - w0
        if profiler is not None:
            profiler.disable()
        used = [f for f in unit.frames if f not in set(withheld)]
        pairs += len(used)
        frames.update(used)
        for k, v in tex.timings_s.items():
            parts[k] = parts.get(k, 0.0) + float(v)
    return {"cpu_s": cpu, "wall_s": wall, "pairs": pairs, "frames": len(frames), "parts": parts}


def run_case(name: str, n_frames: dict[str, int], root: Path, cold: bool,
             profiler: cProfile.Profile | None) -> dict[str, Any]:  # fmt: skip
    """Synthesize, plan and time one case; its JSON block."""
    scene, platform = name.split("-")
    spec = CaseSpec(scene, platform, n_frames[platform])  # type: ignore[arg-type]
    made = root / spec.name / f"made-{spec.n_frames}"
    if made.is_file():  # a package of the same spec made by an earlier run under --out
        case: Any = SimpleNamespace(model=SCENES[scene], package=root / spec.name / "seq")
    else:
        case = make_case(spec, root)
        made.touch()
    units, n_seq = plan_case(case)
    if not cold:
        texture_units(units)
        _FRAMES.clear()  # each frame decoded once in the timed run, as a fresh worker does
        _CACHED_BYTES[0] = 0
    r = texture_units(units, profiler)
    return {
        "sequence_frames": n_seq,
        "units": len(units),
        "building_frame_pairs": r["pairs"],
        "distinct_frames_textured": r["frames"],
        "cpu_s": round(r["cpu_s"], 3),
        "wall_s": round(r["wall_s"], 3),
        "frames_per_cpu_s": round(r["pairs"] / r["cpu_s"], 1) if r["cpu_s"] else None,
        "frames_per_wall_s": round(r["pairs"] / r["wall_s"], 1) if r["wall_s"] else None,
        "sequence_frames_per_cpu_s": round(r["frames"] / r["cpu_s"], 1) if r["cpu_s"] else None,
        "bar_frames_per_cpu_s>=100": bool(r["cpu_s"]) and r["pairs"] / r["cpu_s"] >= 100.0,
        "seconds_by_part": {k: round(v, 3) for k, v in sorted(r["parts"].items())},
        "load_average_1min": round(os.getloadavg()[0], 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma list of {CASES}")
    ap.add_argument("--frames", default="60,24", help="drive,flight frame counts")
    ap.add_argument("--out", type=Path, default=None, help="keep the packages here (reused if present)")
    ap.add_argument("--cold", action="store_true", help="time the first run (no warm-up run)")
    ap.add_argument("--profile", type=Path, default=None, help="write a cProfile of the timed runs")
    a = ap.parse_args()
    n_drive, n_flight = (int(x) for x in a.frames.split(","))
    root = a.out or Path(tempfile.mkdtemp(prefix="citytherm-bench-texture-speed-"))
    root.mkdir(parents=True, exist_ok=True)
    prof = cProfile.Profile() if a.profile else None
    out: dict[str, Any] = {"bench": "texture-speed", "cases": {}}
    for name in a.cases.split(","):
        out["cases"][name] = run_case(name, {"drive": n_drive, "flight": n_flight}, root, a.cold, prof)
        print(f"# {name}: {out['cases'][name]['frames_per_cpu_s']} frames/s", file=sys.stderr, flush=True)
    if prof is not None:
        prof.dump_stats(str(a.profile))
    if a.out is None:
        shutil.rmtree(root, ignore_errors=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

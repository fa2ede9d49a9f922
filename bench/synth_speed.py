"""Rendering speed of the synthetic TIR generator: frames per second at 640×512.

Prints JSON: frames/s of `SynthFrames` (ray casting, temperature field, sensor effects and the
uint16 conversion) for a 20-building procedural scene (drive and flight) and for a drive through
the bundled real Berlin LoD2 model; plus a per-stage split of the 20-building drive. Bar: the
20-building drive >= 10 frames/s. Run: `.venv/bin/python bench/synth_speed.py [--frames N]`.
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

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from db.citygml.reader import read_model
from db.synth_files import write_synthetic_package
from workers.pipeline.synth import BUNDLED_MODEL, SynthOptions, procedural_block, synthesize


def fps(result, n: int) -> dict:
    """Render frames 1..n (frame 0 warms up the ray-casting scene); frames/s and ms/frame."""
    result.frames[0]
    times = []
    for i in range(1, n + 1):
        t = time.perf_counter()
        result.frames[i]
        times.append(time.perf_counter() - t)
    times = np.array(times)
    return {
        "frames": n,
        "fps": round(float(n / times.sum()), 2),
        "ms_per_frame_median": round(float(np.median(times) * 1000), 1),
        "ms_per_frame_min": round(float(times.min() * 1000), 1),
    }


def stages(result, n: int) -> dict:
    """Median ms per stage: ray cast + temperatures (`radiance`), sensor effects, DN conversion."""
    r = result.renderer
    rad, sen, dn = [], [], []
    for i in range(1, n + 1):
        pose = result.truth.poses[i]
        t0 = time.perf_counter()
        img = r.radiance(pose)
        t1 = time.perf_counter()
        img = r.apply_sensor(img, i)
        t2 = time.perf_counter()
        result.manifest.radiometry.dn(img)
        t3 = time.perf_counter()
        rad.append(t1 - t0)
        sen.append(t2 - t1)
        dn.append(t3 - t2)
    pairs = (("radiance", rad), ("sensor", sen), ("dn", dn))
    return {k: round(float(np.median(v) * 1000), 1) for k, v in pairs}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=30)
    args = ap.parse_args()
    n = args.frames
    out: dict = {"resolution": "640x512", "cpu_count": os.cpu_count(), "load_avg_1min": os.getloadavg()[0]}
    block = procedural_block(20, seed=1)
    drive = synthesize(block, SynthOptions(platform="drive", n_frames=n + 1, seed=1, buildings=5))
    out["procedural_20_drive"] = {
        "scene_buildings": len(drive.buildings),
        "triangles": len(drive.mesh.triangles),
        **fps(drive, n),
        "stages_ms": stages(drive, min(n, 10)),
    }
    flight = synthesize(block, SynthOptions(platform="flight", n_frames=n + 1, seed=1, buildings=5))
    out["procedural_20_flight"] = {"scene_buildings": len(flight.buildings), **fps(flight, n)}
    _, berlin = read_model(BUNDLED_MODEL)
    real = synthesize(berlin, SynthOptions(platform="drive", n_frames=n + 1, seed=1, buildings=5))
    out["berlin_61_drive"] = {
        "scene_buildings": len(real.buildings),
        "triangles": len(real.mesh.triangles),
        **fps(real, n),
    }
    # end to end: render + write 16-bit PNGs, imu.csv, manifest and truth
    t0 = time.perf_counter()
    small = synthesize(block, SynthOptions(platform="drive", n_frames=n, seed=2, buildings=5))
    t_setup = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        write_synthetic_package(small, Path(tmp) / "pkg", Path(tmp) / "truth.json")
        t_write = time.perf_counter() - t0
    out["procedural_20_drive_package"] = {
        "synthesize_setup_s": round(t_setup, 2),
        "render_and_write_fps": round(n / t_write, 2),
    }
    out["bar_fps"] = 10.0
    out["bar_met"] = out["procedural_20_drive"]["fps"] >= 10.0
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

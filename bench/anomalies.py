"""Anomaly bench (issue 16): heat leaks and windows found by `citytherm run`, against the truth.

Synthetic sequences (`workers.pipeline.synth.synthesize`) over the real NRW LoD2 tile
(`tests/data/nrw-tile-5659-citygml1-lod2.gml`, every building of the file in the rendered scene,
so the neighbours occlude): a drive and a helicopter flight with leaks planted at 3 per building
(`ThermalOptions(leaks_per_building=3)`, Poisson mean), the same two scenes leak-free
(`leaks_per_building=0`) for the false-leak rate, all with true poses (`--no-refine`), and a
leak drive with the default GNSS/INS errors and refinement on (30 frames 0.1 s apart; frames
the refinement does not confirm are withheld from texturing, so it observes less: see its
`orientation` block). Each runs through the shipped path (`workers.run.run_job`, what
`citytherm run` does); the truth is read back from the truth file the generator wrote, the
detections from the results folder's `anomalies.geojson` (none when the file is absent), and
which truth items the frames observed from the job's own fused textures as its units held them
(`recording_textures`: grid, values and distinct frames per texel of every textured polygon;
the results folder keeps no frame counts). "Observed" (`workers.anomaly_eval`): ≥ 50 % of a
leak's half-maximum disc or of a window's rectangle seen by ≥ 2 distinct frames, and resolvable
on its grid (half-maximum diameter ≥ 2 texels, pane sides ≥ 3 texels); the figures under the
earlier definition (≥ 50 % with any value, `EvalOptions.texels_only()`) follow as
`leaks_texels_only` and `windows_texels_only`. Prints one JSON document, per case:

- `leaks`: truth, truth_observed, detections, matched, false, precision, recall (a match: centre
  within 0.5 m in 3D, one-to-one, greedy by distance), outline IoU median, ΔT error median (K),
  false leaks per 100 m² of observed facade (and of all observed surfaces), recall by texel size
  of the surface, the strongest false detections;
- `windows`: the same counts, precision and recall (a match: centre within 0.5 m or IoU ≥ 0.5);
  `leaks_on_windows`: leak detections on a truth window;
- `speed`: facade textures analysed per second per process: the units' `anomalies` timing
  (`report.json` buildings' `timings_s`, the shipped `analyse_surface` over every surface
  texture of the unit) over the surfaces that got texels (wall clock: the bar's figure), and
  `facades_per_cpu_s`, the same per CPU second of this process (`time.process_time` around
  the units' analysis), which the load of a shared machine does not distort;
- `gdal`: `ogrinfo` on `anomalies.geojson`: geometry type, features, the layer's CRS (EPSG)
  against the model's (the manifest's `EPSG:n`);
- `bars`: the issue's bars for that case and whether each is met (None: figure undefined).

Then `leak_free_total` (the false-leak rate over both leak-free scenes together) and
`bars_met` (counts over all cases).

Usage: `python bench/anomalies.py [--quick] [--building] [--frames 60,16] [--errors-frames 30]
[--seed 1] [--cluster 4] [--leaks 3] [--out DIR]`. `--building`: the units analyse each building's
coplanar adjacent polygons as one facade (`AnomalyOptions.facade_grouping`). `--quick`: the leak drive and the
leak-free drive with 40 frames (about 30 s of CPU); the default run (five cases: 60 drive frames
0.3 s apart, 16 flight frames 0.5 s apart, the errors drive) takes about 2 minutes of CPU (the
job runs its units in one process; the wall time grows with whatever else shares the machine).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.reference.compare import SCENES, Case, CaseSpec, run_product
from workers.anomaly_eval import (
    Coverage,
    EvalOptions,
    detections_from_geojson,
    evaluate_leaks,
    evaluate_windows,
    leaks_on_windows,
)

#: seconds between frames: a drive covers 8 m/s x 0.3 s = 2.4 m per frame (a facade point 11 m
#: away still in about four frames), so that 60 frames pass ~140 m of facades; a flight (20 m/s)
#: moves 10 m per frame on its circle
INTERVAL_S = {"drive": 0.3, "flight": 0.5}

#: the errors case: a drive with frames 0.1 s apart (the spacing the refinement is tuned on, as in
#: `bench/texture.py`); calibration and refinement cost ~1.5 s of CPU per frame on this scene
ERRORS_FRAMES = 30

#: the issue's bars: figure path -> (comparison, limit)
BARS: dict[str, tuple[str, float]] = {
    "leaks.precision": (">=", 0.9),
    "leaks.recall": (">=", 0.9),
    "leaks.outline_iou_median": (">=", 0.5),
    "leaks.delta_k_error_median_k": ("<=", 0.3),
    "windows.precision": (">=", 0.9),
    "windows.recall": (">=", 0.9),
    "leaks.false_leaks_per_100m2_facade": ("<=", 0.1),
    "speed.facades_per_s": (">=", 100.0),
}


@dataclass(frozen=True)
class AnomalyCase:
    """One bench case: platform, frames, leaks per building (Poisson mean), GNSS/INS errors with
    refinement (True) or true poses without (False)."""

    platform: str
    n_frames: int
    leaks: float
    errors: bool = False
    interval_s: float | None = None  # None: INTERVAL_S of the platform

    @property
    def name(self) -> str:
        """`nrw-<platform>-<leaks|clean>[-errors]`."""
        kind = "leaks" if self.leaks > 0 else "clean"
        return f"nrw-{self.platform}-{kind}" + ("-errors" if self.errors else "")


def make_case(case: AnomalyCase, root: Path, seed: int, cluster: int) -> tuple[Case, Any]:
    """Synthesize the case over the whole NRW tile, write package and truth file; returns the
    `Case` (for `run_product`) and the truth read back from its file."""
    from db.citygml.reader import read_model
    from db.synth_files import load_truth, write_synthetic_package
    from workers.pipeline.synth import ErrorOptions, SynthOptions, ThermalOptions, synthesize

    t0 = time.perf_counter()
    model = SCENES["nrw"]
    _, buildings = read_model(model)
    res = synthesize(
        buildings,
        SynthOptions(
            platform=case.platform,  # type: ignore[arg-type]
            n_frames=case.n_frames,
            seed=seed,
            buildings=cluster,
            frame_interval_s=case.interval_s or INTERVAL_S[case.platform],
            errors=ErrorOptions() if case.errors else ErrorOptions(enabled=False),
            thermal=ThermalOptions(leaks_per_building=case.leaks),
            model_path=str(model),
        ),
    )
    truth_path = root / case.name / "seq.truth.json"
    pkg = write_synthetic_package(res, root / case.name / "seq", truth_path)
    spec = CaseSpec("nrw", case.platform, case.n_frames, errors=case.errors, seed=seed, cluster=cluster)  # type: ignore[arg-type]
    return Case(spec, res, pkg, model, time.perf_counter() - t0), load_truth(truth_path)


def coverage_of(out_dir: Path) -> Coverage:
    """The job's observed texels: every textured polygon's grid and fused texture (NaN = DN 0)."""
    from db.results_folder.read import iter_surface_textures, report_radiometry

    report = json.loads((out_dir / "report.json").read_text(encoding="utf-8"))
    tex = iter_surface_textures(out_dir, report_radiometry(report))
    return Coverage({s.polygon.id: (s.grid, s.value) for s in tex})


@dataclass
class Recording:
    """What `recording_textures` records: the `Coverage` of the job's fused textures, and the CPU
    seconds of this process spent in the units' analysis with the number of surface textures
    (with texels) it analysed."""

    coverage: Coverage
    cpu_s: float = 0.0
    surfaces: int = 0


@contextmanager
def recording_textures() -> Iterator[Recording]:
    """While the job runs in this process (`workers == 1`), record every unit's fused textures as
    the anomaly analysis receives them (`units.analyse_unit`, wrapped and called unchanged):
    a `Coverage` with each textured polygon's grid, fused values (NaN: not observed) and
    distinct frames per texel (`anomalies.typical.frames_per_texel`), and the CPU time of the
    analysis (`time.process_time`)."""
    from workers.pipeline import units
    from workers.pipeline.anomalies.typical import frames_per_texel

    rec = Recording(Coverage({}, {}))
    cov = rec.coverage
    original = units.analyse_unit

    def analyse_unit(tex: Any, options: Any) -> Any:
        for g, t in zip(tex.grids, tex.textures, strict=True):
            cov.textures[g.polygon_id] = (g, np.where(g.mask, t.value, np.nan))
            assert cov.frames is not None
            cov.frames[g.polygon_id] = frames_per_texel(t.obs_frame)
            rec.surfaces += int(np.isfinite(t.value[g.mask]).any())
        t0 = time.process_time()
        out = original(tex, options)
        rec.cpu_s += time.process_time() - t0
        return out

    units.analyse_unit = analyse_unit
    try:
        yield rec
    finally:
        units.analyse_unit = original


def speed(report: dict[str, Any]) -> dict[str, Any]:
    """Facade textures analysed per second per process: surfaces with texels over the units'
    `anomalies` time (None until the units time the analysis)."""
    n, t, timed = 0, 0.0, 0
    for b in report.get("buildings", []):
        ts = b.get("timings_s") or {}
        if "anomalies" not in ts:
            continue
        timed += 1
        t += float(ts["anomalies"])
        n += sum(1 for s in b.get("surfaces", []) if int(s.get("texels_observed") or 0) > 0)
    return {
        "facades_per_s": round(n / t, 1) if t > 0 else None,
        "surfaces_analysed": n,
        "anomalies_s": round(t, 3),
        "units_timed": timed,
        "units": len(report.get("buildings", [])),
    }


def cpu_speed(rec: Recording) -> dict[str, Any]:
    """Facade textures with texels analysed per CPU second of this process (`time.process_time`
    around every `units.analyse_unit` call, the job running in this process): unlike the units'
    wall-clock timing, not distorted by other load on the machine."""
    per_s = round(rec.surfaces / rec.cpu_s, 1) if rec.cpu_s > 0 else None
    return {"facades_per_cpu_s": per_s, "anomalies_cpu_s": round(rec.cpu_s, 3)}


def gdal_check(geojson: Path, crs: str) -> dict[str, Any]:
    """`ogrinfo -ro -so -al` on the results' `anomalies.geojson` (the issue's GDAL bar): geometry
    type, feature count, the EPSG codes in the layer's CRS and whether the model's horizontal
    code (`crs`, the manifest's `EPSG:n`) is among them (`ok`; None for an empty layer). `run`
    False without `ogrinfo` or file."""
    exe = shutil.which("ogrinfo")
    if exe is None or not geojson.is_file():
        return {"run": False}
    try:
        text = subprocess.run(
            [exe, "-ro", "-so", "-al", str(geojson)], capture_output=True, text=True, timeout=120
        ).stdout
    except (OSError, subprocess.SubprocessError) as exc:
        return {"run": False, "error": str(exc)}
    geom = re.search(r"^Geometry: (.+)$", text, re.M)
    count = re.search(r"^Feature Count: (\d+)$", text, re.M)
    codes = [int(c) for c in re.findall(r'ID\["EPSG",(\d+)\]', text)]
    want = int(crs.split(":")[1]) if crs.upper().startswith("EPSG:") else None
    geometry = geom.group(1).strip() if geom else None
    n = int(count.group(1)) if count else None
    ok = bool(geometry and geometry.startswith("3D")) and want is not None and want in codes
    return {
        "run": True,
        "geometry": geometry,
        "features": n,
        "layer_crs_epsg": codes[-1] if codes else None,
        "model_epsg": want,
        "ok": None if n == 0 else ok,  # an empty layer has no geometry type to judge
    }


def bars(fig: dict[str, Any], leak_free: bool) -> dict[str, dict[str, Any]]:
    """The issue's bars that apply to a case (leak figures in leak scenes, the false-leak rate in
    leak-free scenes, windows and speed everywhere): value, limit and whether it is met."""
    out: dict[str, dict[str, Any]] = {}
    for path, (op, limit) in BARS.items():
        rate = path == "leaks.false_leaks_per_100m2_facade"
        if path.startswith("leaks.") and rate != leak_free:
            continue
        group, key = path.split(".")
        value = fig.get(group, {}).get(key)
        met = None if value is None else (value >= limit if op == ">=" else value <= limit)
        out[path] = {"value": value, "bar": f"{op} {limit:g}", "met": met}
    gdal = fig.get("gdal") or {}
    if gdal.get("run"):
        value = f"{gdal['geometry']}, EPSG:{gdal['layer_crs_epsg']}"
        out["gdal.opens_3d_in_model_crs"] = {"value": value, "bar": "3D, model CRS", "met": gdal["ok"]}
    return out


def leak_free_total(cases: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """False leaks of all leak-free cases together per 100 m² of their observed facades (one
    scene alone observes a few hundred m²: one false leak is already 0.1-0.3 per 100 m²)."""
    clean = [c["leaks"] for c in cases.values() if c["leaks_per_building"] == 0]
    n = sum(c["false_leaks_facade"] for c in clean)
    area = sum(c["observed_facade_m2"] for c in clean)
    rate = round(100.0 * n / area, 4) if area > 0 else None
    return {
        "cases": len(clean),
        "false_leaks_facade": n,
        "observed_facade_m2": round(area, 1),
        "false_leaks_per_100m2_facade": rate,
        "met": None if rate is None else rate <= BARS["leaks.false_leaks_per_100m2_facade"][1],
    }


def _brief(fig: dict[str, Any]) -> dict[str, Any]:
    """The counts and ratios of an evaluation block (for the second definition of "observed")."""
    keys = (
        "truth_observed",
        "matched",
        "precision",
        "recall",
        "outline_iou_median",
        "delta_k_error_median_k",
    )
    return {k: fig[k] for k in keys if k in fig}


def run_case(
    case: AnomalyCase, root: Path, seed: int, cluster: int, building: bool = False
) -> dict[str, Any]:
    """Synthesize, run the job (refinement with the errors case only), evaluate: the case's block
    (`building`: coplanar adjacent polygons analysed as one facade, `AnomalyOptions.facade_grouping`)."""
    made, truth = make_case(case, root, seed, cluster)
    grouping = {"unit": {"anomalies": {"facade_grouping": True}}} if building else None
    with recording_textures() as rec:
        run = run_product(made, root / case.name / "results", refine=case.errors, options=grouping)
    cov = rec.coverage
    geo = run.out_dir / "anomalies.geojson"
    det = detections_from_geojson(json.loads(geo.read_text(encoding="utf-8"))) if geo.is_file() else []
    t0 = time.perf_counter()
    old = EvalOptions.texels_only()
    fig: dict[str, Any] = {
        "frames": case.n_frames,
        "leaks_per_building": case.leaks,
        "errors_and_refinement": case.errors,
        "detections_file": geo.is_file(),
        "leaks": evaluate_leaks(truth.anomalies, det, cov),
        "windows": evaluate_windows(truth.windows, det, cov),
        "leaks_texels_only": _brief(evaluate_leaks(truth.anomalies, det, cov, old)),
        "windows_texels_only": _brief(evaluate_windows(truth.windows, det, cov, old)),
        "leaks_on_windows": leaks_on_windows(det, truth.windows),
        "bridges_detected": sum(1 for d in det if d.kind == "bridge"),
        "speed": speed(run.report) | cpu_speed(rec),
        "gdal": gdal_check(geo, truth.crs),
    }
    fig["bars"] = bars(fig, leak_free=case.leaks == 0)
    fig["times_s"] = {
        "synth": round(made.synth_s, 1),
        "job": round(run.wall_s, 1),
        "evaluate": round(time.perf_counter() - t0, 1),
        "job_stages": {k: round(float(v), 2) for k, v in run.report.get("timings_s", {}).items()},
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
    if case.errors:
        orient = [b.get("orientation") or {} for b in run.report.get("buildings", [])]
        n_or = sum(int(o.get("frames") or 0) for o in orient)
        fig["orientation"] = {
            "calibration_accepted": (run.report.get("calibration") or {}).get("accepted"),
            "unit_frames_refined_share": round(sum(int(o.get("refined") or 0) for o in orient) / n_or, 3)
            if n_or
            else None,
            "unit_frames_withheld": sum(len(o.get("frames_withheld") or []) for o in orient),
        }
    fig["buildings_processed"] = len(run.report.get("buildings", []))
    fig["buildings_in_scene"] = len(made.res.buildings)
    return fig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", default="60,16", help="drive,flight frame counts")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--cluster", type=int, default=4)
    ap.add_argument("--errors-frames", type=int, default=ERRORS_FRAMES, help="errors drive frames (0: none)")
    ap.add_argument("--leaks", type=float, default=3.0, help="leaks per building (Poisson mean)")
    ap.add_argument("--quick", action="store_true", help="leak and leak-free drives, 40 frames")
    ap.add_argument("--building", action="store_true", help="analyse per building (analyse_building)")
    ap.add_argument("--out", type=Path, default=None, help="keep the packages and results here")
    a = ap.parse_args()
    n_drive, n_flight = (int(x) for x in a.frames.split(","))
    if a.quick:
        cases = [AnomalyCase("drive", 40, a.leaks), AnomalyCase("drive", 40, 0.0)]
    else:
        cases = [
            AnomalyCase("drive", n_drive, a.leaks),
            AnomalyCase("flight", n_flight, a.leaks),
            AnomalyCase("drive", n_drive, 0.0),
            AnomalyCase("flight", n_flight, 0.0),
        ]
        if a.errors_frames > 0:
            cases.append(AnomalyCase("drive", a.errors_frames, a.leaks, errors=True, interval_s=0.1))
    root = a.out or Path(tempfile.mkdtemp(prefix="citytherm-bench-anomalies-"))
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    out: dict[str, Any] = {"bench": "anomalies", "quick": a.quick, "seed": a.seed, "building": a.building}
    out["cases"] = {}
    for case in cases:
        out["cases"][case.name] = run_case(case, root, a.seed, a.cluster, a.building)
        print(f"# {case.name}: done at {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    out["leak_free_total"] = leak_free_total(out["cases"])
    met = [b["met"] for c in out["cases"].values() for b in c["bars"].values()]
    out["bars_met"] = {"met": met.count(True), "not_met": met.count(False), "undefined": met.count(None)}
    out["total_s"] = round(time.perf_counter() - t0, 1)
    out["results"] = str(root) if a.out is not None else None
    if a.out is None:
        shutil.rmtree(root, ignore_errors=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

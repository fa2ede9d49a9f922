"""Texture bench: `citytherm run` against an independent reference texturer on real LoD2 geometry.

Synthetic sequences (`workers.pipeline.synth.synthesize`) are laid over real CityGML files — the
NRW tile 5659 (hilly, dormers, occluding neighbours), the bundled Berlin LoD2 model and the
Potsdam LoD1 block — with every building of the file in the rendered scene (the neighbours
occlude): a drive and a helicopter flight per file. The product runs through the shipped path
(`workers.run.run_job`, what `citytherm run` does; true poses: `--no-refine`), the reference
texturer (`tests/reference`: its own OpenCV projection, z-buffer, mixed-pixel test and fusion)
gets the true poses and the same frame files. Both are evaluated against the truth field at
their own texel centres (`tests/reference/evaluate.py`; every error figure area-weighted, as the
two grids differ in density). Prints JSON, per scene and platform:

- `product` / `reference`: RMSE, p95 and median |error| (K) on the surfaces both textured;
  `rmse_ratio`, `p95_ratio` (product / reference; bar ≤ 1.2);
- `surfaces_textured` (product, reference, both; bar: ratio ≥ 0.95) and
  `observed_area_per_surface_ratio` (product / reference observed area on the surfaces both
  textured, median and overall; the texel-per-surface figure made independent of the two grids'
  densities; bar ≥ 0.95);
- `hidden_surfaces_textured`: surfaces the product textured where the reference finds no clean
  observation in any frame (bar 0; `never_seen_by_any_frame`: not even a texel centre is seen),
  with the worst of them; `unseen_texels_delivered`: product texels at places no frame sees
  (0.2 m tolerance), `texels_without_clean_view_delivered`: at places no frame sees cleanly;
- `visible_untextured`: surfaces the reference textures and the product does not, by kind, in
  buildings the product processed, with or without a reason in `report.json`;
- `worst_surfaces_vs_reference`: the surfaces where the product's squared error exceeds the
  reference's most (K²·m²), with the reference's median view angle;
- `by_class`: errors by texel class (interior, boundary: within 3 px of a polygon-id change in
  the best frame or never clean, grazing > 70°, unseen; roof, wall, other) for both;
- `speed`: the product's texture-stage frames/s per worker process (`decode + texture` unit time
  per building-frame pair, one process) and wall times (the product's wall time includes its
  split-half check where that runs);
- `split_half` (drives; flights with `--split-half-flights`): the product run with `--split-half`
  (its `report.json` `split_half` block: even and odd halves of each building's frames textured
  apart, per-tile shift by phase correlation) and the reference texturer's halves by the same
  rule, compared by the product's own `split_half_agreement` on the reference's grid
  (`tests/reference/split_half.py`): tiles, agree share, median tile shift in texels and metres
  for both, `ratio_m` (product ÷ reference median shift in metres; the two grids' texels may
  differ) and `ratio_texels`; bars: product median shift ≤ 0.3 texel and `ratio_m` ≤ 1.2.
Then `errors`: one scene with the default GNSS/INS errors and refinement on (drive and flight):
product RMSE with errors ÷ product RMSE with true poses (bar ≤ 1.5), on all surfaces it textured;
`orientation.frames_rejected_by_texture`: building-frame pairs whose observations the texture
stage dropped for contradicting the other frames' (`texture.consistency`; a pose off by pixels).

Usage: `python bench/texture.py [--scenes nrw,berlin,potsdam] [--platform drive,flight]
[--frames 60,24] [--errors-scene nrw|none] [--split-half-flights] [--quick] [--out DIR]`.
`--quick`: the NRW tile only, 30 drive and 12 flight frames (a few minutes); the default run takes
~10–15 min on 2 cores.
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
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.reference.compare import SCENES, CaseSpec, make_case, run_product, run_reference
from tests.reference.evaluate import compare_case
from tests.reference.split_half import run_reference_split_half, split_half_figures
from workers.pipeline.texture.split_half import SplitHalfOptions


def bars(fig: dict[str, Any]) -> dict[str, bool | None]:
    """The issue's bars on one true-pose case (None when a figure is undefined)."""

    def le(x: float | None, limit: float) -> bool | None:
        return None if x is None else x <= limit

    def ge(x: float | None, limit: float) -> bool | None:
        return None if x is None else x >= limit

    return {
        "rmse<=1.2x_reference": le(fig["rmse_ratio"], 1.2),
        "p95<=1.2x_reference": le(fig["p95_ratio"], 1.2),
        "hidden_surfaces_textured==0": fig["hidden_surfaces_textured"]["count"] == 0,
        "surfaces_textured>=0.95x_reference": ge(fig["surfaces_textured"]["ratio"], 0.95),
        "observed_area_per_surface>=0.95x_reference": ge(
            fig["observed_area_per_surface_ratio"]["median"], 0.95
        ),
        "visible_untextured_all_with_reason": fig["visible_untextured"]["without_reason"] == 0,
        **(fig["split_half"]["bars"] if "split_half" in fig else {}),
    }


def run_case(
    spec: CaseSpec, root: Path, refine: bool, options: dict[str, Any] | None = None,
    split_half: bool = False,
) -> dict[str, Any]:  # fmt: skip
    """Synthesize, run the product (with `options` overrides) and the reference, compare; the
    case's JSON block. `split_half`: the product runs with `--split-half` (its outputs stay the
    same) and the block gets `split_half` (`split_half_block`)."""
    case = make_case(spec, root)
    opts = {**(options or {}), "split_half": True} if split_half else options
    run = run_product(case, root / spec.name / "results", refine=refine, options=opts)
    polys, refs, ref_s = run_reference(case)
    fig = compare_case(case, run.out_dir, run.report, polys, refs)
    if split_half:
        fig["split_half"] = split_half_block(case, run.report)
    fig["speed"] = {
        "texture_frames_per_s_per_process": round(run.frames_per_s, 1) if run.frames_per_s else None,
        "building_frame_pairs": run.pairs,
        "texture_stage_s": round(run.texture_stage_s, 2),
        "product_wall_s": round(run.wall_s, 1),
        "product_stage_s": {k: round(float(v), 2) for k, v in run.report.get("timings_s", {}).items()},
        "reference_s": round(ref_s, 1),
        "synth_s": round(case.synth_s, 1),
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
    cal = run.report.get("calibration", {})
    orient = [b.get("orientation", {}) for b in run.report.get("buildings", [])]
    n_or = sum(int(o.get("frames") or 0) for o in orient)
    fig["orientation"] = {
        "calibration_accepted": cal.get("accepted"),
        "calibration_reason": cal.get("reason"),
        "unit_frames_refined_share": round(sum(int(o.get("refined") or 0) for o in orient) / n_or, 3)
        if n_or
        else None,
        # building-frame pairs the texture dropped: observations contradicting the other frames'
        "frames_rejected_by_texture": sum(len(o.get("frames_rejected_by_texture") or []) for o in orient),
    }
    fig["frames"] = spec.n_frames
    fig["buildings_in_scene"] = len(case.res.buildings)
    fig["buildings_processed"] = len(run.report.get("buildings", []))
    fig["product_resolution_px_per_m"] = run.report.get("resolution_px_per_m")
    return fig


def split_half_block(case: Any, report: dict[str, Any]) -> dict[str, Any]:
    """The product's split-half figures (`report["split_half"]`) against the reference's on the
    same buildings with the same thresholds (`tests.reference.split_half`), and timings."""
    prod = report.get("split_half") or {}
    if not prod.get("run"):
        return {"error": "the product's report.json has no split_half block"}
    ref = run_reference_split_half(
        case, [b["id"] for b in prod.get("buildings", [])], SplitHalfOptions(**prod["options"])
    )
    fig = split_half_figures(prod, ref)
    fig["product_split_half_s"] = round(float(report.get("timings_s", {}).get("split_half", 0.0)), 2)
    fig["reference_split_half_s"] = ref["seconds"]
    return fig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="nrw,berlin,potsdam", help=f"comma list of {sorted(SCENES)}")
    ap.add_argument("--platform", default="drive,flight")
    ap.add_argument("--frames", default="60,24", help="drive,flight frame counts")
    ap.add_argument("--errors-scene", default="nrw", help="scene of the GNSS/INS error runs, or none")
    ap.add_argument("--cluster", type=int, default=4)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--quick", action="store_true", help="NRW only, 30 drive / 12 flight frames")
    ap.add_argument("--split-half-flights", action="store_true", help="split-half check on flights too")
    ap.add_argument("--out", type=Path, default=None, help="keep the packages and results here")
    ap.add_argument(
        "--options",
        type=json.loads,
        default=None,
        help='overrides of the job options as JSON, e.g. \'{"unit": {"texel": {"oversample": 1}}}\'',
    )
    a = ap.parse_args()
    if a.quick:
        a.scenes, a.frames = "nrw", "30,12"
        a.errors_scene = "nrw" if a.errors_scene != "none" else "none"
    n_drive, n_flight = (int(x) for x in a.frames.split(","))
    frames = {"drive": n_drive, "flight": n_flight}
    platforms = [p for p in a.platform.split(",") if p]
    root = a.out or Path(tempfile.mkdtemp(prefix="citytherm-bench-texture-"))
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    out: dict[str, Any] = {"bench": "texture-vs-reference", "quick": a.quick, "cases": {}}
    for scene in a.scenes.split(","):
        for plat in platforms:
            spec = CaseSpec(scene, plat, frames[plat], seed=a.seed, cluster=a.cluster)  # type: ignore[arg-type]
            sh = plat == "drive" or a.split_half_flights
            fig = run_case(spec, root, refine=False, options=a.options, split_half=sh)
            fig["bars"] = bars(fig)
            out["cases"][spec.name] = fig
            print(f"# {spec.name}: done at {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    if a.errors_scene != "none":
        out["errors"] = {}
        for plat in platforms:
            base = CaseSpec(a.errors_scene, plat, frames[plat], seed=a.seed, cluster=a.cluster)  # type: ignore[arg-type]
            if base.name not in out["cases"]:
                out["cases"][base.name] = run_case(base, root, refine=False, options=a.options)
            spec = CaseSpec(a.errors_scene, plat, frames[plat], errors=True, seed=a.seed, cluster=a.cluster)  # type: ignore[arg-type]
            fig = run_case(spec, root, refine=True, options=a.options)
            true_rmse = out["cases"][base.name]["product_all_surfaces"]
            err_rmse = fig["product_all_surfaces"]
            ratio = (
                round(err_rmse["rmse_k"] / true_rmse["rmse_k"], 3)
                if err_rmse["rmse_k"] is not None and true_rmse["rmse_k"]
                else None
            )
            out["errors"][spec.name] = {
                "product_rmse_errors_refined_k": err_rmse["rmse_k"],
                "product_rmse_true_poses_k": true_rmse["rmse_k"],
                "ratio": ratio,
                "bar_ratio<=1.5": None if ratio is None else ratio <= 1.5,
                "vs_reference_same_case": {k: fig[k] for k in ("product", "reference", "rmse_ratio")},
                "surfaces_textured": fig["surfaces_textured"],
                "hidden_surfaces_textured": fig["hidden_surfaces_textured"]["count"],
                "orientation": fig["orientation"],
                "worst_surfaces_vs_reference": fig["worst_surfaces_vs_reference"][:4],
                "speed": fig["speed"],
            }
            print(f"# {spec.name}: done at {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    out["total_s"] = round(time.perf_counter() - t0, 1)
    out["results"] = str(root) if a.out is not None else None
    if a.out is None:
        shutil.rmtree(root, ignore_errors=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

"""`make demo`: synthesise a drive around a real model, run `citytherm run` on it, and compare the
textures with the ground truth.

Steps: read the bundled Berlin model (CityGML 1.0, 61 LoD2 buildings), synthesise a TIR drive
around a few of its buildings (`workers.pipeline.synth`; error-free poses by default, so that the
texture figures compare with the bars; `--gnss-errors` adds realistic GNSS/INS errors and refines
the poses when the orientation module is installed), write the sequence package, run exactly
what `citytherm run` runs, then print where the results are, the summary, and the texture error
against the ground truth (RMSE in kelvin, misregistration in texels, coverage).

Usage: `python -m services.demo --out demo-out [--frames 120] [--buildings 4] [--workers 2]
[--gnss-errors]`.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from db.citygml.reader import read_model
from db.synth_files import write_synthetic_package
from services.cli.run_cmd import anomalies_line, run_with_progress, summary_table
from workers.job import RunOptions
from workers.pipeline.synth import BUNDLED_MODEL, ErrorOptions, SynthOptions, synthesize
from workers.synth_eval import orientation_accuracy, texture_accuracy


def main(argv: list[str] | None = None) -> int:
    """Run the demo; returns the process exit code."""
    ap = argparse.ArgumentParser(prog="python -m services.demo", description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("demo-out"), help="folder for package and results")
    ap.add_argument("--frames", type=int, default=120, help="frames of the synthetic drive")
    ap.add_argument("--buildings", type=int, default=4, help="buildings the drive goes around")
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--gnss-errors", action="store_true", help="realistic GNSS/INS errors, poses refined")
    ap.add_argument("--no-refine", action="store_true", help="with --gnss-errors: keep the prior poses")
    a = ap.parse_args(argv)
    console = Console()
    t_start = time.perf_counter()
    out = a.out
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)

    console.rule("[bold]citytherm demo")
    console.print(f"model: {BUNDLED_MODEL.name} (bundled Berlin open data, CityGML 1.0, LoD2)")
    _, buildings = read_model(BUNDLED_MODEL)
    errors = ErrorOptions(enabled=a.gnss_errors)
    res = synthesize(
        buildings,
        SynthOptions(
            n_frames=a.frames,
            seed=a.seed,
            buildings=a.buildings,
            frame_interval_s=0.25,
            errors=errors,
            model_path=str(BUNDLED_MODEL),
        ),
    )
    console.print(
        f"synthesising a {a.frames}-frame TIR drive around {len(res.truth.cluster)} buildings "
        f"({'GNSS/INS with realistic errors' if a.gnss_errors else 'error-free poses'}) ..."
    )
    t0 = time.perf_counter()
    pkg = write_synthetic_package(res, out / "sequence", out / "sequence.truth.json")
    console.print(f"package written to {pkg} in {time.perf_counter() - t0:.0f} s")

    refine = a.gnss_errors and not a.no_refine
    options = RunOptions.build(workers=max(1, a.workers), refine=refine, buildings=tuple(res.truth.cluster))
    console.print(
        f"citytherm run {BUNDLED_MODEL.name} {pkg.name} -o {out / 'results'} --workers {options.workers}"
        + ("" if refine else " --no-refine")
        + " --buildings <the drive's cluster>"
    )
    summary = run_with_progress(BUNDLED_MODEL, pkg, out / "results", options, console)
    console.print(summary_table(summary))
    console.print(anomalies_line(summary))

    acc = texture_accuracy(out / "results", res)
    table = Table(title="texture error against the ground truth")
    table.add_column("figure")
    table.add_column("value", justify="right")
    table.add_column("bar (true poses)", justify="right")
    table.add_row("RMSE, all observed texels", f"{acc['rmse_k']:.3f} K", "<= 0.35 K")
    table.add_row("RMSE near sharp edges", f"{acc['rmse_edges_k']:.3f} K", "")
    table.add_row("RMSE away from edges", f"{acc['rmse_away_k']:.3f} K", "")
    mis = acc["misregistration_median_texel"]
    mis_text = f"{mis:.2f} texel" if math.isfinite(mis) else "not measurable (> 3 texels)"
    table.add_row("misregistration (median)", mis_text, "<= 0.3")
    table.add_row("coverage of visible texels", f"{acc['coverage']:.1%}", ">= 95 %")
    ori = orientation_accuracy(out / "results", res)
    if a.gnss_errors:
        table.add_row("prior position error (median)", f"{ori['prior_position_error_median_m']:.2f} m", "")
        if ori["refined_entries"]:
            med = ori["refined_position_error_median_m"]
            table.add_row(
                f"refined position error (median, {ori['refined_entries']} poses)", f"{med:.2f} m", ""
            )
    console.print(table)
    console.print(
        f"results: {(out / 'results').resolve()}  (textured.gml, textures/, orientation.json, "
        "anomalies.geojson, report.json)"
    )
    console.print(f"demo finished in {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

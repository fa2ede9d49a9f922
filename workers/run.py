"""`citytherm run`: the job's stages (`workers.job`) in one process, on files, no server.

In: a CityGML file, a sequence package (folder, its `sequence.json`, or an archive, extracted
for the job's duration), an output folder and `RunOptions`. Out: the results folder of
`docs/results-format.md` and a `RunSummary`.

The building units run in this process (`workers == 1`) or in a forkserver process pool, each
worker with `cpu_count // workers` library threads; their tiles are written as they finish, so
the job's memory stays small. The pool's fork server starts with the job (`pool.start_pool_server`):
it imports the job's modules and decodes the frames (when they fit in the frame cache) while
ingest and calibrate run here, and the orient and units workers fork from it with both done.
Scripts that run pools need the `if __name__ == "__main__"` guard.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from db.results_folder.write import write_tile
from db.sequence_package import open_package
from workers.job import (
    Progress,
    RunOptions,
    UnitFailure,
    calibrate,
    finish,
    ingest,
    no_progress,
    orient,
    orients,
    plan,
    run_unit,
    scene_caster,
)
from workers.pipeline.results import BuildingResult, TextureTile
from workers.pipeline.units import BuildingUnit, Refiner
from workers.pool import cap_library_threads, pool_context, start_pool_server
from workers.split_half import split_half_report


@dataclass
class RunSummary:
    """What a job did: where the results are, per-building results (tile pixels dropped after
    writing), units that failed, per-stage wall times."""

    out_dir: Path
    n_frames: int
    n_buildings_model: int
    results: list[BuildingResult]
    failures: list[UnitFailure]
    units_frames: dict[str, int]
    timings_s: dict[str, float]
    refine: bool
    warning: str | None = None
    calibration: dict[str, Any] | None = None
    orientation: dict[str, Any] | None = None
    split_half: dict[str, Any] | None = None  # report.json's `split_half` block (--split-half)

    @property
    def texels_observed(self) -> int:
        """Observed texels over all buildings."""
        return sum(s.texels_observed for r in self.results for s in r.surfaces)

    @property
    def texels_total(self) -> int:
        """Texels inside the polygons of all processed buildings."""
        return sum(s.texels_total for r in self.results for s in r.surfaces)


def run_units(
    units: Sequence[BuildingUnit], workers: int, refiner: Refiner | None = None
) -> Iterator[BuildingResult | UnitFailure]:
    """Run building units, in this process (`workers <= 1`) or in a pool; yields results (or
    failures) as they finish (pool order is completion order). `refiner` replaces the
    per-building refinement (tests; it must be picklable for a pool)."""
    if workers <= 1 or len(units) <= 1:
        for u in units:
            yield run_unit(u, refiner)
        return
    n, ctx = min(workers, len(units)), pool_context(workers)
    with ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=cap_library_threads) as pool:
        # largest units first: better load balance
        order = sorted(range(len(units)), key=lambda k: -len(units[k].frames))
        futures = [pool.submit(run_unit, units[k], refiner) for k in order]
        for fut in as_completed(futures):
            yield fut.result()


def without_pixels(r: BuildingResult) -> BuildingResult:
    """The same result with empty tile pixels (already written): names kept, memory freed."""
    return replace(r, tiles=tuple(TextureTile(t.name, np.zeros((0, 0), np.uint16)) for t in r.tiles))


def run_job(
    city_gml: str | Path,
    package: str | Path,
    out_dir: str | Path,
    options: RunOptions = RunOptions(),
    progress: Progress = no_progress,
    *,
    refiner: Refiner | None = None,
    on_result: Callable[[BuildingResult], None] | None = None,
) -> RunSummary:
    """Texture the buildings of `city_gml` seen by the sequence `package`; write the results
    folder `out_dir` (created; existing result files are overwritten). Stage wall times go into
    the summary and `report.json`. `on_result` is called with each building's result, tile
    pixels included, as it finishes (its tiles are written by then; the results folder's other
    files come at the end)."""
    timings: dict[str, float] = {}
    with open_package(package) as pkg:  # an archive stays extracted for the job's duration
        # the pool's server imports and decodes the frames while ingest and calibrate run here
        start_pool_server(options.workers, pkg.frames)
        t0 = time.perf_counter()
        ingested = ingest(city_gml, pkg.root, options, progress)
        timings["ingest"] = time.perf_counter() - t0

        caster = None  # shared by the calibrate and orient stages
        if options.refine and options.calibrate:
            t0 = time.perf_counter()
            progress("calibrate", 0, 1)
            caster = scene_caster(ingested)
            calibrated = calibrate(ingested, options, caster)
            progress("calibrate", 1, 1)
            timings["calibrate"] = time.perf_counter() - t0
        else:
            calibrated = calibrate(ingested, options)

        oriented_now = orients(options, calibrated, ingested.manifest.platform)
        t0 = time.perf_counter()
        if oriented_now:
            progress("orient", 0, 1)
        oriented = orient(ingested, calibrated, options, progress, caster)
        if oriented_now:
            timings["orient"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        progress("plan", 0, 1)
        planned = plan(ingested, calibrated, oriented, options)
        progress("plan", 1, 1)
        timings["plan"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        results: list[BuildingResult] = []
        failures: list[UnitFailure] = []
        progress("units", 0, len(planned.units))
        tiles_written = 0.0
        for k, r in enumerate(run_units(planned.units, options.workers, refiner)):
            if isinstance(r, UnitFailure):
                failures.append(r)
            else:
                t1 = time.perf_counter()
                for tile in r.tiles:
                    write_tile(out, tile)
                tiles_written += time.perf_counter() - t1
                if on_result is not None:
                    on_result(r)
                results.append(without_pixels(r))  # pixels are on disk: keep the job's memory small
            progress("units", k + 1, len(planned.units))
        timings["units"] = time.perf_counter() - t0 - tiles_written

        split = None  # --split-half: even vs odd frames per building, into report.json only
        if options.split_half:
            t0 = time.perf_counter()
            split = split_half_report(planned.units, results, workers=options.workers, progress=progress)
            timings["split_half"] = time.perf_counter() - t0

        report = finish(out, ingested, calibrated, oriented, planned, results, failures, options, timings,
                        progress, package=package, write_time_offset_s=tiles_written, split_half=split)
    return RunSummary(
        out_dir=out,
        n_frames=len(ingested.manifest.frames),
        n_buildings_model=ingested.n_model_buildings,
        results=results,
        failures=failures,
        units_frames={u.building.id: len(u.frames) for u in planned.units},
        timings_s=timings,
        refine=options.refine,
        warning=planned.warning,
        calibration=report["calibration"],
        orientation=oriented.report,
        split_half=split,
    )

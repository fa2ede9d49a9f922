"""In-process job orchestration: `citytherm run` without any server.

In: a CityGML file, a sequence package, an output folder and `RunOptions`.
Out: the results folder of `spec/results-format.md` and a `RunSummary`.

Stages: ingest (open the package, georeference the prior poses, stream the model keeping the
buildings within reach of the cameras), calibrate (with refinement: boresight, GNSS offset, lever
arm and time delay once per sequence against all those buildings, `calibrate.calibrate_sequence`;
an accepted calibration gives the units calibrated priors and a-priori accuracy, while
`orientation.json` keeps the manifest-only priors), orient (close-range sequences after an
accepted calibration: every frame's pose refined in blocks of feature tracks and a bundle
adjustment with those buildings, `orient_sequence.orient_sequence`; the units refine from it),
plan (which frames see which building: `units.plan_units`), units (one `run_building_unit` per
building, in a forkserver process pool with `workers > 1`, each worker with `cpu_count // workers`
library threads; a unit that raises is reported, not fatal), write
(`results_files.write_results_folder`: tiles, display copies, `textured.gml`, `orientation.json`,
`report.json`). `plan_job` alone gives the service the units
to dispatch as Celery tasks; scripts that run pools need the `if __name__ == "__main__"` guard.
"""

from __future__ import annotations

import importlib.util
import multiprocessing
import os
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial import cKDTree

from db.citygml.reader import iter_buildings, read_header
from db.sequence_package import SequencePackage, open_package
from services.results_files import write_results_folder, write_tile
from services.sequence_stages import calibrate_priors, calibration_documents, orient_priors, orients
from workers.pipeline.geometry.citymodel import Building, ModelHeader
from workers.pipeline.geometry.georef import prior_poses
from workers.pipeline.geometry.manifest import Radiometry
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
from workers.pipeline.results import BuildingResult, TextureTile
from workers.pipeline.texture.texel import TexelOptions
from workers.pipeline.units import BuildingUnit, PlanOptions, UnitOptions, plan_units, run_building_unit

if TYPE_CHECKING:  # the orientation modules are optional: imported where the stage runs
    from workers.pipeline.orientation.calibration import SequenceCalibration

#: progress callback: (stage, done, total); called with done == 0 when a stage starts.
Progress = Callable[[str, int, int], None]
STAGES = ("ingest", "calibrate", "orient", "plan", "units", "write")


class RunError(ValueError):
    """A job that cannot run as asked (names the file or option)."""


def refine_available() -> bool:
    """True when the orientation module (`workers.pipeline.orientation.building`) is installed."""
    return importlib.util.find_spec("workers.pipeline.orientation.building") is not None


@dataclass(frozen=True)
class RunOptions:
    """Options of one `citytherm run` job.

    Attributes:
        resolution_px_per_m: texels per metre on every surface.
        theme: appearance theme of the textures (`<theme>-display` for the 8-bit copies).
        buildings: ids of the top-level buildings to texture (None: all the sequence sees).
        workers: processes for the building units (1: in this process).
        refine: refine poses per building before texturing (needs the orientation module).
        calibrate: with `refine`, calibrate the sequence (mounting, GNSS offset, time delay)
            before the units, which then refine from the calibrated priors.
        orient: with `refine` and an accepted calibration, orient close-range sequences (drives)
            in blocks (feature tracks, bundle adjustment with the model) before the units, which
            then refine from those poses.
        display: also write the 8-bit colour-mapped `<theme>-display` appearance.
        unit: per-stage options of the units (its texel resolution, theme and refine flag are
            overridden by the fields above).
        plan: planning options.
    """

    resolution_px_per_m: float = 10.0
    theme: str = "thermal-ir"
    buildings: tuple[str, ...] | None = None
    workers: int = 1
    refine: bool = False
    calibrate: bool = True
    orient: bool = True
    display: bool = True
    unit: UnitOptions = field(default_factory=UnitOptions)
    plan: PlanOptions = field(default_factory=PlanOptions)

    def unit_options(self) -> UnitOptions:
        """The units' options with this job's resolution, theme and refine flag."""
        texel = replace(self.unit.texel, resolution_px_per_m=self.resolution_px_per_m)
        return replace(self.unit, texel=texel, theme=self.theme, refine=self.refine)


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

    @property
    def texels_observed(self) -> int:
        """Observed texels over all buildings."""
        return sum(s.texels_observed for r in self.results for s in r.surfaces)

    @property
    def texels_total(self) -> int:
        """Texels inside the polygons of all processed buildings."""
        return sum(s.texels_total for r in self.results for s in r.surfaces)


#: thread-pool sizes of numerical libraries (OpenBLAS, OpenMP, TBB users such as Open3D, OpenCV)
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "TBB_NUM_THREADS")


def _mp_context(workers: int) -> multiprocessing.context.BaseContext:
    """`forkserver` where available (no fork of a process that may hold Open3D threads).

    Worker processes get thread pools of `cpu_count // workers` threads (set in the environment
    the server starts with), so that `workers` processes do not oversubscribe the cores."""
    threads = str(max(1, (os.cpu_count() or 1) // max(1, workers)))
    for var in _THREAD_VARS:
        os.environ.setdefault(var, threads)
    methods = multiprocessing.get_all_start_methods()
    if "forkserver" not in methods:
        return multiprocessing.get_context("spawn")
    ctx = multiprocessing.get_context("forkserver")
    # workers fork from a server that has already imported the pipeline and Open3D (~1 s each)
    ctx.set_forkserver_preload(["workers.pipeline.units", "open3d"])
    return ctx


@dataclass(frozen=True)
class UnitFailure:
    """A building unit that raised: the job goes on without it and reports it."""

    building_id: str
    error: str


def _run_safely(unit: BuildingUnit) -> BuildingResult | UnitFailure:
    """`run_building_unit`, with any exception turned into a `UnitFailure` (picklable)."""
    try:
        return run_building_unit(unit)
    except Exception as exc:  # one bad building must not sink the job
        return UnitFailure(unit.building.id, f"{type(exc).__name__}: {exc}")


def run_units(units: Sequence[BuildingUnit], workers: int) -> Iterator[BuildingResult | UnitFailure]:
    """Run building units, in this process (`workers <= 1`) or in a pool; yields results (or
    failures) as they finish (pool order is completion order)."""
    if workers <= 1 or len(units) <= 1:
        for u in units:
            yield _run_safely(u)
        return
    with ProcessPoolExecutor(max_workers=min(workers, len(units)), mp_context=_mp_context(workers)) as pool:
        # largest units first: better load balance
        order = sorted(range(len(units)), key=lambda k: -len(units[k].frames))
        futures = [pool.submit(_run_safely, units[k]) for k in order]
        for fut in as_completed(futures):
            yield fut.result()


def near_buildings(
    buildings: Iterable[Building], priors: Sequence[Pose], reach_m: float
) -> tuple[list[Building], set[str]]:
    """The buildings whose bounding box comes within `reach_m` of a projection centre, in input
    order, and the ids of all buildings seen (to check requested ids)."""
    centres = np.array([p.center for p in priors]).reshape(-1, 3)
    tree = cKDTree(centres) if len(centres) else None
    keep: list[Building] = []
    ids: set[str] = set()
    for b in buildings:
        ids.add(b.id)
        if tree is None:
            continue
        lo, hi = b.bounds()
        d, _ = tree.query(
            (lo + hi) / 2.0, distance_upper_bound=reach_m + float(np.linalg.norm(hi - lo)) / 2.0
        )
        if np.isfinite(d):
            keep.append(b)
    return keep, ids


def output_radiometry(pkg: SequencePackage) -> Radiometry:
    """The tiles' radiometry: the sequence's, except for 8-bit frames, whose values are kept as
    they are (scale 1, offset 0; `results-format.md`)."""
    rad = pkg.manifest.radiometry
    if pkg.manifest.frames and pkg.frames.raw(0).dtype == np.uint8:
        return Radiometry(unit=rad.unit, scale=1.0, offset=0.0)
    return rad


def resolution_warning(plan: JobPlan, options: RunOptions) -> str | None:
    """A warning when the frames are too far from the buildings for the texel resolution: most
    observations would be coarser than `max_texel_ratio` texels per pixel and be dropped."""
    cam = plan.package.manifest.camera
    res = []
    for u in plan.units:
        lo, hi = u.building.bounds()
        for p in u.poses:
            res.append(float(np.linalg.norm(np.clip(p.center, lo, hi) - p.center)) / max(cam.fx, cam.fy))
    if not res:
        return None
    typical = float(np.median(res))  # m/px at the nearest point, head-on: a best case
    ratio = options.unit.visibility.max_texel_ratio
    if typical > ratio / options.resolution_px_per_m:
        suggest = max(0.5, round(ratio / typical / 2, 1))
        return (
            f"the frames see the buildings at about {typical:.2f} m per pixel at best: at "
            f"{options.resolution_px_per_m:g} texels/m most observations are too coarse to use; "
            f"try --resolution {suggest:g}"
        )
    return None


@dataclass
class JobPlan:
    """An ingested and planned job: what the units stage needs (the service dispatches `units`
    as tasks; `citytherm run` runs them in a pool). Owns the opened package: `package.close()`."""

    city_gml: Path
    package_path: Path
    header: ModelHeader
    buildings: list[Building]
    package: SequencePackage
    priors: list[Pose]
    units: list[BuildingUnit]
    n_model_buildings: int = 0
    warning: str | None = None
    calibration: SequenceCalibration | None = None
    orientation: dict[str, Any] = field(default_factory=lambda: {"run": False})


def plan_job(
    city_gml: str | Path,
    package: str | Path,
    options: RunOptions = RunOptions(),
    progress: Progress | None = None,
    timings: dict[str, float] | None = None,
) -> JobPlan:
    """Ingest (read the model and the package, georeference the prior poses), calibrate (with
    `refine` and `calibrate`: the units get the calibrated priors, `JobPlan.priors` stays the
    manifest-only prior) and plan (one building unit per building the sequence sees). Stage
    wall times go into `timings`."""
    report: Progress = progress or (lambda stage, done, total: None)
    timings = timings if timings is not None else {}
    if options.workers < 1:
        raise RunError(f"workers must be >= 1, got {options.workers}")
    if options.refine and not refine_available():
        raise RunError("refine: the orientation module (workers.pipeline.orientation.building) is not installed")
    TexelOptions(resolution_px_per_m=options.resolution_px_per_m)  # validates the resolution

    t0 = time.perf_counter()
    report("ingest", 0, 3)
    if not Path(city_gml).is_file():
        raise RunError(f"{city_gml}: city model not found")
    header = read_header(city_gml)
    report("ingest", 1, 3)
    pkg = open_package(package)
    try:
        manifest = pkg.manifest
        priors = prior_poses(manifest, header.srs_name)
        report("ingest", 2, 3)
        # stream the model; keep the buildings within reach of the cameras (memory follows the
        # drive, not the city)
        reach = min(options.plan.max_distance_m, options.unit.visibility.max_distance_m)
        buildings, ids = near_buildings(iter_buildings(city_gml), priors, reach)
        if options.buildings is not None:
            missing = [b for b in options.buildings if b not in ids]
            if missing:
                raise RunError(f"buildings: not in {city_gml}: {', '.join(missing)}")
        report("ingest", 3, 3)
        timings["ingest"] = time.perf_counter() - t0

        # the units refine from the calibrated priors; `priors` stays the manifest-only prior
        unit_priors, accuracy, calibration = priors, manifest.accuracy, None
        caster = None  # over the buildings near the cameras, shared by the calibrate and orient stages
        if options.refine and options.calibrate:
            t0 = time.perf_counter()
            report("calibrate", 0, 1)
            caster = RayCaster(build_scene_mesh(buildings)) if buildings else None
            calibration, unit_priors, accuracy = calibrate_priors(buildings, manifest, priors, pkg.frames,
                                                                  caster)
            report("calibrate", 1, 1)
            timings["calibrate"] = time.perf_counter() - t0

        # close-range sequences: every frame oriented in blocks before the units
        sequence, orientation = None, {"run": False}
        if options.refine and options.orient and calibration is not None and calibration.accepted \
                and orients(manifest.platform):
            t0 = time.perf_counter()
            report("orient", 0, 1)
            sequence, orientation = orient_priors(buildings, manifest, unit_priors, pkg.frames, accuracy,
                                                  lambda done, total: report("orient", done, total), caster)
            timings["orient"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        report("plan", 0, 1)
        unit_options = options.unit_options()
        if calibration is not None and calibration.accepted and unit_options.refine_options is None:
            # the common error is removed: the units skip their wide searches
            from workers.pipeline.orientation.building import CoregisterOptions, calibrated_options

            unit_options = replace(unit_options, refine_options=calibrated_options(CoregisterOptions()))
        units = plan_units(
            buildings,
            manifest.camera,
            unit_priors,
            pkg.frames,
            output_radiometry(pkg),
            times=[f.time for f in manifest.frames],
            frame_indices=[f.index for f in manifest.frames],
            accuracy=accuracy,
            options=unit_options,
            plan=options.plan,
            targets=None
            if options.buildings is None
            else [b.id for b in buildings if b.id in options.buildings],
            sequence=sequence,
        )
        report("plan", 1, 1)
        timings["plan"] = time.perf_counter() - t0
    except BaseException:
        pkg.close()
        raise
    plan = JobPlan(Path(city_gml), Path(package), header, buildings, pkg, priors, units, len(ids))
    plan.calibration = calibration
    plan.orientation = orientation
    plan.warning = resolution_warning(plan, options)
    return plan


def run_job(
    city_gml: str | Path,
    package: str | Path,
    out_dir: str | Path,
    options: RunOptions = RunOptions(),
    progress: Progress | None = None,
) -> RunSummary:
    """Texture the buildings of `city_gml` seen by the sequence `package`; write the results
    folder `out_dir` (created; existing result files are overwritten)."""
    timings: dict[str, float] = {}
    plan = plan_job(city_gml, package, options, progress, timings)
    try:
        return _run_planned(plan, Path(out_dir), options, progress, timings)
    finally:
        plan.package.close()


def _run_planned(
    plan: JobPlan, out: Path, options: RunOptions, progress: Progress | None, timings: dict[str, float]
) -> RunSummary:
    """Units and write stages of `run_job`."""
    report: Progress = progress or (lambda stage, done, total: None)
    units, buildings, header, priors = plan.units, plan.buildings, plan.header, plan.priors
    manifest = plan.package.manifest
    city_gml, package = plan.city_gml, plan.package_path

    # -- units -------------------------------------------------------------------------------
    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    results: list[BuildingResult] = []
    failures: list[UnitFailure] = []
    report("units", 0, len(units))
    tiles_written = 0.0
    for k, r in enumerate(run_units(units, options.workers)):
        if isinstance(r, UnitFailure):
            failures.append(r)
        else:
            t1 = time.perf_counter()
            for tile in r.tiles:
                write_tile(out, tile)
            tiles_written += time.perf_counter() - t1
            results.append(replace_tiles(r))  # pixels are on disk: keep the job's memory small
        report("units", k + 1, len(units))
    timings["units"] = time.perf_counter() - t0 - tiles_written

    # -- write -------------------------------------------------------------------------------
    t0 = time.perf_counter()
    frames_of = {u.building.id: len(u.frames) for u in units}
    mounting, calibration = calibration_documents(
        plan.calibration, manifest.mounting, timings.get("calibrate")
    )
    job = {
        "city_model": str(city_gml),
        "package": str(package),
        "refine": options.refine,
        "calibrate": plan.calibration is not None,
        "sequence_orientation": plan.orientation,
        "workers": options.workers,
        "buildings_in_model": plan.n_model_buildings,
        "buildings_near_the_cameras": len(buildings),
        "failed": [{"id": f.building_id, "error": f.error} for f in failures],
        "warnings": [plan.warning] if plan.warning else [],
    }
    write_results_folder(
        out,
        buildings=buildings,
        results=results,
        manifest=manifest,
        priors=priors,
        mounting=mounting,
        calibration=calibration,
        srs_name=header.srs_name,
        theme=options.theme,
        resolution_px_per_m=options.resolution_px_per_m,
        display=options.display,
        frames_of=frames_of,
        timings_s=timings,
        job=job,
        progress=lambda done, total: report("write", done, total),
        write_time_offset_s=tiles_written,
        started=t0,
    )
    return RunSummary(
        out_dir=out,
        n_frames=len(manifest.frames),
        n_buildings_model=plan.n_model_buildings,
        results=results,
        failures=failures,
        units_frames=frames_of,
        timings_s=timings,
        refine=options.refine,
        warning=plan.warning,
        calibration=calibration,
        orientation=plan.orientation,
    )


def replace_tiles(r: BuildingResult) -> BuildingResult:
    """The same result with empty tile pixels (already written): names kept, memory freed."""
    return BuildingResult(
        building_id=r.building_id,
        appearance=r.appearance,
        tiles=tuple(TextureTile(t.name, np.zeros((0, 0), np.uint16)) for t in r.tiles),
        radiometry=r.radiometry,
        surfaces=r.surfaces,
        poses=r.poses,
        anomalies=r.anomalies,
        timings_s=r.timings_s,
    )

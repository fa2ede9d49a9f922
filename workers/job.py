"""The stages of a texturing job, each a function over plain, picklable data (`DESIGN.md`).

`citytherm run` calls them in one process (`workers.run.run_job`); the service runs ingest +
calibrate + orient as one task per sequence, one task per building unit, then finish.

- `ingest(city_gml, package_dir, options) -> Ingested`: read the package (a folder: archives are
  extracted by the caller) and georeference the prior poses; stream the model, keeping the
  buildings within reach of the cameras.
- `calibrate(ingested, options) -> Calibrated`: with refinement, boresight, GNSS offset, lever arm
  and time delay once per sequence against those buildings
  (`orientation.calibration.calibrate_sequence`). An accepted calibration gives the units
  calibrated priors and a-priori accuracy; `orientation.json` keeps the manifest-only priors.
- `orient(ingested, calibrated, options) -> Oriented`: close-range sequences, calibrated or not:
  every frame's pose refined in blocks of feature tracks and a bundle adjustment with those
  buildings (`orientation.sequence.orient_sequence`); the units refine from it.
- `plan(ingested, calibrated, oriented, options) -> Planned`: which frames see which building
  (`plan.plan_units`): one `BuildingUnit` per building.
- `run_unit(unit) -> BuildingResult | UnitFailure`: one building (`units.run_building_unit`); a
  unit that raises is reported, not fatal.
- `finish(out_dir, ...)`: the results folder (`db.results_folder.write`).

Options: `RunOptions` (`workers.run_options`, imported here), one frozen dataclass that
round-trips through JSON (`to_dict` / `from_dict`) so that the service stores it with the job. The
texel resolution, theme and refinement live in `RunOptions.unit` only.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from db.citygml.reader import iter_buildings, read_header
from db.results_folder.write import write_results_folder
from db.sequence_package import open_package
from workers.orient_rgb import rgb_registered
from workers.pipeline.geometry.citymodel import Building, ModelHeader
from workers.pipeline.geometry.georef import prior_poses
from workers.pipeline.geometry.manifest import Accuracy, FrameSource, Mounting, Radiometry, SequenceManifest
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
from workers.pipeline.orientation.building import calibrated_options
from workers.pipeline.orientation.calibration import (
    CalibrationOptions,
    SequenceCalibration,
    apply_calibration,
    calibrate_sequence,
    calibrated_accuracy,
)
from workers.pipeline.orientation.mounting import calibration_report, mounting_document
from workers.pipeline.orientation.sequence import (
    SEQUENCE_PLATFORMS,
    SequenceOrientation,
    SequenceOrientationOptions,
    WindowMap,
    orient_sequence,
)
from workers.pipeline.orientation.wireframe import EdgeOptions, Wireframe, WireframeError, mesh_wireframe
from workers.pipeline.plan import near_buildings, plan_units, resolution_warning
from workers.pipeline.reconstruction.combine import with_reconstruction
from workers.pipeline.results import BuildingResult, output_radiometry
from workers.pipeline.texture.texel import TexelOptions
from workers.pipeline.units import BuildingUnit, Refiner, UnitOptions, run_building_unit
from workers.pool import pool_map
from workers.run_options import RunOptions

#: progress callback: (stage, done, total); called with done == 0 when a stage starts.
Progress = Callable[[str, int, int], None]
STAGES = ("ingest", "calibrate", "orient", "plan", "units", "write")


class RunError(ValueError):
    """A job that cannot run as asked (names the file or option)."""


@dataclass(frozen=True, eq=False)
class Ingested:
    """What the ingest stage read: the model header, the package, the prior poses and the
    buildings within reach of the cameras.

    Attributes:
        city_gml: the city model: its file, or the name of a model from the database.
        package_dir: the package folder (`sequence.json` in it).
        header: the model's CRS and name.
        manifest: the sequence manifest (positions in the manifest's CRS).
        frames: the package's frames (`PackageFrames`: picklable, loads by path).
        priors: manifest-only prior camera pose per frame, manifest order (world = model CRS).
        buildings: the top-level buildings within reach of the cameras, model order.
        n_model_buildings: top-level buildings in the whole model.
        radiometry: the output tiles' radiometry (`results.output_radiometry`).
    """

    city_gml: Path | str
    package_dir: Path
    header: ModelHeader
    manifest: SequenceManifest
    frames: FrameSource
    priors: tuple[Pose, ...]
    buildings: tuple[Building, ...]
    n_model_buildings: int
    radiometry: Radiometry

    @property
    def frame_indices(self) -> list[int]:
        """The frames' indices, manifest order."""
        return [f.index for f in self.manifest.frames]

    @property
    def times(self) -> list[float]:
        """The frames' time stamps in seconds, manifest order."""
        return [float(f.time) for f in self.manifest.frames]


@dataclass(frozen=True, eq=False)
class Calibrated:
    """The calibrate stage's result.

    Attributes:
        calibration: the sequence calibration (None: the stage did not run).
        priors: the poses the units start from, manifest order (`apply_calibration`: the
            manifest-only priors unless the calibration was accepted).
        accuracy: their a-priori accuracy (`calibrated_accuracy`; the manifest's unless accepted).
    """

    calibration: SequenceCalibration | None
    priors: tuple[Pose, ...]
    accuracy: Accuracy | None

    @property
    def accepted(self) -> bool:
        """True when a calibration ran and was accepted."""
        return self.calibration is not None and self.calibration.accepted


@dataclass(frozen=True, eq=False)
class Oriented:
    """The orient stage's result: the sequence orientation (None when it did not run or failed)
    and the `report.json` `sequence_orientation` block."""

    orientation: SequenceOrientation | None
    report: dict[str, Any]


@dataclass(frozen=True, eq=False)
class Planned:
    """The plan stage's result: one unit per building seen, and a resolution warning."""

    units: tuple[BuildingUnit, ...]
    warning: str | None = None


@dataclass(frozen=True)
class UnitFailure:
    """A building unit that raised: the job goes on without it and reports it."""

    building_id: str
    error: str


def no_progress(stage: str, done: int, total: int) -> None:
    """The default progress callback: nothing."""


#: a model's top-level buildings for ingest: `(prior poses, reach in metres) -> buildings` in
#: model order; it may leave out buildings farther than the reach from every camera (a spatial
#: query), never one within it (`plan.near_buildings` keeps those).
BuildingSource = Callable[[Sequence[Pose], float], Iterable[Building]]


def _check_options(options: RunOptions) -> None:
    if options.workers < 1:
        raise RunError(f"workers must be >= 1, got {options.workers}")
    TexelOptions(resolution_px_per_m=options.resolution_px_per_m)  # validates the resolution


def ingest(
    city_gml: str | Path, package_dir: str | Path, options: RunOptions, progress: Progress = no_progress
) -> Ingested:
    """The ingest stage (see the module docstring) on a CityGML file (`ingest_buildings` with the
    file's buildings, streamed). Raises `RunError` naming the file or option, `PackageError` /
    `CityGMLError` for bad input."""
    _check_options(options)
    city_gml = Path(city_gml)
    progress("ingest", 0, 3)
    if not city_gml.is_file():
        raise RunError(f"{city_gml}: city model not found")
    header = read_header(city_gml)
    progress("ingest", 1, 3)
    every = lambda priors, reach: iter_buildings(city_gml)  # noqa: E731 - the whole file, streamed
    return ingest_buildings(header, every, package_dir, options, progress, city_model=city_gml)


def ingest_buildings(
    header: ModelHeader,
    buildings: BuildingSource,
    package_dir: str | Path,
    options: RunOptions,
    progress: Progress = no_progress,
    *,
    city_model: str | Path,
    model_ids: Collection[str] | None = None,
) -> Ingested:
    """The ingest stage over a model given by its header and its buildings (a file's, or a
    database model's: `db.model_load`): read the package, georeference the prior poses into
    `header.srs_name`, keep the buildings within reach of the cameras. `city_model` names the
    model in messages and `report.json`; `model_ids` are the ids of all the model's top-level
    buildings when `buildings` leaves some out (requested ids are checked against them, their
    number is `n_model_buildings`; None: the ids `buildings` gives). Raises as `ingest`."""
    _check_options(options)
    given = Path(package_dir).resolve()
    with open_package(package_dir) as pkg:
        if pkg.root.resolve() not in (given, given.parent):
            raise RunError(f"{package_dir}: ingest takes a package folder; extract the archive first")
        manifest, frames = pkg.manifest, pkg.frames
        raw_dtype = frames.raw(0).dtype if manifest.frames else np.dtype(np.uint16)
    priors = prior_poses(manifest, header.srs_name)
    progress("ingest", 2, 3)
    reach = min(options.plan.max_distance_m, options.unit.visibility.max_distance_m)
    near, ids = near_buildings(buildings(priors, reach), priors, reach)
    known: Collection[str] = ids if model_ids is None else model_ids
    if options.buildings is not None:
        missing = [b for b in options.buildings if b not in known]
        if missing:
            raise RunError(f"buildings: not in {city_model}: {', '.join(missing)}")
    progress("ingest", 3, 3)
    return Ingested(
        city_gml=city_model,
        package_dir=pkg.root,
        header=header,
        manifest=manifest,
        frames=frames,
        priors=tuple(priors),
        buildings=tuple(near),
        n_model_buildings=len(known),
        radiometry=output_radiometry(manifest.radiometry, raw_dtype),
    )


def scene_caster(ingested: Ingested) -> RayCaster | None:
    """A ray caster over the buildings near the cameras (None when there are none); the calibrate
    and orient stages of one process share it."""
    return RayCaster(build_scene_mesh(ingested.buildings)) if ingested.buildings else None


#: the last scene wireframe made here: `(caster, edge options, wireframe)`
_WIREFRAME: list[tuple[RayCaster, EdgeOptions, Wireframe]] = []


def scene_wireframe(caster: RayCaster, edges: EdgeOptions) -> Wireframe | None:
    """`mesh_wireframe(caster.mesh, edges)` (None when the scene has none), made once per caster:
    the calibrate and orient stages of one process share the caster (`scene_caster`) and, with
    equal edge options, its wireframe (a pure function of the two; about 5 % of each stage)."""
    if _WIREFRAME and _WIREFRAME[0][0] is caster and _WIREFRAME[0][1] == edges:
        return _WIREFRAME[0][2]
    try:
        wf = mesh_wireframe(caster.mesh, edges)
    except WireframeError:
        return None
    _WIREFRAME[:] = [(caster, edges, wf)]
    return wf


def calibrate(ingested: Ingested, options: RunOptions, caster: RayCaster | None = None) -> Calibrated:
    """The calibrate stage: `calibrate_sequence` over every frame against the buildings near the
    cameras (`caster`: a ray caster over them, built here when None).

    Runs only with refinement and `options.calibrate`; otherwise the units start from the
    manifest-only priors. A calibration that raises is returned as rejected, its `reason`
    naming the error: one sequence the method cannot handle must not sink the job.
    """
    m = ingested.manifest
    if not (options.refine and options.calibrate):
        return Calibrated(None, ingested.priors, m.accuracy)
    frames, times = ingested.frame_indices, ingested.times
    if not ingested.buildings:
        cal = SequenceCalibration(theta=np.zeros(10), reason="no buildings near the cameras")
    else:
        try:
            caster = caster if caster is not None else scene_caster(ingested)
            wf = scene_wireframe(caster, CalibrationOptions().edges) if caster is not None else None
            cal = calibrate_sequence(
                m.camera,
                caster,
                frames,
                ingested.frames,
                dict(zip(frames, ingested.priors, strict=True)),
                dict(zip(frames, times, strict=True)),
                m.accuracy,
                wireframe=wf,
            )
        except Exception as exc:  # reported in report.json: the job goes on
            cal = SequenceCalibration(theta=np.zeros(10), reason=f"failed: {type(exc).__name__}: {exc}")
    calibrated = apply_calibration(list(ingested.priors), times, cal)
    return Calibrated(cal, tuple(calibrated), calibrated_accuracy(cal, prior=m.accuracy))


def orients(options: RunOptions, calibrated: Calibrated, platform: str) -> bool:
    """True when the orient stage runs: refinement and `options.orient` on, a platform of
    `orientation.sequence.SEQUENCE_PLATFORMS` (close range, flights), the calibration accepted or
    not."""
    return options.refine and options.orient and platform in SEQUENCE_PLATFORMS


def orient(
    ingested: Ingested,
    calibrated: Calibrated,
    options: RunOptions,
    progress: Progress = no_progress,
    caster: RayCaster | None = None,
    map_windows: WindowMap | None = None,
) -> Oriented:
    """The orient stage: `orient_sequence` over every frame from the priors and accuracy of
    `calibrated` (calibrated or the manifest's), against the buildings near the cameras (`caster`);
    its windows run through `map_windows` (default: `options.workers` processes, `pool.pool_map`).

    An orientation that raises is reported, not fatal: the units then refine from the priors.
    """
    if not orients(options, calibrated, ingested.manifest.platform):
        return Oriented(None, {"run": False})
    if not ingested.buildings:
        return Oriented(None, {"run": False, "reason": "no buildings near the cameras"})
    frames = ingested.frame_indices
    times = dict(zip(frames, ingested.times, strict=True))
    try:
        caster = caster if caster is not None else scene_caster(ingested)
        start, rgb = list(calibrated.priors), None
        if options.rgb:  # method 3: the block onto the RGB camera's cloud (`workers.orient_rgb`)
            start, rgb = rgb_registered(ingested, start)
        prior = dict(zip(frames, start, strict=True))
        so = None  # `sfm`: the reconstruction alone
        if options.orientation != "sfm":
            wf = scene_wireframe(caster, SequenceOrientationOptions().coregister.edges) if caster else None
            so = orient_sequence(
                ingested.manifest.camera, caster, frames, ingested.frames, prior, times, calibrated.accuracy,
                progress=lambda done, total: progress("orient", done, total),
                map_windows=map_windows or pool_map(options.workers), wireframe=wf,
            )
        so, method = with_reconstruction(  # `RunOptions.orientation`: edges, sfm or both
            options.orientation, so, ingested.manifest.camera, caster, frames, ingested.frames, prior, times,
            calibrated.accuracy,
        )
    except Exception as exc:  # reported in report.json: the job goes on
        return Oriented(None, {"run": False, "reason": f"failed: {type(exc).__name__}: {exc}"})
    report = so.to_dict("calibrated" if calibrated.accepted else "manifest")
    if rgb is not None:
        report["rgb"] = rgb
    return Oriented(so, {"run": True, **report, **method})


def unit_options(options: RunOptions, calibrated: Calibrated) -> UnitOptions:
    """The units' options: after an accepted calibration the common error is removed, so the
    refinement skips its wide searches (`calibrated_options`)."""
    unit = options.unit
    if calibrated.accepted and unit.refine is not None:
        unit = replace(unit, refine=calibrated_options(unit.refine))
    return unit


def plan(ingested: Ingested, calibrated: Calibrated, oriented: Oriented, options: RunOptions) -> Planned:
    """The plan stage: one building unit per building the sequence sees (of `options.buildings`
    when given), starting from the calibrated priors and the sequence orientation."""
    m = ingested.manifest
    targets = None
    if options.buildings is not None:
        targets = [b.id for b in ingested.buildings if b.id in options.buildings]
    uopts = unit_options(options, calibrated)
    if m.platform == "flight" and uopts.refine is not None:
        # a flight frame orients alone where the sequence's pose is not confirmed by a building
        uopts = replace(uopts, refine=replace(uopts.refine, sequence_fallback=True))
    units = plan_units(
        ingested.buildings,
        m.camera,
        calibrated.priors,
        ingested.frames,
        ingested.radiometry,
        times=ingested.times,
        frame_indices=ingested.frame_indices,
        accuracy=calibrated.accuracy,
        options=uopts,
        plan=options.plan,
        targets=targets,
        sequence=oriented.orientation,
    )
    return Planned(tuple(units), resolution_warning(units, m.camera, uopts))


def run_unit(unit: BuildingUnit, refiner: Refiner | None = None) -> BuildingResult | UnitFailure:
    """`run_building_unit`, with any exception turned into a `UnitFailure` (picklable)."""
    try:
        if refiner is None:
            return run_building_unit(unit)
        return run_building_unit(unit, refiner)
    except Exception as exc:  # one bad building must not sink the job
        return UnitFailure(unit.building.id, f"{type(exc).__name__}: {exc}")


def calibration_documents(
    calibrated: Calibrated, mounting: Mounting, seconds: float | None
) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """`orientation.json` `mounting` (None: the manifest's `mounting`, no delay) and `report.json`
    `calibration` (`{"run": false}` when the stage did not run; `seconds` its wall time)."""
    cal = calibrated.calibration
    if cal is None:
        return None, {"run": False}
    return mounting_document(mounting, cal), calibration_report(cal, mounting, seconds)


def job_warnings(
    planned: Planned, calibrated: Calibrated, oriented: Oriented, options: RunOptions
) -> list[str]:
    """`report.json` `warnings`: the plan's resolution warning, and a warning when refinement was
    asked for but no frame was oriented (the calibration refused or off, and the sequence
    orientation accepted no block): the textures then come from the GNSS/INS poses as recorded."""
    out = [planned.warning] if planned.warning else []
    cal, rep = calibrated.calibration, oriented.report
    if not options.refine or calibrated.accepted or rep.get("frames_oriented", 0) > 0:
        return out
    if cal is None and not rep.get("run", False):
        return out  # neither stage asked for (`--no-calibrate`, no orientation): nothing expected
    why = [f"the sequence calibration was refused ({cal.reason})" if cal else "no calibration ran"]
    blocks = rep.get("blocks") or []
    if rep.get("run", False):
        reasons = sorted({str(b.get("reason", "")) for b in blocks if b.get("reason")})
        why.append(f"the sequence orientation accepted none of its {len(blocks)} blocks"
                   + (f" ({'; '.join(reasons)})" if reasons else ""))
    elif rep.get("reason"):
        why.append(f"the sequence orientation did not run ({rep['reason']})")
    out.append("refinement was asked for but no frame was oriented: " + " and ".join(why)
               + "; the textures come from the GNSS/INS poses as recorded (expect misregistration by the"
               " GNSS/INS error) or are missing where a building's own refinement rejected its frames")
    return out


def finish(
    out_dir: str | Path,
    ingested: Ingested,
    calibrated: Calibrated,
    oriented: Oriented,
    planned: Planned,
    results: Sequence[BuildingResult],
    failures: Sequence[UnitFailure],
    options: RunOptions,
    timings: dict[str, float],
    progress: Progress = no_progress,
    *,
    package: str | Path | None = None,
    write_time_offset_s: float = 0.0,
    split_half: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The finish stage: the results folder `out_dir` (tiles already written are kept: results
    whose tiles have empty pixels; `db.results_folder.write.write_results_folder`) with the
    job's figures in `report.json` (`package`: the package as the user named it, default its
    folder; `split_half`: the split-half check's block, `workers.split_half`). `timings` gets the
    `write` stage time. Returns the `report.json` document."""
    t0 = time.perf_counter()
    frames_of = {u.building.id: len(u.frames) for u in planned.units}
    mounting, calibration = calibration_documents(
        calibrated, ingested.manifest.mounting, timings.get("calibrate")
    )
    job = {
        "city_model": str(ingested.city_gml),
        "package": str(package if package is not None else ingested.package_dir),
        "refine": options.refine,
        "calibrate": calibrated.calibration is not None,
        "sequence_orientation": oriented.report,
        "workers": options.workers,
        "buildings_in_model": ingested.n_model_buildings,
        "buildings_near_the_cameras": len(ingested.buildings),
        "failed": [{"id": f.building_id, "error": f.error} for f in failures],
        "warnings": job_warnings(planned, calibrated, oriented, options),
        "options": options.to_dict(),
    }
    if split_half is not None:
        job["split_half"] = dict(split_half)
    if ingested.manifest.conditions is not None:  # the survey's weather (`citytherm compare`)
        job["conditions"] = ingested.manifest.conditions.to_dict()
    return write_results_folder(
        out_dir,
        buildings=ingested.buildings,
        results=results,
        manifest=ingested.manifest,
        priors=ingested.priors,
        mounting=mounting,
        calibration=calibration,
        srs_name=ingested.header.srs_name,
        theme=options.theme,
        texel=options.unit.texel,
        display=options.display,
        anomalies=options.unit.anomalies.enabled,
        frames_of=frames_of,
        timings_s=timings,
        job=job,
        progress=lambda done, total: progress("write", done, total),
        write_time_offset_s=write_time_offset_s,
        started=t0,
    )

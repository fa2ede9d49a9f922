"""The building unit: the unit of work of a texturing job, run alike in a local process pool
(`citytherm run`) and as one Celery task per building (the service).

In: a `BuildingUnit` (made by `plan.plan_units`): the building (model CRS, metres) and its
occluding neighbours, the camera, the frames that see it with their prior `Pose`s (world = model
CRS) and times, a picklable `FrameSource` (float32 physical frames), the radiometry, options and,
when the sequence orientation ran, its part of it.
Out: `run_building_unit(unit)` -> `results.BuildingResult` (poses, atlas tiles with texture
coordinates, per-surface statistics and facade figures, anomalies, timings): the poses refined
against the building (`orientation.building.refine_building`, unless `options.refine` is None),
then every surface textured (`texture_unit`), packed, and analysed for thermal anomalies
(`anomalies.analyse_surface`: windows, leak candidates, facade figures). A unit keeps no global
state and writes no files.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np

from workers.pipeline.anomalies import AnomalyOptions, SurfaceAnalysis, analyse_building
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building, Polygon
from workers.pipeline.geometry.manifest import Accuracy, FrameSource, Radiometry
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
from workers.pipeline.orientation.block import UnitSequence
from workers.pipeline.orientation.building import CoregisterOptions, refine_building
from workers.pipeline.results import BuildingResult, FramePose, RefinedPose, SurfaceStats
from workers.pipeline.texture.atlas import AtlasOptions, build_atlas
from workers.pipeline.texture.consistency import reject_inconsistent_frames
from workers.pipeline.texture.fusion import FusionOptions, SurfaceTexels, SurfaceTexture, texture_frame
from workers.pipeline.texture.sight import SurfaceSight, surface_resolution, surface_sight
from workers.pipeline.texture.texel import TexelGrid, TexelOptions, texel_grid
from workers.pipeline.texture.visibility import OcclusionScene, VisibilityOptions, buried_texels

_log = logging.getLogger(__name__)


class UnitError(ValueError):
    """Inconsistent input to planning or running building units."""


@dataclass(frozen=True)
class UnitOptions:
    """Everything that steers a building unit, one frozen options object per stage. The one
    home of the job's texel resolution (`texel.resolution_px_per_m`), theme and refinement.

    Attributes:
        texel: the texel grids (resolution in texels per metre).
        visibility, fusion, atlas: the texture stages.
        anomalies: the thermal-anomaly analysis of every fused surface texture (typical
            temperature, windows, leak candidates, facade figures; `anomalies.enabled` False
            skips it).
        theme: appearance theme of the textures.
        refine: options of the per-building pose refinement (`orientation.building`); None
            textures with the poses as given (GNSS/INS, calibrated or sequence-oriented).
        max_prior_px: with refinement, a frame whose pose the refinement did not confirm (it
            kept its prior) textures the building only when the prior's a-priori uncertainty,
            projected onto the building, is at most this many pixels (`prior_sigma_px`): a
            texture from a pose metres off is worse than none (inf: always).
    """

    texel: TexelOptions = field(default_factory=TexelOptions)
    visibility: VisibilityOptions = field(default_factory=VisibilityOptions)
    fusion: FusionOptions = field(default_factory=FusionOptions)
    atlas: AtlasOptions = field(default_factory=AtlasOptions)
    anomalies: AnomalyOptions = field(default_factory=AnomalyOptions)
    theme: str = "thermal-ir"
    refine: CoregisterOptions | None = field(default_factory=CoregisterOptions)
    max_prior_px: float = 3.0


class Refiner(Protocol):
    """The per-building pose refinement a unit calls (`orientation.building.refine_building`;
    tests inject another)."""

    def __call__(
        self,
        camera: Camera,
        building: Building,
        raycaster: RayCaster,
        frames: list[int],
        frame_source: FrameSource,
        prior: Mapping[int, Pose],
        accuracy: Accuracy | None,
        *,
        times: Mapping[int, float],
        options: CoregisterOptions,
        sequence: UnitSequence | None,
    ) -> Mapping[int, RefinedPose]: ...


@dataclass(frozen=True, eq=False)
class BuildingUnit:
    """A plain, picklable description of the work on one top-level building.

    Attributes:
        building: the building (with its parts) to texture.
        occluders: neighbouring buildings that can hide parts of it from the frames.
        camera: interior orientation.
        frames: frame indices (into the sequence) that can see the building, recording order.
        poses: prior pose of each of `frames` (world = model CRS).
        times: time stamp of each of `frames`, seconds.
        frame_source: loads frames as float32 physical values.
        radiometry: DN encoding of the input (and of the output tiles).
        accuracy: a-priori GNSS/INS accuracy (weights for refinement), if known.
        options: per-stage options.
        sequence: the sequence orientation's poses, covariances and tracks for `frames`
            (`orientation.block.UnitSequence`), when the orient stage ran: refinement starts there.
    """

    building: Building
    occluders: tuple[Building, ...]
    camera: Camera
    frames: tuple[int, ...]
    poses: tuple[Pose, ...]
    times: tuple[float, ...]
    frame_source: FrameSource
    radiometry: Radiometry
    accuracy: Accuracy | None = None
    options: UnitOptions = field(default_factory=UnitOptions)
    sequence: UnitSequence | None = None

    def __post_init__(self) -> None:
        if not (len(self.frames) == len(self.poses) == len(self.times)):
            raise UnitError(
                f"unit {self.building.id}: frames ({len(self.frames)}), poses ({len(self.poses)}) "
                f"and times ({len(self.times)}) differ in length"
            )


def prior_sigma_px(unit: BuildingUnit, pose: Pose) -> float:
    """A-priori uncertainty (pixels, 1σ) of a prior `pose` projected onto the unit's building:
    `f · (σ_position / distance + σ_attitude)` with the RMS of the accuracy's three components
    (`unit.accuracy`; 1 m and 1° when the sequence states none) and the distance to the
    building's bounding-box centre."""
    acc = unit.accuracy
    sp = float(np.sqrt(np.mean(np.square(acc.position_m)))) if acc is not None else 1.0
    sa_deg = float(np.sqrt(np.mean(np.square(acc.attitude_deg)))) if acc is not None else 1.0
    sa = math.radians(sa_deg)
    lo, hi = unit.building.bounds()
    d = max(float(np.linalg.norm(0.5 * (np.asarray(lo) + np.asarray(hi)) - pose.center)), 1.0)
    return max(unit.camera.fx, unit.camera.fy) * (sp / d + sa)


def withheld_frames(
    unit: BuildingUnit, poses: Mapping[int, Pose], records: tuple[FramePose, ...]
) -> list[int]:
    """Frames that must not texture the building: with refinement on, those that kept a prior
    whose projected uncertainty exceeds `options.max_prior_px` (`prior_sigma_px`)."""
    if unit.options.refine is None or not np.isfinite(unit.options.max_prior_px):
        return []
    kept = {r.frame for r in records if r.status == "prior"}
    limit = unit.options.max_prior_px
    return [f for f in unit.frames if f in kept and prior_sigma_px(unit, poses[f]) > limit]


def refine_unit(
    unit: BuildingUnit, raycaster: RayCaster, refiner: Refiner = refine_building
) -> tuple[dict[int, Pose], tuple[FramePose, ...]]:
    """Refine the unit's poses when its options ask for it (`raycaster`: over the unit's scene,
    `unit_raycaster`).

    Returns the poses to texture with (frame index -> pose) and the per-frame orientation records
    (empty when refinement is off; every frame at its prior when the refiner raised).
    """
    prior = dict(zip(unit.frames, unit.poses, strict=True))
    if unit.options.refine is None:
        return prior, ()
    try:
        refined = refiner(
            unit.camera,
            unit.building,
            raycaster,
            list(unit.frames),
            unit.frame_source,
            prior,
            unit.accuracy,
            times=dict(zip(unit.frames, unit.times, strict=True)),
            options=unit.options.refine,
            sequence=unit.sequence,
        )
    except Exception:  # orientation failed: texture with the priors, say so
        _log.exception("orientation of building %s failed; its prior poses are kept", unit.building.id)
        return prior, tuple(FramePose(f, unit.building.id, prior[f], "prior") for f in unit.frames)
    poses = dict(prior)
    records = []
    for f in unit.frames:
        r = refined.get(f)
        if r is None:
            continue
        if r.status == "refined":
            poses[f] = r.pose
        records.append(
            FramePose(
                frame=f,
                building_id=unit.building.id,
                pose=r.pose if r.status == "refined" else prior[f],
                status=r.status,
                rms_px=float(r.rms_px),
                matches=int(r.matches),
            )
        )
    return poses, tuple(records)


_PERCENTILES = {"p05": 5, "p25": 25, "median": 50, "p75": 75, "p95": 95}


def surface_stats(
    grid: TexelGrid, tex: SurfaceTexture, surface_class: str, resolution_px_per_m: float = float("nan"),
    reason: str = "", analysis: SurfaceAnalysis | None = None,
) -> SurfaceStats:
    """Per-surface statistics of a fused texture (texels inside the polygon only); `reason` says
    why a surface the frames see has no texel observed; `analysis` (the anomaly analysis of the
    texture, if it ran) gives the facade figures."""
    m = grid.mask & tex.observed
    vals = tex.value[m].astype(np.float64)
    temp: dict[str, float] = {}
    if len(vals):
        temp = {"mean": float(vals.mean()), "std": float(vals.std()), "min": float(vals.min())}
        temp["max"] = float(vals.max())
        pct = np.percentile(vals, list(_PERCENTILES.values()))
        temp.update({k: float(v) for k, v in zip(_PERCENTILES, pct, strict=True)})
    nan = float("nan")
    return SurfaceStats(
        polygon_id=grid.polygon_id,
        building_id=grid.building_id,
        surface_class=surface_class,
        texels_total=grid.n_texels,
        texels_observed=int(m.sum()),
        frames_used=tuple(int(f) for f in tex.frames_used(m)),
        mean_resolution_m=float(tex.resolution[m].mean()) if len(vals) else nan,
        mean_view_angle_deg=float(tex.view_angle[m].mean()) if len(vals) else nan,
        temperature=temp,
        resolution_px_per_m=float(resolution_px_per_m),
        best_resolution_m=float(tex.resolution[m].min()) if len(vals) else nan,
        mean_observations=float(tex.count[m].mean()) if len(vals) else nan,
        reason="" if len(vals) else reason,
        **(_figures(analysis) if analysis is not None else {}),
    )


def _figures(a: SurfaceAnalysis) -> dict[str, float | int]:
    """The facade figures of an anomaly analysis, as `SurfaceStats` fields."""
    return {
        "typical": a.typical,
        "spread": a.spread,
        "hot_share": a.hot_share,
        "window_share": a.window_share,
        "heat_loss_index": a.heat_loss_index,
        "windows": sum(1 for x in a.anomalies if x.kind == "window"),
        "leaks": sum(1 for x in a.anomalies if x.kind == "leak"),
    }


def analyse_unit(tex: UnitTextures, options: AnomalyOptions) -> list[SurfaceAnalysis | None]:
    """The anomaly analysis of every fused surface texture of a unit (`anomalies.analyse_building`:
    per polygon, or per facade with `options.facade_grouping`; None each when disabled)."""
    if not options.enabled:
        return [None] * len(tex.grids)
    return list(analyse_building(tex.grids, tex.textures, options))


@dataclass(eq=False)
class UnitTextures:
    """The fused textures of a unit's surfaces before packing (for tests and benches).

    `resolutions` (texels per metre of each grid) and `reasons` (why a polygon the frames see got
    no texel, by polygon id) go into the surface statistics; `rejected`: frames whose
    observations contradicted the other frames' and were dropped (`texture.consistency`)."""

    polygons: list[Polygon]
    grids: list[TexelGrid]
    textures: list[SurfaceTexture]
    timings_s: dict[str, float]
    empty: list[SurfaceStats] = field(default_factory=list)
    resolutions: list[float] = field(default_factory=list)
    reasons: dict[str, str] = field(default_factory=dict)
    rejected: list[int] = field(default_factory=list)


def _reason_untextured(
    sight: SurfaceSight, n_withheld: int, has_grid: bool, max_view_angle_deg: float
) -> str:
    """Why a polygon would get no texel (recorded only when it gets none, `surface_stats`)."""
    if sight.seen:
        if has_grid:
            return "no texel passed the clean-pixel test (too small or thin for the sampling footprint)"
        return "polygon degenerate or smaller than min_area_m2"
    if n_withheld:
        return f"{n_withheld} frames withheld: poses left at priors too uncertain to texture from"
    return sight.reason_unseen(max_view_angle_deg)


def texture_unit(
    unit: BuildingUnit, poses: Mapping[int, Pose], raycaster: RayCaster | None, withheld: Sequence[int] = ()
) -> UnitTextures:
    """Texel grids for every polygon of the unit's building (at the resolution the frames support,
    `texture.sight`) and the textures fused from its frames, but for the `withheld` ones (poses too
    uncertain, `withheld_frames`)."""
    opts = unit.options
    t0 = time.perf_counter()
    skip = set(withheld)
    frames = [f for f in unit.frames if f not in skip]
    owned = [(part.id, poly) for part in unit.building.iter_buildings() for poly in part.polygons]
    sights = surface_sight([p for _, p in owned], unit.camera, [poses[f] for f in frames], raycaster,
                           opts.visibility)  # fmt: skip
    polygons: list[Polygon] = []
    grids: list[TexelGrid] = []
    resolutions: list[float] = []
    empty: list[SurfaceStats] = []
    reasons: dict[str, str] = {}
    for (part_id, poly), sight in zip(owned, sights, strict=True):
        r = opts.texel.resolution_px_per_m
        if opts.texel.follow_frames:
            r = surface_resolution(r, sight.best_resolution_m, opts.texel.oversample)
        grid = texel_grid(poly, part_id, replace(opts.texel, resolution_px_per_m=r))
        reason = _reason_untextured(sight, len(skip), grid is not None, opts.visibility.max_view_angle_deg)
        if grid is None:
            empty.append(SurfaceStats(poly.id, part_id, poly.surface_class, 0, 0, reason=reason))
            continue
        polygons.append(poly)
        grids.append(grid)
        resolutions.append(r)
        reasons[poly.id] = reason
    surfaces = [SurfaceTexels.of(g) for g in grids]
    if raycaster is not None:  # texels covered by a touching building (shared walls) are never seen
        surfaces = [s.without(buried_texels(raycaster, s.points, s.grid.normal)) for s in surfaces]
    scene = None
    if raycaster is not None:  # the ray caster is over the unit's scene (`unit_raycaster`)
        scene = OcclusionScene(raycaster, unit.camera, opts.visibility, [unit.building, *unit.occluders])
    textures = [SurfaceTexture.empty(g.shape, opts.fusion.fused) for g in grids]
    t_grid = time.perf_counter() - t0
    t_load = 0.0
    t_tex = 0.0
    for f in frames:
        t1 = time.perf_counter()
        image = unit.frame_source.load(f)
        t2 = time.perf_counter()
        texture_frame(
            image, unit.camera, poses[f], f, surfaces, textures, scene, opts.visibility, opts.fusion
        )
        t_load += t2 - t1
        t_tex += time.perf_counter() - t2
    t1 = time.perf_counter()
    rejected = reject_inconsistent_frames(textures, opts.fusion.consistency)
    t_tex += time.perf_counter() - t1
    timings = {"grid": t_grid, "decode": t_load, "texture": t_tex}
    return UnitTextures(polygons=polygons, grids=grids, textures=textures, timings_s=timings, empty=empty,
                        resolutions=resolutions, reasons=reasons, rejected=rejected)  # fmt: skip


class HeldFrames:
    """A unit's `FrameSource` that loads each frame once from `source` and holds it for the
    unit's run: the refinement loads all of the unit's frames and holds them anyway
    (`orientation.building`), and texturing then reads the same arrays instead of loading
    (converting, copying) every frame a second time. Callers must not write into the frames."""

    def __init__(self, source: FrameSource) -> None:
        self.source = source
        self.frames: dict[int, np.ndarray] = {}

    def load(self, index: int) -> np.ndarray:
        """Frame `index` `(H, W)` float32 physical values, loaded on the first call."""
        image = self.frames.get(index)
        if image is None:
            image = self.frames[index] = self.source.load(index)
        return image


def unit_raycaster(unit: BuildingUnit) -> RayCaster:
    """A ray caster over the unit's scene: its building and its occluders (world = model CRS)."""
    return RayCaster(build_scene_mesh([unit.building, *unit.occluders]))


def run_building_unit(unit: BuildingUnit, refiner: Refiner = refine_building) -> BuildingResult:
    """Run one building unit: refine its poses (unless `options.refine` is None), extract and
    fuse the textures of its surfaces, pack them into atlas tiles. Pure: reads frames through
    `unit.frame_source` (with refinement each frame once, `HeldFrames`), writes nothing."""
    if unit.options.refine is not None:
        unit = replace(unit, frame_source=HeldFrames(unit.frame_source))
    t0 = time.perf_counter()
    raycaster = unit_raycaster(unit)
    t_scene = time.perf_counter() - t0
    t0 = time.perf_counter()
    poses, records = refine_unit(unit, raycaster, refiner)
    withheld = withheld_frames(unit, poses, records)
    t_orient = time.perf_counter() - t0
    tex = texture_unit(unit, poses, raycaster, withheld)
    t0 = time.perf_counter()
    tiles, appearance = build_atlas(
        unit.building.id,
        tex.polygons,
        tex.grids,
        [t.value for t in tex.textures],
        unit.radiometry,
        unit.options.theme,
        unit.options.atlas,
    )
    t_atlas = time.perf_counter() - t0
    t0 = time.perf_counter()
    analyses = analyse_unit(tex, unit.options.anomalies)
    t_anomalies = time.perf_counter() - t0
    by_id = {
        g.polygon_id: surface_stats(g, t, p.surface_class, r, tex.reasons.get(p.id, ""), a)
        for p, g, t, r, a in zip(
            tex.polygons, tex.grids, tex.textures, tex.resolutions, analyses, strict=True
        )
    }
    by_id.update({s.polygon_id: s for s in tex.empty})
    stats = tuple(by_id[p.id] for p in unit.building.iter_polygons() if p.id in by_id)
    timings = {"scene": t_scene, "orient": t_orient, **tex.timings_s, "atlas": t_atlas}
    timings["anomalies"] = t_anomalies
    anomalies = tuple(x for a in analyses if a is not None for x in a.anomalies)
    return BuildingResult(
        building_id=unit.building.id,
        appearance=appearance,
        tiles=tiles,
        radiometry=unit.radiometry,
        surfaces=stats,
        poses=records,
        anomalies=anomalies,
        timings_s=timings,
        frames_withheld=tuple(withheld),
        frames_rejected=tuple(tex.rejected),
    )

"""The building unit: the unit of work of a texturing job, run alike in a local process pool
(`citytherm run`) and as one Celery task per building (the service).

In: buildings (model CRS, metres), the camera, one prior `Pose` per frame (world = model CRS),
a picklable `FrameSource` (float32 physical frames), the radiometry and options.
Out: `plan_units` -> picklable `BuildingUnit`s (which frames see which building, which neighbours
can occlude it); `run_building_unit(unit)` -> `results.BuildingResult` (poses, atlas tiles with
texture coordinates, per-surface statistics, timings). A unit keeps no global state and writes
no files.
"""

from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building, Polygon
from workers.pipeline.geometry.manifest import Accuracy, FrameSource, Radiometry
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
from workers.pipeline.results import BuildingResult, FramePose, SurfaceStats
from workers.pipeline.texture.atlas import AtlasOptions, build_atlas
from workers.pipeline.texture.fusion import FusionOptions, SurfaceTexels, SurfaceTexture, texture_frame
from workers.pipeline.texture.texel import TexelGrid, TexelOptions, texel_grid
from workers.pipeline.texture.visibility import (
    OcclusionScene,
    VisibilityOptions,
    boxes_in_frustum,
    buried_texels,
    pixel_rays,
)

if TYPE_CHECKING:  # the orientation modules are optional: only their types are named here
    from workers.pipeline.orientation.block import UnitSequence
    from workers.pipeline.orientation.sequence import SequenceOrientation

_log = logging.getLogger(__name__)


class UnitError(ValueError):
    """Inconsistent input to planning or running building units."""


@dataclass(frozen=True)
class PlanOptions:
    """Options of the planning stage.

    Attributes:
        max_distance_m: frames farther than this from a building's box do not see it.
        occluder_margin_m: a neighbour is an occluder candidate when its box meets the box spanned
            by the building and the projection centres that see it, grown by this margin.
        min_frames: buildings seen by fewer frames get no unit.
        ray_step_px: after the box test, rays through every `ray_step_px`-th pixel (in both
            directions) are cast through the candidate buildings; a frame sees a building only
            when at least `min_ray_hits` of them hit it first (0: box test only).
        adjacency_m: buildings whose boxes come this close are always each other's occluders
            (shared walls).
    """

    max_distance_m: float = 300.0
    occluder_margin_m: float = 1.0
    min_frames: int = 1
    ray_step_px: int = 8
    min_ray_hits: int = 2
    adjacency_m: float = 0.5


@dataclass(frozen=True)
class UnitOptions:
    """Everything that steers a building unit, one frozen options object per stage.

    Attributes:
        theme: appearance theme of the textures.
        refine: refine the poses against the building (orientation module) before texturing.
        refine_options: options object of the orientation module (None: its defaults).
    """

    texel: TexelOptions = field(default_factory=TexelOptions)
    visibility: VisibilityOptions = field(default_factory=VisibilityOptions)
    fusion: FusionOptions = field(default_factory=FusionOptions)
    atlas: AtlasOptions = field(default_factory=AtlasOptions)
    theme: str = "thermal-ir"
    refine: bool = False
    refine_options: object | None = None


@dataclass(frozen=True)
class ArrayFrameSource:
    """An in-memory `FrameSource`: frame index -> `(H, W)` float32 physical values (tests, demos)."""

    frames: Mapping[int, np.ndarray]

    def load(self, index: int) -> np.ndarray:
        """Frame `index` as float32."""
        return np.asarray(self.frames[index], dtype=np.float32)


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
            (`coregister_block.UnitSequence`), when the orient stage ran: refinement starts there.
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


def plan_units(
    buildings: Sequence[Building],
    camera: Camera,
    poses: Sequence[Pose],
    frame_source: FrameSource,
    radiometry: Radiometry,
    *,
    times: Sequence[float] | None = None,
    frame_indices: Sequence[int] | None = None,
    accuracy: Accuracy | None = None,
    options: UnitOptions = UnitOptions(),
    plan: PlanOptions = PlanOptions(),
    targets: Sequence[str] | None = None,
    sequence: SequenceOrientation | None = None,
) -> list[BuildingUnit]:
    """Decide which frames see which building and which neighbours can occlude it.

    Args:
        buildings: all top-level buildings of the model (occluders are taken from them).
        poses: one prior pose per frame, recording order; `frame_indices` gives their indices
            (default `0..N-1`), `times` their stamps (default the indices).
        targets: ids of the buildings to make units for (default all).
        sequence: the orient stage's result; each unit gets its part (`for_frames`).

    Returns one unit per target building seen by at least `plan.min_frames` frames, in the
    order of `buildings`. The test per frame is a conservative bounding-box frustum test, then a
    sparse grid of pixel rays cast through the candidate buildings.
    """
    n = len(poses)
    idx = list(range(n)) if frame_indices is None else [int(i) for i in frame_indices]
    stamps = [float(i) for i in idx] if times is None else [float(t) for t in times]
    if len(idx) != n or len(stamps) != n:
        raise UnitError(f"poses ({n}), frame_indices ({len(idx)}) and times ({len(stamps)}) differ in length")
    if not buildings:
        return []
    bounds = [b.bounds() for b in buildings]
    lo = np.stack([b[0] for b in bounds])
    hi = np.stack([b[1] for b in bounds])
    vis_opts = VisibilityOptions(
        margin_px=options.visibility.margin_px,
        min_depth_m=options.visibility.min_depth_m,
        max_distance_m=min(plan.max_distance_m, options.visibility.max_distance_m),
    )
    sees = np.zeros((n, len(buildings)), dtype=bool)
    for f, pose in enumerate(poses):
        sees[f] = boxes_in_frustum(camera, pose, lo, hi, vis_opts)
    boxes = sees.copy()  # conservative: occluder candidates
    if plan.ray_step_px > 0 and sees.any():
        sees &= _ray_sees(buildings, camera, poses, sees, vis_opts.max_distance_m, plan)
    wanted = None if targets is None else set(targets)
    if wanted is not None:
        missing = wanted - {b.id for b in buildings}
        if missing:
            raise UnitError(f"buildings not in the model: {', '.join(sorted(missing))}")
    units: list[BuildingUnit] = []
    centers = np.stack([p.center for p in poses]) if n else np.zeros((0, 3))
    for k, b in enumerate(buildings):
        if wanted is not None and b.id not in wanted:
            continue
        fr = np.nonzero(sees[:, k])[0]
        if len(fr) < plan.min_frames or len(fr) == 0:
            continue
        # occluders: in the frustum of one of these frames and meeting the box spanned by the building
        # and the projection centres that see it; plus the buildings it touches
        span_lo = np.minimum(lo[k], centers[fr].min(axis=0)) - plan.occluder_margin_m
        span_hi = np.maximum(hi[k], centers[fr].max(axis=0)) + plan.occluder_margin_m
        meets = np.all((lo <= span_hi) & (hi >= span_lo), axis=1) & boxes[fr].any(axis=0)
        meets |= np.all((lo <= hi[k] + plan.adjacency_m) & (hi >= lo[k] - plan.adjacency_m), axis=1)
        meets[k] = False
        units.append(
            BuildingUnit(
                building=b,
                occluders=tuple(buildings[j] for j in np.nonzero(meets)[0]),
                camera=camera,
                frames=tuple(idx[f] for f in fr),
                poses=tuple(poses[f] for f in fr),
                times=tuple(stamps[f] for f in fr),
                frame_source=frame_source,
                radiometry=radiometry,
                accuracy=accuracy,
                options=options,
                sequence=None if sequence is None else sequence.for_frames([idx[f] for f in fr]),
            )
        )
    return units


def _ray_sees(
    buildings: Sequence[Building],
    camera: Camera,
    poses: Sequence[Pose],
    candidates: np.ndarray,
    max_distance_m: float,
    plan: PlanOptions,
) -> np.ndarray:
    """`(F, B)` bool: frame f sees building b with at least `plan.min_ray_hits` first hits of a
    sparse grid of pixel rays cast through the candidate buildings (`candidates (F, B)`)."""
    ids = np.nonzero(candidates.any(axis=0))[0]
    mesh = build_scene_mesh([buildings[j] for j in ids])
    caster = RayCaster(mesh)
    local = {buildings[j].id: j for j in ids}
    poly_building = np.array([local[b] for b in mesh.polygon_building], dtype=np.intp)
    step = plan.ray_step_px
    rays = pixel_rays(camera)[step // 2 :: step, step // 2 :: step].reshape(-1, 3).astype(np.float64)
    out = np.zeros_like(candidates)
    for f, pose in enumerate(poses):
        if not candidates[f].any():
            continue
        hits = caster.cast(np.broadcast_to(pose.center, rays.shape), rays @ pose.R_world_from_cam.T)
        ok = (hits.polygon >= 0) & (hits.t <= max_distance_m)
        counts = np.bincount(poly_building[hits.polygon[ok]], minlength=len(buildings))
        out[f] = counts >= plan.min_ray_hits
    return out


def _refine(unit: BuildingUnit, raycaster: RayCaster) -> tuple[dict[int, Pose], tuple[FramePose, ...]]:
    """Refine the unit's poses with the orientation module when it is there and asked for.

    Returns the poses to texture with (frame index -> pose) and the per-frame orientation records
    (empty when refinement did not run).
    """
    prior = dict(zip(unit.frames, unit.poses, strict=True))
    if not unit.options.refine:
        return prior, ()
    try:
        coregister = importlib.import_module("workers.pipeline.orientation.building")
    except ImportError:
        return prior, ()
    extra = {} if unit.options.refine_options is None else {"options": unit.options.refine_options}
    try:
        refined = _call_refine(coregister, unit, raycaster, prior, extra)
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


def _call_refine(
    coregister: object, unit: BuildingUnit, raycaster: RayCaster, prior: dict[int, Pose], extra: dict
) -> Mapping[int, object]:
    """`coregister.refine_building` for the unit's frames."""
    if unit.sequence is not None:
        extra = {**extra, "sequence": unit.sequence}
    return coregister.refine_building(  # type: ignore[attr-defined]
        unit.camera,
        unit.building,
        raycaster,
        list(unit.frames),
        unit.frame_source,
        prior,
        unit.accuracy,
        times=dict(zip(unit.frames, unit.times, strict=True)),
        **extra,
    )


_PERCENTILES = {"p05": 5, "p25": 25, "median": 50, "p75": 75, "p95": 95}


def surface_stats(grid: TexelGrid, tex: SurfaceTexture, surface_class: str) -> SurfaceStats:
    """Per-surface statistics of a fused texture (texels inside the polygon only)."""
    m = grid.mask & tex.observed
    vals = tex.value[m].astype(np.float64)
    temp: dict[str, float] = {}
    if len(vals):
        temp = {"mean": float(vals.mean()), "std": float(vals.std()), "min": float(vals.min())}
        temp["max"] = float(vals.max())
        pct = np.percentile(vals, list(_PERCENTILES.values()))
        temp.update({k: float(v) for k, v in zip(_PERCENTILES, pct, strict=True)})
    return SurfaceStats(
        polygon_id=grid.polygon_id,
        building_id=grid.building_id,
        surface_class=surface_class,
        texels_total=grid.n_texels,
        texels_observed=int(m.sum()),
        frames_used=tuple(int(f) for f in np.unique(tex.frame[m])),
        mean_resolution_m=float(tex.resolution[m].mean()) if len(vals) else float("nan"),
        mean_view_angle_deg=float(tex.view_angle[m].mean()) if len(vals) else float("nan"),
        temperature=temp,
    )


@dataclass(eq=False)
class UnitTextures:
    """The fused textures of a unit's surfaces before packing (for tests and benches)."""

    polygons: list[Polygon]
    grids: list[TexelGrid]
    textures: list[SurfaceTexture]
    timings_s: dict[str, float]
    empty: list[SurfaceStats] = field(default_factory=list)


def texture_unit(unit: BuildingUnit, poses: Mapping[int, Pose], raycaster: RayCaster | None) -> UnitTextures:
    """Texel grids for every polygon of the unit's building and the textures fused from its frames."""
    opts = unit.options
    t0 = time.perf_counter()
    polygons: list[Polygon] = []
    grids: list[TexelGrid] = []
    empty: list[SurfaceStats] = []
    for part in unit.building.iter_buildings():
        for poly in part.polygons:
            grid = texel_grid(poly, part.id, opts.texel)
            if grid is None:
                empty.append(SurfaceStats(poly.id, part.id, poly.surface_class, 0, 0))
                continue
            polygons.append(poly)
            grids.append(grid)
    surfaces = [SurfaceTexels.of(g) for g in grids]
    if raycaster is not None:  # texels covered by a touching building (shared walls) are never seen
        surfaces = [s.without(buried_texels(raycaster, s.points, s.grid.normal)) for s in surfaces]
    scene = OcclusionScene(raycaster, unit.camera, opts.visibility) if raycaster is not None else None
    textures = [SurfaceTexture.empty(g.shape) for g in grids]
    t_grid = time.perf_counter() - t0
    t_load = 0.0
    t_tex = 0.0
    for f in unit.frames:
        t1 = time.perf_counter()
        image = unit.frame_source.load(f)
        t2 = time.perf_counter()
        texture_frame(
            image, unit.camera, poses[f], f, surfaces, textures, scene, opts.visibility, opts.fusion
        )
        t_load += t2 - t1
        t_tex += time.perf_counter() - t2
    timings = {"grid": t_grid, "decode": t_load, "texture": t_tex}
    return UnitTextures(polygons=polygons, grids=grids, textures=textures, timings_s=timings, empty=empty)


def run_building_unit(unit: BuildingUnit) -> BuildingResult:
    """Run one building unit: (optionally) refine its poses, extract and fuse the textures of its
    surfaces, pack them into atlas tiles. Pure: reads frames through `unit.frame_source`, writes
    nothing."""
    t0 = time.perf_counter()
    mesh = build_scene_mesh([unit.building, *unit.occluders])
    raycaster = RayCaster(mesh)
    t_scene = time.perf_counter() - t0
    t0 = time.perf_counter()
    poses, records = _refine(unit, raycaster)
    t_orient = time.perf_counter() - t0
    tex = texture_unit(unit, poses, raycaster)
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
    by_id = {
        g.polygon_id: surface_stats(g, t, p.surface_class)
        for p, g, t in zip(tex.polygons, tex.grids, tex.textures, strict=True)
    }
    by_id.update({s.polygon_id: s for s in tex.empty})
    stats = tuple(by_id[p.id] for p in unit.building.iter_polygons() if p.id in by_id)
    timings = {"scene": t_scene, "orient": t_orient, **tex.timings_s, "atlas": t_atlas}
    return BuildingResult(
        building_id=unit.building.id,
        appearance=appearance,
        tiles=tiles,
        radiometry=unit.radiometry,
        surfaces=stats,
        poses=records,
        timings_s=timings,
    )

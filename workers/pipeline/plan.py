"""Planning a job: which buildings the cameras come near, which frames see which building, which
neighbours can occlude it; the building units that result.

In: the buildings of the model (model CRS, metres), the camera, one pose per frame (world = model
CRS), the frames (`FrameSource`), the output radiometry and the units' options. Out:
`near_buildings` -> the buildings within reach of the projection centres (streamed: memory
follows the drive, not the city); `plan_units` -> picklable `units.BuildingUnit`s, one per
building seen; `resolution_warning` -> a message when the texel resolution asks for more than
the frames can give.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.manifest import Accuracy, FrameSource, Radiometry
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster, build_scene_mesh
from workers.pipeline.orientation.sequence import SequenceOrientation
from workers.pipeline.texture.visibility import VisibilityOptions, boxes_in_frustum, pixel_rays
from workers.pipeline.units import BuildingUnit, UnitError, UnitOptions


@dataclass(frozen=True)
class PlanOptions:
    """Options of the planning stage.

    Attributes:
        max_distance_m: frames farther than this from a building's box do not see it (800 m:
            a 200 m high flight looking 45° down sees 520 m far at the top of its frames; the
            default camera resolves 1 m there; surfaces get the texel size the frames support).
        occluder_margin_m: a neighbour is an occluder candidate when its box meets the box spanned
            by the building and the projection centres that see it, grown by this margin.
        min_frames: buildings seen by fewer frames get no unit.
        ray_step_px: after the box test, rays through every `ray_step_px`-th pixel (in both
            directions) are cast through the candidate buildings; a frame sees a building only
            when at least `min_ray_hits` of them hit it first (0: box test only).
        glimpse_step_px: a building that some of those rays hit, but never `min_ray_hits` in one
            frame (a small or far building seen through a few pixels), is tested again with rays
            through every `glimpse_step_px`-th pixel of its projected box, in the frames whose
            rays hit it; 0: no second test (such a building gets no unit).
        adjacency_m: buildings whose boxes come this close are always each other's occluders
            (shared walls).
    """

    max_distance_m: float = 800.0
    occluder_margin_m: float = 1.0
    min_frames: int = 1
    ray_step_px: int = 8
    min_ray_hits: int = 2
    glimpse_step_px: int = 4
    adjacency_m: float = 0.5



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
    sparse grid of pixel rays cast through the candidate buildings (`candidates (F, B)`); a
    building glimpsed by fewer in every frame is counted again on a denser grid over its box
    (`PlanOptions.glimpse_step_px`)."""
    ids = np.nonzero(candidates.any(axis=0))[0]
    mesh = build_scene_mesh([buildings[j] for j in ids])
    caster = RayCaster(mesh)
    local = {buildings[j].id: j for j in ids}
    poly_building = np.array([local[b] for b in mesh.polygon_building], dtype=np.intp)
    step = plan.ray_step_px
    rays = pixel_rays(camera)[step // 2 :: step, step // 2 :: step].reshape(-1, 3).astype(np.float64)
    counts = np.zeros(candidates.shape, np.int64)
    for f, pose in enumerate(poses):
        if not candidates[f].any():
            continue
        hits = caster.cast(np.broadcast_to(pose.center, rays.shape), rays @ pose.R_world_from_cam.T)
        ok = (hits.polygon >= 0) & (hits.t <= max_distance_m)
        counts[f] = np.bincount(poly_building[hits.polygon[ok]], minlength=len(buildings))
    out = counts >= plan.min_ray_hits
    glimpsed = np.flatnonzero((counts.max(axis=0) > 0) & ~out.any(axis=0))
    if plan.glimpse_step_px > 0 and len(glimpsed):
        out |= _glimpses(
            buildings, camera, poses, counts, glimpsed, caster, poly_building, max_distance_m, plan
        )
    return out


def _glimpses(
    buildings: Sequence[Building],
    camera: Camera,
    poses: Sequence[Pose],
    counts: np.ndarray,
    glimpsed: np.ndarray,
    caster: RayCaster,
    poly_building: np.ndarray,
    max_distance_m: float,
    plan: PlanOptions,
) -> np.ndarray:
    """`(F, B)` bool: frame f sees building b (one of `glimpsed`, hit by some of the sparse rays,
    `counts (F, B)`, but never `plan.min_ray_hits` times in a frame) with at least
    `plan.min_ray_hits` first hits of rays through every `plan.glimpse_step_px`-th pixel inside
    the image box of its bounding box's corners, in the frames whose sparse rays hit it. Cheap: a
    few small, far buildings, and only their own pixels."""
    out = np.zeros(counts.shape, bool)
    step = plan.glimpse_step_px
    all_rays = pixel_rays(camera)
    W, H = camera.width, camera.height
    for b in glimpsed:
        lo, hi = buildings[b].bounds()
        corners = np.array(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij")).reshape(3, -1).T
        for f in np.flatnonzero(counts[:, b] > 0):
            pose = poses[f]
            uv, depth = pose.project(camera, corners)
            if np.all(depth > 0) and np.all(np.isfinite(uv)):
                u0, v0 = np.clip(np.floor(uv.min(axis=0)).astype(int), 0, [W - 1, H - 1])
                u1, v1 = np.clip(np.ceil(uv.max(axis=0)).astype(int), 0, [W - 1, H - 1])
            else:  # a corner behind the camera: the whole frame
                u0, v0, u1, v1 = 0, 0, W - 1, H - 1
            # the dense grid's pixels inside the box (aligned with the image, not the box)
            us = np.arange(step // 2, W, step)
            vs = np.arange(step // 2, H, step)
            us, vs = us[(us >= u0) & (us <= u1)], vs[(vs >= v0) & (vs <= v1)]
            if len(us) == 0 or len(vs) == 0:
                continue
            rays = all_rays[vs[:, None], us[None, :]].reshape(-1, 3).astype(np.float64)
            hits = caster.cast(np.broadcast_to(pose.center, rays.shape), rays @ pose.R_world_from_cam.T)
            ok = (hits.polygon >= 0) & (hits.t <= max_distance_m)
            out[f, b] = int(np.sum(poly_building[hits.polygon[ok]] == b)) >= plan.min_ray_hits
    return out


def near_buildings(
    buildings: Iterable[Building], priors: Sequence[Pose], reach_m: float
) -> tuple[list[Building], set[str]]:
    """The buildings whose bounding box comes within `reach_m` of a projection centre, in input
    order, and the ids of all buildings seen (to check requested ids). `buildings` is consumed
    once (a stream from the CityGML reader)."""
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


def resolution_warning(units: Sequence[BuildingUnit], camera: Camera, options: UnitOptions) -> str | None:
    """A warning when the frames are too far from the buildings for the texel resolution: most
    observations would be coarser than `visibility.max_texel_ratio` texels per pixel and be
    dropped. The typical ground resolution (m/px) is the median over the units' frames at the
    nearest point of the building's box, head-on: a best case."""
    res = []
    for u in units:
        lo, hi = u.building.bounds()
        for p in u.poses:
            distance = float(np.linalg.norm(np.clip(p.center, lo, hi) - p.center))
            res.append(distance / max(camera.fx, camera.fy))
    if not res:
        return None
    typical = float(np.median(res))
    ratio = options.visibility.max_texel_ratio
    resolution = options.texel.resolution_px_per_m
    if typical > ratio / resolution:
        suggest = max(0.5, round(ratio / typical / 2, 1))
        return (
            f"the frames see the buildings at about {typical:.2f} m per pixel at best: at "
            f"{resolution:g} texels/m most observations are too coarse to use; "
            f"try --resolution {suggest:g}"
        )
    return None

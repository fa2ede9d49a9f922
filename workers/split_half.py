"""The split-half check of a texturing job (`citytherm run --split-half`): texture quality without
ground truth.

After the building units have run, each unit is textured twice more: once from its even frames
and once from its odd frames (alternate frames of those that see the building, in recording
order: the 1st, 3rd, ... and the 2nd, 4th, ...), both with the poses the unit textured with
(refined where its refinement accepted them, else its priors) and refinement off. The two
half-textures of every surface lie on one texel grid (the delivered texture's; where the texture
stage lays a surface's grid from what the frames see and one half sees it more coarsely, the
coarser grid that half supports) and are compared by
`workers.pipeline.texture.split_half.split_half_agreement` (per-tile sub-texel shift, value
difference). Nothing of this touches the job's outputs: only `report.json` gets the
`split_half` block (`split_half_report`).

In: the planned `BuildingUnit`s and the units' `BuildingResult`s (tile pixels may be dropped:
only `poses` is read). Out: `UnitSplitHalf` per unit, and the JSON block.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from workers.pipeline.geometry.citymodel import Building, Polygon
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.results import BuildingResult
from workers.pipeline.texture.split_half import (
    SplitHalfOptions,
    SurfaceAgreement,
    split_half_agreement,
    summarize,
)
from workers.pipeline.texture.texel import TexelGrid
from workers.pipeline.units import BuildingUnit, UnitTextures, texture_unit, unit_raycaster
from workers.pool import pool_context

#: how the frames are split, as `report.json` states it
HALVES = "alternate frames of each building's frames, recording order: even 1st, 3rd, ...; odd 2nd, 4th, ..."


@dataclass(frozen=True, eq=False)
class SurfaceSplit:
    """One surface's split-half comparison: polygon id, its building (part) id and class, and
    the comparison (`a` = even half, `b` = odd half)."""

    polygon_id: str
    building_id: str
    surface_class: str
    agreement: SurfaceAgreement


@dataclass(frozen=True, eq=False)
class UnitSplitHalf:
    """The split-half check of one building unit.

    Attributes:
        building_id: the top-level building.
        frames_even, frames_odd: frames in each half.
        surfaces: the surfaces both halves observe (at least one texel in common), model order.
        seconds: wall time of the two texturings and the comparison.
        error: why the check failed (None: it ran).
    """

    building_id: str
    frames_even: int
    frames_odd: int
    surfaces: tuple[SurfaceSplit, ...] = ()
    seconds: float = 0.0
    error: str | None = None


def textured_poses(unit: BuildingUnit, result: BuildingResult | None) -> dict[int, Pose]:
    """The poses `run_building_unit` textured `unit` with: frame index -> pose (world = model
    CRS); the refined pose where `result.poses` says `"refined"`, the unit's prior elsewhere
    (`units.refine_unit`'s rule)."""
    poses = dict(zip(unit.frames, unit.poses, strict=True))
    for p in result.poses if result is not None else ():
        if p.status == "refined" and p.frame in poses:
            poses[p.frame] = p.pose
    return poses


def _with_frames(unit: BuildingUnit, keep: Sequence[int], poses: Mapping[int, Pose]) -> BuildingUnit:
    """`unit` with only its frames at positions `keep`, the given `poses` as their priors,
    refinement off and no sequence orientation: it textures exactly with those poses."""
    frames = tuple(unit.frames[k] for k in keep)
    return replace(
        unit,
        frames=frames,
        poses=tuple(poses[f] for f in frames),
        times=tuple(unit.times[k] for k in keep),
        options=replace(unit.options, refine=None),
        sequence=None,
    )


def half_unit(unit: BuildingUnit, parity: int, poses: Mapping[int, Pose]) -> BuildingUnit:
    """`unit` restricted to its even (`parity` 0) or odd (1) frames (alternate frames of
    `unit.frames`), with the given `poses` (see `_with_frames`)."""
    return _with_frames(unit, range(parity, len(unit.frames), 2), poses)


def _textures(unit: BuildingUnit, caster: RayCaster) -> UnitTextures:
    """`texture_unit` of a half unit with its own poses (its priors)."""
    return texture_unit(unit, dict(zip(unit.frames, unit.poses, strict=True)), caster)


def _only(building: Building, ids: Collection[str]) -> Building:
    """`building` with only the polygons `ids` (parts kept, their polygons filtered alike)."""
    return replace(
        building,
        polygons=tuple(p for p in building.polygons if p.id in ids),
        parts=tuple(_only(part, ids) for part in building.parts),
    )


def _grids_alike(a: TexelGrid, b: TexelGrid) -> bool:
    """True when two grids of one polygon are the same raster (shape, texel size, corner)."""
    return a.shape == b.shape and math.isclose(a.size, b.size, rel_tol=1e-9) and bool(
        np.allclose(a.corner, b.corner, rtol=0.0, atol=1e-6 * a.size)
    )


def _pairs(
    even: BuildingUnit, odd: BuildingUnit, caster: RayCaster
) -> Iterator[tuple[Polygon, TexelGrid, np.ndarray, np.ndarray]]:
    """Per polygon of the unit's building that both halves texture: `(polygon, grid, even
    values, odd values)` on one grid, values `(H, W)` float32 K with NaN outside the polygon and
    where unobserved.

    The texture stage may lay a surface's grid from what the frames see (a surface seen only
    coarsely gets coarser texels, `TexelOptions`): where the halves' grids of a polygon differ,
    both are textured again at the coarser of the two resolutions (polygons grouped by it; the
    rest of the building still occludes through `caster`), which both halves then support.
    """
    te, to = _textures(even, caster), _textures(odd, caster)
    odd_by_id = {p.id: (g, t) for p, g, t in zip(to.polygons, to.grids, to.textures, strict=True)}
    again: dict[float, list[str]] = {}
    for poly, ge, tex_e in zip(te.polygons, te.grids, te.textures, strict=True):
        if poly.id not in odd_by_id:
            continue
        go, tex_o = odd_by_id[poly.id]
        if _grids_alike(ge, go):
            yield poly, ge, tex_e.value, tex_o.value
        else:
            again.setdefault(1.0 / max(ge.size, go.size), []).append(poly.id)
    for resolution, ids in again.items():
        texel = replace(even.options.texel, resolution_px_per_m=resolution)
        units = [replace(u, building=_only(u.building, set(ids)), options=replace(u.options, texel=texel))
                 for u in (even, odd)]  # fmt: skip
        te, to = _textures(units[0], caster), _textures(units[1], caster)
        for poly, ge, go, tex_e, tex_o in zip(te.polygons, te.grids, to.grids, te.textures, to.textures,
                                              strict=True):  # fmt: skip
            if _grids_alike(ge, go):
                yield poly, ge, tex_e.value, tex_o.value


def compare_halves(
    unit: BuildingUnit,
    poses: Mapping[int, Pose],
    odd_poses: Mapping[int, Pose] | None = None,
    options: SplitHalfOptions | None = None,
) -> UnitSplitHalf:
    """Texture `unit`'s even and odd frames separately and compare every surface.

    Args:
        unit: a planned building unit (its options steer the texture stages; refinement is off
            for the halves).
        poses: frame index -> pose for the even half (and the odd one unless `odd_poses`),
            world = model CRS.
        odd_poses: other poses for the odd half (tests: a deliberately biased half).
        options: comparison thresholds (`SplitHalfOptions()` when None).

    Returns:
        The comparison of every surface both halves observe (`a` = even, `b` = odd: shifts are
        the odd half's against the even half's, in texels of the grid both share: the
        delivered texture's, or the coarser one a half supports, `_pairs`).
    """
    t0 = time.perf_counter()
    opts = options if options is not None else SplitHalfOptions()
    even = half_unit(unit, 0, poses)
    odd = half_unit(unit, 1, odd_poses if odd_poses is not None else poses)
    if not even.frames or not odd.frames:
        return UnitSplitHalf(unit.building.id, len(even.frames), len(odd.frames))
    found = {}
    for poly, grid, ve, vo in _pairs(even, odd, unit_raycaster(unit)):
        a = np.where(grid.mask, ve, np.nan).astype(np.float32)
        b = np.where(grid.mask, vo, np.nan).astype(np.float32)
        if (np.isfinite(a) & np.isfinite(b)).any():
            agreement = split_half_agreement(a, b, grid.size, options=opts)
            found[poly.id] = SurfaceSplit(poly.id, grid.building_id, poly.surface_class, agreement)
    return UnitSplitHalf(
        building_id=unit.building.id,
        frames_even=len(even.frames),
        frames_odd=len(odd.frames),
        surfaces=tuple(found[p.id] for p in unit.building.iter_polygons() if p.id in found),
        seconds=time.perf_counter() - t0,
    )


def split_half_unit(
    unit: BuildingUnit, result: BuildingResult | None, options: SplitHalfOptions | None = None
) -> UnitSplitHalf:
    """`compare_halves` with the frames and poses the unit textured with (`textured_poses`,
    without the frames it withheld); an exception is returned as `error` (one building must not
    sink the check)."""
    try:
        poses = textured_poses(unit, result)
        withheld = set(result.frames_withheld) if result is not None else set()
        if withheld:
            unit = _with_frames(unit, [k for k, f in enumerate(unit.frames) if f not in withheld], poses)
        return compare_halves(unit, poses, options=options)
    except Exception as exc:  # reported in report.json
        n = len(unit.frames)
        return UnitSplitHalf(unit.building.id, (n + 1) // 2, n // 2, error=f"{type(exc).__name__}: {exc}")


def unit_block(u: UnitSplitHalf) -> dict[str, Any]:
    """`report.json` entry of one building: `summarize` over its surfaces, frames per half, and
    per surface (`id`, `building`, `class`, `texel_size_m`, `summarize` of that surface)."""
    doc: dict[str, Any] = {"id": u.building_id, "frames_even": u.frames_even, "frames_odd": u.frames_odd}
    if u.error is not None:
        return {**doc, "error": u.error}
    doc.update(summarize(s.agreement for s in u.surfaces))
    doc["seconds"] = round(u.seconds, 3)
    doc["surfaces"] = [
        {"id": s.polygon_id, "building": s.building_id, "class": s.surface_class,
         "texel_size_m": s.agreement.texel_size_m, **s.agreement.to_dict()}
        for s in u.surfaces
    ]
    return doc


def job_block(checks: Sequence[UnitSplitHalf], options: SplitHalfOptions) -> dict[str, Any]:
    """The `report.json` `split_half` block: the job's `summarize` over every surface of every
    building, how the halves were made, the options, and one entry per building
    (`unit_block`)."""
    ok = [c for c in checks if c.error is None]
    return {
        "run": True,
        "halves": HALVES,
        "options": dataclasses.asdict(options),
        **summarize(s.agreement for c in ok for s in c.surfaces),
        "buildings": [unit_block(c) for c in checks],
    }


def _run_pool(
    pairs: Sequence[tuple[BuildingUnit, BuildingResult | None]], workers: int, options: SplitHalfOptions
) -> Iterator[tuple[int, UnitSplitHalf]]:
    """`split_half_unit` over `pairs`, in this process (`workers <= 1`) or a process pool (the
    units' pool context, `workers.pool`): `(index into pairs, check)` in completion order."""
    if workers <= 1 or len(pairs) <= 1:
        for k, (unit, result) in enumerate(pairs):
            yield k, split_half_unit(unit, result, options)
        return
    with ProcessPoolExecutor(max_workers=min(workers, len(pairs)), mp_context=pool_context(workers)) as pool:
        futures = {pool.submit(split_half_unit, u, r, options): k for k, (u, r) in enumerate(pairs)}
        for fut in as_completed(futures):
            yield futures[fut], fut.result()


def split_half_report(
    units: Sequence[BuildingUnit],
    results: Sequence[BuildingResult],
    *,
    workers: int = 1,
    options: SplitHalfOptions | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict[str, Any]:
    """The split-half check of a job's units that produced a result (failed units are left
    out), in `workers` processes; returns the `report.json` `split_half` block (`job_block`),
    buildings in the units' order. `progress(stage, done, total)` as `workers.job.Progress`,
    stage `"split_half"`."""
    opts = options if options is not None else SplitHalfOptions()
    by_id = {r.building_id: r for r in results}
    pairs = [(u, by_id[u.building.id]) for u in units if u.building.id in by_id and len(u.frames) >= 2]
    if progress is not None:
        progress("split_half", 0, len(pairs))
    done: dict[int, UnitSplitHalf] = {}
    for k, c in _run_pool(pairs, workers, opts):
        done[k] = c
        if progress is not None:
            progress("split_half", len(done), len(pairs))
    return job_block([done[k] for k in range(len(pairs))], opts)

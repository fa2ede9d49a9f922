"""The reference texturer's split-half figures and their comparison with the product's (issue 15).

Issue 15's bar: on synthetic drives with true poses, the product's split-half agreement (median
tile shift between the textures of the even and of the odd frames) ≤ 0.3 texel, and ≤ 1.2× the
reference texturer's on the same halves.

In: a `compare.Case`, the buildings to check (ids of top-level buildings, e.g. those of the
product's `report.json` `split_half` block) and the comparison's thresholds. The reference
textures each surface twice (`texturer.reference_half_textures`: alternate frames of those that
see the building, recording order, the product's rule, decided by the reference's own z-buffer),
from the TRUE poses and the package's frames, both halves on the reference's own regular grid of
the polygon (texel centres inside the polygon; rows from the top = `−t`, columns along `s`, as the
product's rasters). Out: the reference's `split_half` block, shaped as the product's (`summarize`
of the job, per building `frames_even`, `frames_odd` and `summarize`), and the product's figures
against it (`split_half_figures`).

The yardstick is shared on purpose: the halves are compared by the product's pure
`workers.pipeline.texture.split_half.split_half_agreement` and pooled by its `summarize`, so
that both texturers are judged by one rule. The reference's texturing shares nothing with the
product's texture path.
"""

from __future__ import annotations

import time
from collections.abc import Collection, Mapping
from typing import Any

import numpy as np

from tests.reference.compare import Case, frame_loader, reference_options
from tests.reference.geometry import scene_polygons
from tests.reference.texturer import ReferenceOptions, RefTexture, reference_half_textures
from tests.reference.zbuffer import RefCamera, RefGround
from workers.pipeline.texture.split_half import (
    SplitHalfOptions,
    SurfaceAgreement,
    split_half_agreement,
    summarize,
)

#: the bars: product median tile shift, texels; product ÷ reference median tile shift (metres)
MAX_SHIFT_TEXELS = 0.3
MAX_RATIO = 1.2

#: how the reference's frames are split, as its block states it
HALVES = "alternate frames of those whose z-buffer shows the building, recording order: even 1st, 3rd, ..."


def half_raster(tex: RefTexture) -> np.ndarray:
    """A reference texture as a raster `(H, W)` float32 kelvin of its grid's bounding raster
    (`grid.shape`), NaN outside the polygon and where unobserved."""
    out = np.full(tex.grid.shape, np.nan, np.float32)
    out[tex.grid.rows, tex.grid.cols] = tex.value
    return out


def compare_reference_halves(
    halves: Mapping[str, tuple[RefTexture, RefTexture]], options: SplitHalfOptions | None = None
) -> dict[str, SurfaceAgreement]:
    """`split_half_agreement(even, odd)` of every surface both halves observe (at least one
    texel in common, as the product's `workers.split_half.compare_halves`): polygon id -> the
    comparison, shifts in the reference's texels (`grid.size` metres)."""
    out: dict[str, SurfaceAgreement] = {}
    for pid, (even, odd) in halves.items():
        if not (even.observed & odd.observed).any():
            continue
        a, b = half_raster(even), half_raster(odd)
        out[pid] = split_half_agreement(a, b, even.grid.size, options=options)
    return out


def run_reference_split_half(
    case: Case,
    buildings: Collection[str] | None = None,
    options: SplitHalfOptions | None = None,
    ref_options: ReferenceOptions | None = None,
) -> dict[str, Any]:
    """The reference's split-half block of `case`, true poses.

    Args:
        case: the synthetic case (its `res` and package).
        buildings: top-level building ids whose surfaces are checked (None: every building a
            frame sees).
        options: comparison thresholds (the product's, e.g. `SplitHalfOptions(**block["options"])`).
        ref_options: the reference's options (None: `compare.reference_options`).

    Returns:
        `{"halves", "texels_per_m", **summarize(every surface), "seconds", "buildings": [{"id",
        "frames_even", "frames_odd", **summarize(its surfaces)}], "surfaces": {polygon id:
        {"building", "tiles", "median_shift_texels"}}}`; shifts in texels of the reference's grid
        and in metres.
    """
    t0 = time.perf_counter()
    res = case.res
    o = ref_options or reference_options(case.spec)
    polys = scene_polygons(res.buildings)
    wanted = None if buildings is None else {p.polygon_id for p in polys if p.building_id in set(buildings)}
    halves, frames = reference_half_textures(
        polys,
        wanted,
        RefCamera.from_params(res.manifest.camera, supersample=o.supersample),
        [(p.R_world_from_cam, p.center) for p in res.truth.poses],
        frame_loader(case),
        o,
        ground_z=RefGround.from_truth(res.truth),
    )
    found = compare_reference_halves(halves, options)
    owner = {p.polygon_id: p.building_id for p in polys}
    per_building: list[dict[str, Any]] = []
    order = list(buildings) if buildings is not None else sorted(frames)
    for b in order:
        seen = frames.get(b, [])
        mine = [s for pid, s in found.items() if owner[pid] == b]
        per_building.append(
            {"id": b, "frames_even": len(seen[0::2]), "frames_odd": len(seen[1::2]), **summarize(mine)}
        )
    return {
        "halves": HALVES,
        "sees_min_pixels": o.sees_min_pixels,
        "texels_per_m": o.texels_per_m,
        **summarize(found.values()),
        "seconds": round(time.perf_counter() - t0, 2),
        "buildings": per_building,
        "surfaces": {
            pid: {
                "building": owner[pid],
                "tiles": len(s.tiles),
                "median_shift_texels": summarize([s])["median_shift_texels"],
            }
            for pid, s in found.items()
        },
    }


def _headline(block: Mapping[str, Any]) -> dict[str, Any]:
    """The figures of a `split_half` block the bar reads."""
    keys = ("tiles", "tiles_agreeing", "agree_share", "median_shift_texels", "median_shift_m",
            "p90_shift_texels", "median_abs_diff_k", "texels_common")  # fmt: skip
    return {k: block.get(k) for k in keys}


def _ratio(a: float | None, b: float | None) -> float | None:
    """`a / b` rounded, None when either is undefined or `b` is 0."""
    return round(a / b, 3) if a is not None and b else None


def split_half_figures(product: Mapping[str, Any], reference: Mapping[str, Any]) -> dict[str, Any]:
    """The product's split-half block (`report.json` `split_half`) against the reference's
    (`run_reference_split_half`) on the same case.

    Returns `{"product", "reference"}` headlines (tiles, agree share, median and p90 tile shift
    in texels, median shift in metres, median |ΔT| K), `ratio_m` (product ÷ reference median
    tile shift in metres: the bar's ratio, as the two grids' texels may differ), `ratio_texels`
    (the same in each one's own texels), the frames per half of the buildings both checked
    (`frames_per_half_match`: buildings whose even and odd frame counts agree with the
    product's), and `bars` (`median_shift<=0.3_texel`, `median_shift<=1.2x_reference`; None
    when a figure is undefined)."""
    p, r = _headline(product), _headline(reference)
    ratio_m = _ratio(p["median_shift_m"], r["median_shift_m"])
    ratio_tx = _ratio(p["median_shift_texels"], r["median_shift_texels"])
    ref_frames = {b["id"]: (b["frames_even"], b["frames_odd"]) for b in reference.get("buildings", [])}
    both = [b for b in product.get("buildings", []) if b["id"] in ref_frames]
    same = sum(1 for b in both if (b.get("frames_even"), b.get("frames_odd")) == ref_frames[b["id"]])
    shift = p["median_shift_texels"]
    return {
        "product": p,
        "reference": {**r, "texels_per_m": reference.get("texels_per_m")},
        "ratio_m": ratio_m,
        "ratio_texels": ratio_tx,
        "frames_per_half_match": {"buildings": len(both), "same_counts": same},
        "bars": {
            f"median_shift<={MAX_SHIFT_TEXELS}_texel": None if shift is None else shift <= MAX_SHIFT_TEXELS,
            f"median_shift<={MAX_RATIO}x_reference": None if ratio_m is None else ratio_m <= MAX_RATIO,
        },
    }

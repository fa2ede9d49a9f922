"""Figures of the product's results folder and of the reference's textures against the truth.

In: a `compare.Case` (synthetic truth: `res.thermal.surface_temperature(polygon id, X)`, ground
plane), the product's results folder (read with `db.results_folder.read.iter_surface_textures`,
its texel grids re-laid from `report.json`) and the reference's textures. Each texturer is
evaluated at its OWN texel centres (world, model CRS, metres; kelvin). Texels below the synthetic
ground (its plane or terrain, `truth.ground_height`) are left out of the product's figures, as
`workers.synth_eval` does (that world buries them; the product cannot know).

Every error figure is area-weighted (each texel counts by its area): the two grids differ in
density, and the product's may differ from surface to surface.

Texel classes (from the reference texel at the same place, within `tolerance_m`):
`interior`; `boundary` (within `boundary_px` pixels of a polygon-id change in the best frame, or
seen by some frame but never with a clean footprint); `grazing` (best view angle > 70°); and, for
the product only, `unseen` (no frame sees the place at all). Surface classes: roof, wall, other.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tests.reference.compare import Case
from tests.reference.geometry import ScenePolygon
from tests.reference.texturer import RefTexture


@dataclass(frozen=True)
class EvalOptions:
    """Thresholds of the evaluation: `tolerance_m` (how far a product texel may sit from a place
    the reference sees before it counts as unseen: a texel or two), `boundary_px`, `grazing_deg`."""

    tolerance_m: float = 0.2
    boundary_px: float = 3.0
    grazing_deg: float = 70.0


def weighted_quantile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    """The `q`-quantile (0..1) of `values (N,)` with `weights (N,)` (lower value at ties).

    >>> weighted_quantile(np.array([1.0, 2.0, 3.0]), np.array([1.0, 1.0, 2.0]), 0.5)
    2.0
    """
    order = np.argsort(values)
    cw = np.cumsum(weights[order])
    return float(values[order][min(int(np.searchsorted(cw, q * cw[-1])), len(cw) - 1)])


@dataclass
class Errors:
    """Accumulated errors (K) of one texturer in one bucket, each texel weighted by its area
    (the two texturers' grids differ in density, and the product's from surface to surface:
    every figure is per square metre of surface, not per texel)."""

    parts: list[np.ndarray] = field(default_factory=list)
    weights: list[np.ndarray] = field(default_factory=list)

    def add(self, err: np.ndarray, texel_area_m2: float) -> None:
        """Add errors `(N,)` kelvin of texels of `texel_area_m2` each."""
        if len(err):
            self.parts.append(np.asarray(err, np.float64))
            self.weights.append(np.full(len(err), float(texel_area_m2)))

    def summary(self) -> dict[str, float | int | None]:
        """`{"texels", "area_m2", "sse_k2m2", "rmse_k", "p95_abs_k", "median_abs_k"}`, all
        area-weighted (None when empty)."""
        e = np.concatenate(self.parts) if self.parts else np.zeros(0)
        if len(e) == 0:
            return {"texels": 0, "area_m2": 0.0, "sse_k2m2": 0.0, "rmse_k": None, "p95_abs_k": None,
                    "median_abs_k": None}  # fmt: skip
        w = np.concatenate(self.weights)
        a = np.abs(e)
        return {
            "texels": len(e),
            "area_m2": round(float(w.sum()), 2),
            "sse_k2m2": round(float(np.sum(w * e**2)), 3),
            "rmse_k": round(float(np.sqrt(np.sum(w * e**2) / w.sum())), 4),
            "p95_abs_k": round(weighted_quantile(a, w, 0.95), 4),
            "median_abs_k": round(weighted_quantile(a, w, 0.5), 4),
        }


def surface_kind(cls: str) -> str:
    """`roof`, `wall` or `other` of a CityGML surface class."""
    return {"RoofSurface": "roof", "WallSurface": "wall"}.get(cls, "other")


@dataclass(frozen=True, eq=False)
class _Lookup:
    """Raster lookups of one reference texture: the texel under a world point within a
    tolerance, and whether the place is seen / cleanly observed."""

    ref: RefTexture
    cells: int

    def nearest(self, X: np.ndarray, usable: np.ndarray) -> np.ndarray:
        """`(N,)` index of the nearest reference texel with `usable` set (`(n_ref,)` bool) within
        `cells` raster cells of the points `X (N, 3)`, -1 where none."""
        g = self.ref.grid
        raster = np.full(g.shape, -1, np.int64)
        raster[g.rows[usable], g.cols[usable]] = np.flatnonzero(usable)
        r, c = g.cell_of(X)
        out = np.full(len(X), -1, np.int64)
        k = self.cells
        offs = sorted(
            ((dr, dc) for dr in range(-k, k + 1) for dc in range(-k, k + 1)),
            key=lambda o: o[0] ** 2 + o[1] ** 2,
        )
        for dr, dc in offs:
            rr, cc = r + dr, c + dc
            ok = (out < 0) & (rr >= 0) & (rr < g.shape[0]) & (cc >= 0) & (cc < g.shape[1])
            out[ok] = raster[rr[ok], cc[ok]]
        return out


def _classify(
    ref: RefTexture | None, X: np.ndarray, o: EvalOptions
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point `X (N, 3)` on the reference's surface: (class name `(N,)` str, seen `(N,)`
    bool, clean `(N,)` bool) by the nearest reference texel within the tolerance."""
    n = len(X)
    if ref is None:
        return np.full(n, "unseen"), np.zeros(n, bool), np.zeros(n, bool)
    lk = _Lookup(ref, max(1, math.ceil(o.tolerance_m / ref.grid.size)))
    j = lk.nearest(X, ref.seen)
    clean = lk.nearest(X, ref.observed) >= 0
    seen = j >= 0
    cls = np.full(n, "interior", dtype=object)
    jj = np.maximum(j, 0)
    boundary = ~ref.observed[jj] | (ref.best_edge_px[jj] <= o.boundary_px)
    cls[boundary] = "boundary"
    cls[ref.best_angle_deg[jj] > o.grazing_deg] = "grazing"
    cls[~seen] = "unseen"
    return cls.astype(str), seen, clean


def report_reasons(report: Any) -> dict[str, str]:
    """Polygon id -> reason the product's `report.json` gives for not texturing it: any object
    anywhere in the report naming a polygon (`id`, `polygon`, `polygon_id`) with a truthy member
    whose name contains `reason`."""
    out: dict[str, str] = {}

    def walk(node: Any) -> None:
        if isinstance(node, dict):
            pid = node.get("polygon_id") or node.get("polygon") or node.get("id")
            reason = next((v for k, v in node.items() if "reason" in k and v), None)
            if isinstance(pid, str) and reason:
                out[pid] = str(reason)
            for v in node.values():
                walk(v)
        elif isinstance(node, list):
            for v in node:
                walk(v)

    walk(report)
    return out


def above_ground(X: np.ndarray, truth: Any) -> np.ndarray:
    """`(N,)` bool: points `X (N, 3)` (world, m) at or above the synthetic ground of `truth`
    (`SynthTruth`: its plane, or its terrain `ground` whose heights never exceed `ground.top`).
    Points above the top are not looked up (as `workers.synth_eval.below_ground`): the same
    answer as `X[:, 2] >= truth.ground_height(X)` for every point."""
    top = float(truth.ground.top) if truth.ground is not None else float(truth.ground_z)
    out = np.ones(len(X), bool)
    low = np.flatnonzero(X[:, 2] < top)
    out[low] = X[low, 2] >= truth.ground_height(X[low])
    return out


def product_textures(out_dir: Any, case: Case) -> Iterable[tuple[str, np.ndarray, np.ndarray, float]]:
    """The product's textures: per textured polygon `(polygon id, texel centres (N, 3), values
    (N,) K, texel size m)` of its observed texels above the synthetic ground."""
    from db.results_folder.read import iter_surface_textures

    truth = case.res.truth
    for s in iter_surface_textures(out_dir, case.res.manifest.radiometry):
        r, c = np.nonzero(s.grid.mask & np.isfinite(s.value))
        X = s.grid.centres(r, c)
        above = above_ground(X, truth)
        yield s.polygon.id, X[above], s.value[r, c][above].astype(np.float64), float(s.grid.size)


def compare_case(
    case: Case, product_dir: Any, report: dict[str, Any], polys: list[ScenePolygon],
    refs: dict[str, RefTexture], options: EvalOptions = EvalOptions(),
) -> dict[str, Any]:  # fmt: skip
    """Every figure of one case (see `bench/texture.py`'s docstring for their meaning)."""
    o = options
    truth = case.res.thermal.surface_temperature
    by_id = {p.polygon_id: p for p in polys}
    processed = {b["id"] for b in report.get("buildings", [])}
    prod: dict[str, dict[str, Any]] = {}
    for pid, X, val, size in product_textures(product_dir, case):
        if len(X) == 0 or pid not in by_id:
            continue
        cls, seen, clean = _classify(refs.get(pid), X, o)
        prod[pid] = {
            "err": val - truth(pid, X),
            "cls": cls,
            "seen": seen,
            "clean": clean,
            "area": len(X) * size**2,
            "a": size**2,
        }
    ref_done = {pid: r for pid, r in refs.items() if r.observed.any()}
    both = sorted(set(prod) & set(ref_done))
    e_p, e_r = Errors(), Errors()
    cls_p: dict[str, Errors] = {}
    cls_r: dict[str, Errors] = {}
    ratios = []
    worst: list[dict[str, Any]] = []  # surfaces where the product's squared error exceeds the reference's
    area_p = area_r = 0.0
    for pid in both:
        d, ref = prod[pid], ref_done[pid]
        kind = surface_kind(by_id[pid].surface_class)
        e_p.add(d["err"], d["a"])
        for c in np.unique(d["cls"]):
            cls_p.setdefault(c, Errors()).add(d["err"][d["cls"] == c], d["a"])
        cls_p.setdefault(kind, Errors()).add(d["err"], d["a"])
        m = ref.observed
        Xr = ref.grid.centres[m]
        er = ref.value[m] - truth(pid, Xr)
        a_ref = ref.grid.size**2
        e_r.add(er, a_ref)
        rc, _, _ = _classify(ref, Xr, o)
        for c in np.unique(rc):
            cls_r.setdefault(c, Errors()).add(er[rc == c], a_ref)
        cls_r.setdefault(kind, Errors()).add(er, a_ref)
        worst.append({
            "polygon": pid, "class": by_id[pid].surface_class, "texels": len(d["err"]),
            "rmse_k": round(float(np.sqrt(np.mean(d["err"] ** 2))), 3),
            "reference_rmse_k": round(float(np.sqrt(np.mean(er**2))), 3),
            "excess_sse_k2m2": round(float(d["area"] * (np.mean(d["err"] ** 2) - np.mean(er**2))), 3),
            "reference_median_view_deg": round(float(np.nanmedian(ref.best_angle_deg[m])), 1),
        })  # fmt: skip
        a_r = float(m.sum()) * ref.grid.size**2
        ratios.append(d["area"] / a_r)
        area_p += d["area"]
        area_r += a_r
    sp, sr = e_p.summary(), e_r.summary()

    def ratio(a: float | None, b: float | None) -> float | None:
        return round(a / b, 3) if a is not None and b else None

    # hidden surfaces textured: no clean observation by the reference in any frame
    hidden = sorted(set(prod) - set(ref_done))
    sse_all = sum(float(d["a"] * np.sum(d["err"] ** 2)) for d in prod.values())
    hid = []
    for pid in hidden:
        d = prod[pid]
        ever = pid in refs and bool(refs[pid].seen.any())
        hid.append({
            "polygon": pid, "class": by_id[pid].surface_class, "texels": len(d["err"]),
            "rmse_k": round(float(np.sqrt(np.mean(d["err"] ** 2))), 3),
            "seen_by_some_frame": ever,
        })  # fmt: skip
    hid.sort(key=lambda h: -h["texels"] * h["rmse_k"] ** 2)
    sse_hidden = sum(float(prod[h["polygon"]]["a"] * np.sum(prod[h["polygon"]]["err"] ** 2)) for h in hid)
    n_prod = sum(len(d["err"]) for d in prod.values())
    unseen = sum(int((~d["seen"]).sum()) for d in prod.values())
    unclean = sum(int((~d["clean"]).sum()) for d in prod.values())
    e_unseen = Errors()
    for d in prod.values():
        e_unseen.add(d["err"][~d["seen"]], d["a"])
    # visible surfaces the product leaves untextured
    reasons = report_reasons(report)
    missing = sorted(set(ref_done) - set(prod))
    miss_kind: dict[str, int] = {}
    for pid in missing:
        k = surface_kind(by_id[pid].surface_class)
        miss_kind[k] = miss_kind.get(k, 0) + 1
    miss_area = sorted(float(ref_done[p].observed.sum()) * ref_done[p].grid.size ** 2 for p in missing)
    in_processed = [p for p in missing if by_id[p].building_id in processed]
    e_all = Errors()
    for d in prod.values():
        e_all.add(d["err"], d["a"])
    return {
        "product": sp,
        "reference": sr,
        "rmse_ratio": ratio(sp["rmse_k"], sr["rmse_k"]),
        "p95_ratio": ratio(sp["p95_abs_k"], sr["p95_abs_k"]),
        "surfaces_textured": {
            "product": len(prod),
            "reference": len(ref_done),
            "both": len(both),
            "ratio": ratio(len(prod), len(ref_done)),
        },
        "observed_area_per_surface_ratio": {
            "median": round(float(np.median(ratios)), 3) if ratios else None,
            "overall": ratio(area_p, area_r),
        },
        "product_all_surfaces": e_all.summary(),
        "hidden_surfaces_textured": {
            "count": len(hid),
            "never_seen_by_any_frame": sum(1 for h in hid if not h["seen_by_some_frame"]),
            "share_of_product_sse": round(sse_hidden / sse_all, 3) if sse_all else None,
            "worst": hid[:8],
        },
        "unseen_texels_delivered": {
            "texels": unseen,
            "share": round(unseen / n_prod, 4) if n_prod else None,
            "error": e_unseen.summary(),
        },
        "texels_without_clean_view_delivered": {
            "texels": unclean,
            "share": round(unclean / n_prod, 4) if n_prod else None,
        },
        "visible_untextured": {
            "count": len(missing),
            "by_kind": miss_kind,
            "in_processed_buildings": len(in_processed),
            "with_reason_in_report": sum(1 for p in missing if p in reasons),
            "without_reason": sum(1 for p in missing if p not in reasons),
            "median_visible_area_m2": round(float(np.median(miss_area)), 2) if miss_area else None,
        },
        "worst_surfaces_vs_reference": sorted(worst, key=lambda w: -w["excess_sse_k2m2"])[:6],
        "by_class": {
            "product": {k: v.summary() for k, v in sorted(cls_p.items())},
            "reference": {k: v.summary() for k, v in sorted(cls_r.items())},
        },
    }

"""Truth-based evaluation of thermal-anomaly detections (the figures of issue 16).

In: the truth of a synthetic scene (`synth.Anomaly` leaks with half-maximum outlines,
`synth.Window` rectangles; world = model CRS, metres, kelvin), the detections (objects with
`kind`, `polygon_id`, `centre (3,)`, `outline (N, 3)`, `peak_delta_k`: `results.Anomaly`, or the
features of an `anomalies.geojson` through `detections_from_geojson`) and which places the job's
frames observed (`Coverage`: the fused textures, NaN = not observed). Out: plain dictionaries of
figures (`evaluate_leaks`, `evaluate_windows`, `false_leak_rate`). Pure: no files, no database.

What counts:
- a truth item is **observed** (`EvalOptions`, the default definition, the same for every
  case) when
  1. at least `observed_share` (50 %) of its area (a leak's half-maximum disc, a window's
     rectangle) is seen by at least `min_frames` (2) distinct frames: share of the texel
     centres inside the region, of the grid of its polygon, whose fused texel rests on kept
     observations from `min_frames` distinct frames (`Coverage.observed_share`; a region
     holding no texel centre takes the texel under its centre). The issue has the detector
     ignore texels seen by one frame only, so the evaluation does not ask it to find what they
     show;
  2. it is **resolvable** on its polygon's texel grid: a leak's half-maximum diameter spans at
     least `min_leak_texels` (2) texels, a window pane at least `min_pane_texels` (3) texels
     on each side;
  `EvalOptions.texels_only()` is the earlier definition (any value in ≥ 50 % of the region,
  no frame count, no resolution), kept for comparison;
- a **leak match**: a detection of kind `leak` whose centre lies within `match_distance_m`
  (0.5 m, 3D) of a truth leak's centre; pairs taken greedily by distance, one-to-one. A window
  match: a `window` detection within 0.5 m, or with outline IoU ≥ `window_iou` (0.5);
- precision = matched observed items / (detections − those matched to unobserved items);
  recall = matched observed items / observed items. Outline IoU is the polygon IoU in the truth
  item's plane (both rings projected orthogonally); ΔT error = |peak_delta_k − delta_k|;
- false leaks per 100 m²: unmatched `leak` detections per 100 m² of observed area (walls, the
  facade figure of the issue's bar, and all surfaces).

Which places were observed is decided from the job's own product: the fused textures of its
units as the job held them in memory (`bench/anomalies.py` records, for every textured polygon,
its grid, fused values and distinct frames per texel while the job runs: the results folder
keeps no frame counts), or the results folder's textures (`coverage_of`, DN 0 read as NaN; no
frame counts: only `EvalOptions.texels_only()` applies). A leak on a surface the job never
textured, or whose frames it withheld, counts as not observed, whatever the frames show.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import shapely
from scipy.spatial import cKDTree

from workers.pipeline.geometry.polygons import newell_normal, open_ring, surface_axes, to_plane_2d
from workers.pipeline.results import Anomaly as Detected
from workers.pipeline.synth.anomaly import Anomaly as TruthLeak
from workers.pipeline.synth.anomaly import Window as TruthWindow
from workers.pipeline.texture.texel import TexelGrid


@dataclass(frozen=True)
class EvalOptions:
    """Thresholds of the evaluation (issue 16) and the definition of "observed" (module
    docstring)."""

    match_distance_m: float = 0.5  # detection centre to truth centre, 3D
    window_iou: float = 0.5  # a window also matches with outline IoU at least this
    observed_share: float = 0.5  # share of a truth region observed for it to count
    min_frames: int = 2  # distinct frames a texel needs to count as observed
    min_leak_texels: float = 2.0  # a leak's half-maximum diameter must span this many texels
    min_pane_texels: float = 3.0  # a window's sides must each span this many texels

    @classmethod
    def texels_only(cls) -> EvalOptions:
        """The earlier definition: a region is observed when half of it has a value (any number
        of frames, any texel size)."""
        return cls(min_frames=1, min_leak_texels=0.0, min_pane_texels=0.0)


class Detection(Protocol):
    """What the evaluation reads of a detection (`results.Anomaly` has it)."""

    kind: str
    polygon_id: str | None
    centre: np.ndarray
    outline: np.ndarray
    peak_delta_k: float


class Coverage:
    """Which texels a job observed, per polygon: `textures` maps polygon id to its texel grid
    and fused texture `(H, W)` (NaN = not observed), e.g. a results folder's
    (`db.results_folder.read.iter_surface_textures`); `frames` (optional) maps polygon id to
    the distinct frames `(H, W)` int behind each fused texel (the job's in-memory textures,
    `anomalies.typical.frames_per_texel`)."""

    def __init__(
        self,
        textures: Mapping[str, tuple[TexelGrid, np.ndarray]],
        frames: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        self.textures = dict(textures)
        self.frames = None if frames is None else dict(frames)

    def seen(self, polygon_id: str, min_frames: int = 1) -> np.ndarray | None:
        """`(H, W)` bool: texels with a value seen by at least `min_frames` distinct frames
        (None: polygon not textured). Raises ValueError when `min_frames` > 1 and the coverage
        has no frame counts."""
        got = self.textures.get(polygon_id)
        if got is None:
            return None
        ok = np.isfinite(got[1])
        if min_frames > 1:
            if self.frames is None:
                raise ValueError("coverage without frame counts: use EvalOptions.texels_only()")
            n = self.frames.get(polygon_id)
            ok = ok & (n >= min_frames) if n is not None else np.zeros_like(ok)
        return ok

    def observed_share(self, polygon_id: str, ring: np.ndarray, min_frames: int = 1) -> float:
        """Share 0-1 of the region `ring` `(N, 3)` (world, on the polygon) that was observed: its
        texel centres inside the polygon with a value seen by at least `min_frames` distinct
        frames (0 when the polygon has no texture)."""
        got = self.textures.get(polygon_id)
        if got is None or len(ring) < 3:
            return 0.0
        grid = got[0]
        value = np.where(self.seen(polygon_id, min_frames), 0.0, np.nan)
        xy = grid.raster_xy(np.asarray(ring, float).reshape(-1, 3))
        region = shapely.Polygon(xy).buffer(0)
        H, W = grid.shape
        x0, y0, x1, y1 = region.bounds
        c0, c1 = max(int(np.floor(x0 - 0.5)), 0), min(int(np.ceil(x1 - 0.5)), W - 1)
        r0, r1 = max(int(np.floor(y0 - 0.5)), 0), min(int(np.ceil(y1 - 0.5)), H - 1)
        if c0 > c1 or r0 > r1:
            return 0.0
        rr, cc = np.mgrid[r0 : r1 + 1, c0 : c1 + 1]
        inside = shapely.contains_xy(region, cc + 0.5, rr + 0.5) & grid.mask[rr, cc]
        if not inside.any():  # smaller than a texel: the texel under its centre
            c = np.asarray(region.centroid.coords)[0]
            r, k = int(np.clip(c[1], 0, H - 1)), int(np.clip(c[0], 0, W - 1))
            return float(grid.mask[r, k] and np.isfinite(value[r, k]))
        return float(np.isfinite(value[rr, cc][inside]).mean())

    def observed_area_m2(self, surface_classes: Iterable[str] | None = None) -> float:
        """Observed area, m² (texels inside their polygon with a value × texel area), over the
        polygons of `surface_classes` (None: all)."""
        keep = None if surface_classes is None else set(surface_classes)
        total = 0.0
        for grid, value in self.textures.values():
            if keep is None or grid.surface_class in keep:
                total += float(np.count_nonzero(grid.mask & np.isfinite(value))) * grid.size**2
        return total

    def texel_size_m(self, polygon_id: str) -> float | None:
        """Texel edge of a textured polygon's grid, metres (None: not textured)."""
        got = self.textures.get(polygon_id)
        return None if got is None else float(got[0].size)

    def surface_class(self, polygon_id: str | None) -> str | None:
        """The class of a textured polygon (None: not textured)."""
        got = self.textures.get(polygon_id or "")
        return None if got is None else got[0].surface_class


def detections_from_geojson(doc: Mapping[str, Any]) -> list[Detected]:
    """The features of an `anomalies.geojson` document as `results.Anomaly` (outline: the
    exterior ring of the 3D polygon; `kind` defaults to "leak")."""
    out: list[Detected] = []
    for feat in doc.get("features") or []:
        props = feat.get("properties") or {}
        rings = (feat.get("geometry") or {}).get("coordinates") or []
        outline = np.asarray(rings[0], float).reshape(-1, 3) if rings else np.zeros((0, 3))
        out.append(
            Detected(
                building_id=str(props.get("building", "")),
                polygon_id=props.get("surface"),
                outline=outline,
                centre=np.asarray(props["centre"], float).reshape(3),
                area_m2=float(props.get("area_m2") or 0.0),
                peak_delta_k=float(props.get("peak_delta_k") or 0.0),
                mean_delta_k=float(props.get("mean_delta_k") or 0.0),
                kind=str(props.get("kind") or "leak"),
            )
        )
    return out


def greedy_match(
    det_xyz: np.ndarray,
    truth_xyz: np.ndarray,
    max_distance: float,
    extra: Mapping[tuple[int, int], bool] | None = None,
) -> list[tuple[int, int, float]]:
    """One-to-one matches `(detection, truth, distance)` between centres `(D, 3)` and `(T, 3)`:
    candidate pairs within `max_distance` (or flagged True in `extra`, e.g. by IoU), taken by
    increasing distance, each index used once.

    >>> greedy_match(np.array([[0, 0, 0], [1, 0, 0.]]), np.array([[0.9, 0, 0], [0.2, 0, 0]]), 0.5)
    [(1, 0, 0.1), (0, 1, 0.2)]
    """
    D, T = np.asarray(det_xyz, float).reshape(-1, 3), np.asarray(truth_xyz, float).reshape(-1, 3)
    if len(D) == 0 or len(T) == 0:
        return []
    pairs = set(cKDTree(D).sparse_distance_matrix(cKDTree(T), max_distance, output_type="dict"))
    pairs |= {p for p, ok in (extra or {}).items() if ok}
    cand = sorted((round(float(np.linalg.norm(D[i] - T[j])), 12), i, j) for i, j in pairs)
    used_d: set[int] = set()
    used_t: set[int] = set()
    out = []
    for d, i, j in cand:
        if i not in used_d and j not in used_t:
            used_d.add(i)
            used_t.add(j)
            out.append((int(i), int(j), d))
    return out


def ring_iou(truth_ring: np.ndarray, other_ring: np.ndarray) -> float:
    """IoU 0-1 of two 3D rings `(N, 3)`, `(M, 3)` in the plane of `truth_ring` (both projected
    orthogonally onto it; 0 when either is degenerate)."""
    a = open_ring(np.asarray(truth_ring, float).reshape(-1, 3))
    b = np.asarray(other_ring, float).reshape(-1, 3)
    if len(a) < 3 or len(b) < 3:
        return 0.0
    n = newell_normal(a)
    if not np.all(np.isfinite(n)) or np.linalg.norm(n) < 1e-12:
        return 0.0
    n = n / np.linalg.norm(n)
    s, t = surface_axes(n, a)
    o = a.mean(axis=0)
    pa = shapely.Polygon(to_plane_2d(a, o, s, t)).buffer(0)
    pb = shapely.Polygon(to_plane_2d(b, o, s, t)).buffer(0)
    union = pa.union(pb).area
    return float(pa.intersection(pb).area / union) if union > 0 else 0.0


def _ratio(num: int, den: int) -> float | None:
    return None if den == 0 else round(num / den, 4)


def _median(values: Sequence[float]) -> float | None:
    return None if len(values) == 0 else round(float(np.median(values)), 4)


def _observed(
    coverage: Coverage | None,
    polygon_id: str,
    ring: np.ndarray | None,
    sides_m: tuple[float, ...],
    min_texels: float,
    options: EvalOptions,
) -> bool:
    """Whether a truth region counts as observed (module docstring; no coverage: every region
    does): `options.observed_share` of it seen by `options.min_frames` frames, and each of
    `sides_m` (a leak's half-maximum diameter, a pane's width and height) at least `min_texels`
    texels of its polygon's grid."""
    if coverage is None:
        return True
    if ring is None:
        raise ValueError(f"truth region on {polygon_id!r} has no outline (old truth: Anomaly.with_outline)")
    size = coverage.texel_size_m(polygon_id)
    if size is None or min(sides_m) < min_texels * size - 1e-9:
        return False
    return coverage.observed_share(polygon_id, ring, options.min_frames) >= options.observed_share


def evaluate_leaks(
    truth: Sequence[TruthLeak],
    detections: Sequence[Detection],
    coverage: Coverage | None,
    options: EvalOptions = EvalOptions(),
) -> dict[str, Any]:
    """Leak figures of one scene: counts, precision, recall, outline IoU median, ΔT error median
    (K), centre error median (m), false leaks per 100 m² (walls and all surfaces, when
    `coverage` is given), and the ids of the observed leaks missed (up to 10)."""
    det = [d for d in detections if d.kind == "leak"]
    o = options
    seen = [
        _observed(coverage, a.polygon_id, a.outline, (2 * a.half_max_radius_m,), o.min_leak_texels, o)
        for a in truth
    ]
    matches = greedy_match(
        np.array([d.centre for d in det]).reshape(-1, 3),
        np.array([a.center for a in truth]).reshape(-1, 3),
        options.match_distance_m,
    )
    tp = [(i, j, d) for i, j, d in matches if seen[j]]
    ignored = len(matches) - len(tp)  # detections of leaks the frames did not observe enough
    fp = len(det) - len(matches)
    n_seen = int(sum(seen))
    ious = [ring_iou(truth[j].outline, det[i].outline) for i, j, _ in tp if truth[j].outline is not None]
    dts = [abs(float(det[i].peak_delta_k) - truth[j].delta_k) for i, j, _ in tp]
    hit = {j for _, j, _ in tp}
    out: dict[str, Any] = {
        "truth": len(truth),
        "truth_observed": n_seen,
        "detections": len(det),
        "matched": len(tp),
        "matched_unobserved_ignored": ignored,
        "false": fp,
        "precision": _ratio(len(tp), len(det) - ignored),
        "recall": _ratio(len(tp), n_seen),
        "outline_iou_median": _median(ious),
        "delta_k_error_median_k": _median(dts),
        "centre_error_median_m": _median([d for _, _, d in tp]),
        "missed": [truth[j].id for j in range(len(truth)) if seen[j] and j not in hit][:10],
        "false_examples": _false_examples(det, {i for i, _, _ in matches}, truth),
    }
    if coverage is not None:
        out.update(false_leak_rate(det, coverage, matched={i for i, _, _ in matches}))
        out["recall_by_texel_size"] = _recall_by_size(
            [coverage.texel_size_m(a.polygon_id) for a in truth], seen, hit
        )
    return out


def _false_examples(
    det: Sequence[Detection], matched: set[int], truth: Sequence[TruthLeak], n: int = 5
) -> list[dict[str, Any]]:
    """Up to `n` unmatched leak detections, strongest first: surface, centre, peak ΔT (K) and
    the distance to the nearest truth leak (m; None without truth leaks), to tell a detection
    near a real leak from one on something else (a pipe, a corner, a window)."""
    false = sorted((k for k in range(len(det)) if k not in matched), key=lambda k: -abs(det[k].peak_delta_k))
    T = np.array([a.center for a in truth]).reshape(-1, 3)
    out = []
    for k in false[:n]:
        c = np.asarray(det[k].centre, float)
        near = float(np.min(np.linalg.norm(T - c, axis=1))) if len(T) else None
        out.append({
            "surface": det[k].polygon_id,
            "centre": [round(float(v), 2) for v in c],
            "peak_delta_k": round(float(det[k].peak_delta_k), 2),
            "nearest_truth_leak_m": None if near is None else round(near, 2),
        })  # fmt: skip
    return out


def _recall_by_size(sizes: Sequence[float | None], seen: Sequence[bool], hit: set[int]) -> dict[str, Any]:
    """Observed and matched truth items by the texel size of their surface's grid (`≤0.1 m`,
    `≤0.25 m`, `>0.25 m`): coarse textures (flights) hold small leaks in a few texels."""
    out: dict[str, Any] = {}
    for j, size in enumerate(sizes):
        if not seen[j] or size is None:
            continue
        key = "<=0.1m" if size <= 0.1 + 1e-9 else "<=0.25m" if size <= 0.25 + 1e-9 else ">0.25m"
        b = out.setdefault(key, {"observed": 0, "matched": 0})
        b["observed"] += 1
        b["matched"] += j in hit
    return dict(sorted(out.items()))


def evaluate_windows(
    truth: Sequence[TruthWindow],
    detections: Sequence[Detection],
    coverage: Coverage | None,
    options: EvalOptions = EvalOptions(),
) -> dict[str, Any]:
    """Window figures of one scene: counts, precision, recall (a match: centre within
    `match_distance_m` or outline IoU ≥ `window_iou`), outline IoU median of the matches."""
    det = [d for d in detections if d.kind == "window"]
    o = options
    seen = [
        _observed(coverage, w.polygon_id, w.outline, (w.width_m, w.height_m), o.min_pane_texels, o)
        for w in truth
    ]
    D = np.array([d.centre for d in det]).reshape(-1, 3)
    T = np.array([w.center for w in truth]).reshape(-1, 3)
    extra: dict[tuple[int, int], bool] = {}
    if len(D) and len(T):
        near = cKDTree(D).sparse_distance_matrix(cKDTree(T), 3.0, output_type="dict")
        for i, j in near:
            if len(det[i].outline) >= 3:
                extra[(i, j)] = ring_iou(truth[j].outline, det[i].outline) >= options.window_iou
    matches = greedy_match(D, T, options.match_distance_m, extra)
    tp = [(i, j) for i, j, _ in matches if seen[j]]
    ignored = len(matches) - len(tp)
    n_seen = int(sum(seen))
    ious = [ring_iou(truth[j].outline, det[i].outline) for i, j in tp if len(det[i].outline) >= 3]
    return {
        "truth": len(truth),
        "truth_observed": n_seen,
        "detections": len(det),
        "matched": len(tp),
        "matched_unobserved_ignored": ignored,
        "false": len(det) - len(matches),
        "precision": _ratio(len(tp), len(det) - ignored),
        "recall": _ratio(len(tp), n_seen),
        "outline_iou_median": _median(ious),
    }


def false_leak_rate(
    detections: Sequence[Detection], coverage: Coverage, matched: set[int] | None = None
) -> dict[str, Any]:
    """Unmatched `leak` detections (indices not in `matched`; all of them in a leak-free scene)
    per 100 m² of observed area: on walls (`false_leaks_per_100m2_facade`, the issue's bar) and
    on every surface; with the observed areas in m²."""
    det = [d for d in detections if d.kind == "leak"]
    false = [d for k, d in enumerate(det) if k not in (matched or set())]
    wall_area = coverage.observed_area_m2(["WallSurface"])
    all_area = coverage.observed_area_m2()
    n_wall = sum(1 for d in false if coverage.surface_class(d.polygon_id) == "WallSurface")

    def per100(n: int, area: float) -> float | None:
        return None if area <= 0 else round(100.0 * n / area, 4)

    return {
        "false_leaks_facade": n_wall,
        "false_leaks_per_100m2_facade": per100(n_wall, wall_area),
        "false_leaks_per_100m2_all": per100(len(false), all_area),
        "observed_facade_m2": round(wall_area, 1),
        "observed_all_m2": round(all_area, 1),
    }


def leaks_on_windows(
    detections: Sequence[Detection], windows: Sequence[TruthWindow], margin_m: float = 0.2
) -> int:
    """Number of `leak` detections whose centre lies within `margin_m` (3D) of a truth window's
    rectangle (a window reported as a leak)."""
    det = [d for d in detections if d.kind == "leak"]
    if not det or not windows:
        return 0
    tree = cKDTree(np.array([w.center for w in windows]))
    n = 0
    for d in det:
        for j in tree.query_ball_point(np.asarray(d.centre, float), 2.0):
            w = windows[j]
            o, s, t = w.outline[0], w.outline[1] - w.outline[0], w.outline[3] - w.outline[0]
            q = np.asarray(d.centre, float) - o
            u, v = q @ s / (s @ s), q @ t / (t @ t)
            off = abs(q @ np.cross(s, t)) / np.linalg.norm(np.cross(s, t))
            mu, mv = margin_m / np.linalg.norm(s), margin_m / np.linalg.norm(t)
            if -mu <= u <= 1 + mu and -mv <= v <= 1 + mv and off <= margin_m:
                n += 1
                break
    return n

"""Writing a job's results folder (`docs/results-format.md`): texture tiles, `textured.gml`,
`orientation.json`, `report.json`, `anomalies.geojson`.

In: `BuildingResult`s of the building units, the buildings, the prior poses and the manifest.
Out: files under the results folder. File I/O only; no numerical work beyond colour mapping.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from db.citygml.writer import write_citygml
from db.surface_checks import jsonable
from workers.pipeline.geometry.citymodel import Appearance, Building, ParameterizedTexture
from workers.pipeline.geometry.crs import UnknownCRSError, horizontal_epsg, vertical_epsg
from workers.pipeline.geometry.manifest import Radiometry, SequenceManifest
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.options import options_to_dict
from workers.pipeline.results import Anomaly, BuildingResult, TextureTile
from workers.pipeline.texture.texel import TexelOptions

ORIENTATION_FORMAT = "citytherm-orientation/1"
REPORT_FORMAT = "citytherm-report/1"


class ResultsWriteError(OSError):
    """A results file could not be written (names the file)."""


def write_json(path: Path, data: Any) -> None:
    """Write `data` as strict JSON (no NaN) to `path`."""
    try:
        path.write_text(json.dumps(jsonable(data), indent=1, allow_nan=False) + "\n", encoding="utf-8")
    except OSError as exc:
        raise ResultsWriteError(f"{path}: {exc}") from exc


def geojson_crs_name(srs_name: str) -> str:
    """The name of the model CRS as GeoJSON readers (GDAL, QGIS) resolve it: an OGC URN of its
    EPSG codes, compound with the height system where the model names one
    (`urn:ogc:def:crs,crs:EPSG::25832,crs:EPSG::7837` for the ADV name of ETRS89 / UTM 32N +
    DHHN2016); the srsName as it is when it has no EPSG code."""
    try:
        h, v = horizontal_epsg(srs_name), vertical_epsg(srs_name)
    except UnknownCRSError:
        return srs_name
    if h is None:
        return srs_name
    return f"urn:ogc:def:crs,crs:EPSG::{h},crs:EPSG::{v}" if v is not None else f"urn:ogc:def:crs:EPSG::{h}"


def anomalies_document(features: Sequence[Mapping[str, Any]], srs_name: str | None) -> dict[str, Any]:
    """The `anomalies.geojson` document: a FeatureCollection of 3D polygons in the model CRS,
    named by a `crs` member when the CRS is known (`docs/results-format.md`): `name` as GDAL
    resolves it (`geojson_crs_name`), `srsName` the model's own name."""
    doc: dict[str, Any] = {"type": "FeatureCollection", "features": list(features)}
    if srs_name:
        doc["crs"] = {"type": "name", "properties": {"name": geojson_crs_name(srs_name), "srsName": srs_name}}
    return doc


def _finite(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def anomaly_feature(a: Anomaly) -> dict[str, Any]:
    """One `anomalies.geojson` feature (`docs/results-format.md`): the closed 3D outline as a
    `Polygon` in the model CRS and the detector's figures as properties."""
    ring = np.asarray(a.outline, dtype=np.float64).reshape(-1, 3)
    if len(ring) and not np.array_equal(ring[0], ring[-1]):
        ring = np.vstack([ring, ring[:1]])
    return {
        "type": "Feature",
        "id": a.id or None,
        "geometry": {"type": "Polygon", "coordinates": [ring.tolist()]} if len(ring) >= 4 else None,
        "properties": {
            "id": a.id or None,
            "building": a.building_id,
            "surface": a.polygon_id,
            "kind": a.kind,
            "centre": [float(v) for v in np.asarray(a.centre, dtype=np.float64).reshape(3)],
            "area_m2": float(a.area_m2),
            "peak_delta_k": float(a.peak_delta_k),
            "mean_delta_k": float(a.mean_delta_k),
            "frames": int(a.frames),
            "best_resolution_m": _finite(a.best_resolution_m),
            "confidence": _finite(a.confidence),
        },
    }


def write_tile(out_dir: Path, tile: TextureTile) -> Path:
    """Write one 16-bit single-channel PNG tile under `out_dir` (its `name` is relative)."""
    path = out_dir / tile.name
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.ascontiguousarray(tile.dn, dtype=np.uint16)):
        raise ResultsWriteError(f"{path}: PNG encoder failed")
    return path


def read_tile(out_dir: Path, name: str) -> TextureTile:
    """Read back a 16-bit tile written by `write_tile`."""
    path = out_dir / name
    dn = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if dn is None or dn.dtype != np.uint16:
        raise ResultsWriteError(f"{path}: not a 16-bit PNG")
    return TextureTile(name=name, dn=dn)


def display_name(name: str) -> str:
    """`textures/X_0.png` -> `textures/X_0-display.png`."""
    p = Path(name)
    return str(p.with_name(f"{p.stem}-display{p.suffix}"))


def write_display_tile(
    out_dir: Path, tile: TextureTile, radiometry: Radiometry, value_range: tuple[float, float]
) -> Path:
    """Write an 8-bit colour-mapped (inferno) RGB copy of a tile; unobserved texels black."""
    lo, hi = value_range
    vals = radiometry.physical(tile.dn)
    scaled = np.clip((vals - lo) / max(hi - lo, 1e-6) * 254.0 + 1.0, 1, 255).astype(np.uint8)
    bgr = cv2.applyColorMap(scaled, cv2.COLORMAP_INFERNO)
    bgr[tile.dn == 0] = 0
    path = out_dir / display_name(tile.name)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), bgr):
        raise ResultsWriteError(f"{path}: PNG encoder failed")
    return path


def display_appearance(app: Appearance) -> Appearance:
    """The `<theme>-display` twin of an appearance: same targets, `-display` images."""
    data = tuple(
        ParameterizedTexture(
            id=f"{sd.id}_display",
            image_uri=display_name(sd.image_uri),
            targets=sd.targets,
            mime_type=sd.mime_type,
        )
        for sd in app.surface_data
        if isinstance(sd, ParameterizedTexture)
    )
    return Appearance(
        theme=f"{app.theme}-display", surface_data=data, id=f"{app.id}_display" if app.id else None
    )


def write_textured_gml(
    path: Path,
    buildings: Sequence[Building],
    results: Mapping[str, BuildingResult],
    srs_name: str | None,
    display: bool,
) -> int:
    """Write `textured.gml`: the textured buildings, complete, with the job's appearances and,
    on every analysed surface, its facade figures as generic attributes (`surface_attributes`)."""
    extra: dict[str, list[Appearance]] = {}
    attributes: dict[str, dict[str, Any]] = {}
    for b in buildings:
        r = results.get(b.id)
        if r is None or r.appearance is None:
            continue
        extra[b.id] = [r.appearance, display_appearance(r.appearance)] if display else [r.appearance]
        attributes.update(surface_attributes(r))
    textured = [b for b in buildings if b.id in extra]
    try:
        return write_citygml(
            path, textured, srs_name=srs_name, extra_appearances=extra, surface_attributes=attributes
        )
    except OSError as exc:
        raise ResultsWriteError(f"{path}: {exc}") from exc


FIGURES = ("typical", "spread", "hot_share", "window_share", "heat_loss_index", "windows", "leaks")


def facade_attributes(figures: Mapping[str, Any], leak_ids: Sequence[str]) -> dict[str, Any] | None:
    """The generic attributes of one analysed surface (`surface_attributes`) from its facade
    figures (`FIGURES`: `SurfaceStats` fields) and the ids of its leak candidates; None when the
    surface has no typical temperature (not observed, analysis off)."""
    typical = figures.get("typical")
    if typical is None or not np.isfinite(typical):
        return None
    attrs: dict[str, Any] = {"thermal_typical": float(typical)}
    for key in ("spread", "hot_share", "window_share", "heat_loss_index"):
        v = figures.get(key)
        if v is not None and np.isfinite(v):
            attrs[f"thermal_{key}"] = float(v)
    attrs["thermal_windows"] = int(figures.get("windows") or 0)
    attrs["thermal_leaks"] = int(figures.get("leaks") or 0)
    if leak_ids:
        attrs["thermal_leak_ids"] = " ".join(leak_ids)
    return attrs


def surface_attributes(r: BuildingResult) -> dict[str, dict[str, Any]]:
    """The facade figures of a building's analysed surfaces as CityGML generic attributes, by
    polygon id (`docs/results-format.md`): `thermal_typical`, `thermal_spread` (radiometry unit),
    `thermal_hot_share`, `thermal_window_share`, `thermal_heat_loss_index`, `thermal_windows`,
    `thermal_leaks`, and `thermal_leak_ids` (the ids of its leak candidates in
    `anomalies.geojson`). Surfaces without figures (not observed, analysis off) get none."""
    leak_ids: dict[str, list[str]] = {}
    for a in r.anomalies:
        if a.kind == "leak" and a.id:
            leak_ids.setdefault(a.polygon_id, []).append(a.id)
    out: dict[str, dict[str, Any]] = {}
    for s in r.surfaces:
        attrs = facade_attributes({k: getattr(s, k) for k in FIGURES}, leak_ids.get(s.polygon_id, ()))
        if attrs is not None:
            out[s.polygon_id] = attrs
    return out


def orientation_document(
    manifest: SequenceManifest,
    priors: Sequence[Pose],
    results: Sequence[BuildingResult],
    mounting: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The `orientation.json` document: prior pose of every frame (the manifest-only prior),
    refined poses per building, and `mounting`: the estimated `boresight_deg`, `lever_arm_m`
    and `time_delay_s` when given (a calibration ran), else the manifest's values and delay 0."""
    refined: dict[int, list[dict[str, Any]]] = {}
    for r in results:
        for fp in r.poses:
            refined.setdefault(fp.frame, []).append(
                {
                    "building": fp.building_id,
                    **fp.pose.to_dict(),
                    "rms_px": fp.rms_px,
                    "matches": fp.matches,
                    "status": fp.status,
                }
            )
    m = manifest.mounting
    if mounting is None:
        mounting = {
            "boresight_deg": np.asarray(m.boresight_deg, dtype=float).tolist(),
            "lever_arm_m": np.asarray(m.lever_arm_m, dtype=float).tolist(),
            "time_delay_s": 0.0,
        }
    return {
        "format": ORIENTATION_FORMAT,
        "mounting": dict(mounting),
        "frames": [
            {"index": f.index, "file": f.file, "prior": pose.to_dict(), "refined": refined.get(f.index, [])}
            for f, pose in zip(manifest.frames, priors, strict=True)
        ],
    }


def building_report(r: BuildingResult, n_frames: int) -> dict[str, Any]:
    """Per-building section of `report.json`."""
    total = sum(s.texels_total for s in r.surfaces)
    observed = sum(s.texels_observed for s in r.surfaces)
    refined = [p for p in r.poses if p.status == "refined"]
    return {
        "id": r.building_id,
        "frames": n_frames,
        "frames_used": sorted({f for s in r.surfaces for f in s.frames_used}),
        "texels_total": total,
        "texels_observed": observed,
        "observed_share": observed / total if total else 0.0,
        "surfaces_observed": sum(1 for s in r.surfaces if s.texels_observed),
        "tiles": [t.name for t in r.tiles],
        "orientation": {
            "frames": len(r.poses),
            "refined": len(refined),
            "mean_rms_px": float(np.mean([p.rms_px for p in refined])) if refined else None,
            "mean_matches": float(np.mean([p.matches for p in refined])) if refined else None,
            "frames_withheld": list(r.frames_withheld),
            "frames_rejected_by_texture": list(r.frames_rejected),
        },
        "timings_s": dict(r.timings_s),
        "anomalies": {k: sum(1 for a in r.anomalies if a.kind == k) for k in ("leak", "window", "bridge")},
        "surfaces": [
            {
                "id": s.polygon_id,
                "building": s.building_id,
                "class": s.surface_class,
                "texels_total": s.texels_total,
                "texels_observed": s.texels_observed,
                "observed_share": s.observed_share,
                "frames_used": list(s.frames_used),
                "mean_resolution_m": s.mean_resolution_m,
                "mean_view_angle_deg": s.mean_view_angle_deg,
                "temperature": dict(s.temperature),
                "resolution_px_per_m": s.resolution_px_per_m,
                "best_resolution_m": s.best_resolution_m,
                "mean_observations": s.mean_observations,
                **({"reason": s.reason} if s.reason else {}),
                "typical": s.typical,
                "spread": s.spread,
                "hot_share": s.hot_share,
                "window_share": s.window_share,
                "heat_loss_index": s.heat_loss_index,
                "windows": s.windows,
                "leaks": s.leaks,
            }
            for s in r.surfaces
        ],
    }


def radiometry_document(radiometry: Radiometry | None) -> dict[str, Any]:
    """`report.json`'s `radiometry` member (the tiles' `value = DN · scale + offset` in `unit`);
    empty when not known (a job without results)."""
    if radiometry is None:
        return {}
    return {
        "radiometry": {
            "unit": radiometry.unit,
            "scale": float(radiometry.scale),
            "offset": float(radiometry.offset),
        }
    }


def value_range(results: Sequence[BuildingResult]) -> tuple[float, float]:
    """Display range of a job: 5th percentile of the surfaces' p05, 95th of their p95."""
    lo = [s.temperature["p05"] for r in results for s in r.surfaces if s.temperature]
    hi = [s.temperature["p95"] for r in results for s in r.surfaces if s.temperature]
    if not lo:
        return 0.0, 1.0
    return float(np.percentile(lo, 5)), float(np.percentile(hi, 95))


def write_results_folder(
    out_dir: str | Path,
    *,
    buildings: Sequence[Building],
    results: Sequence[BuildingResult],
    manifest: SequenceManifest,
    priors: Sequence[Pose],
    srs_name: str | None,
    theme: str,
    mounting: Mapping[str, Any] | None = None,
    calibration: Mapping[str, Any] | None = None,
    texel: TexelOptions,
    display: bool = True,
    frames_of: Mapping[str, int] | None = None,
    timings_s: dict[str, float] | None = None,
    job: Mapping[str, Any] | None = None,
    progress: Callable[[int, int], None] | None = None,
    write_time_offset_s: float = 0.0,
    started: float | None = None,
    radiometry: Radiometry | None = None,
    anomalies: bool = True,
) -> dict[str, Any]:
    """Write a whole results folder (`docs/results-format.md`) from building results: the
    in-process run and the service (results loaded from the database) share it.

    Tiles with pixels are written; tiles with an empty `dn` are taken as already written (the
    display copies are then made from the files). `frames_of` gives the frames per building for
    the report, `job` extra report fields; `timings_s` gets the `write` stage time.
    `priors` are the manifest-only priors; `mounting` the estimated mounting for
    `orientation.json` (None: the manifest's, delay 0) and `calibration` the report's
    `calibration` block (None: `{"run": false}`). `texel` (the units' texel-grid options) goes
    into the report whole, so that readers lay the same grids. `radiometry` (the tiles'; default:
    the results') goes into the report as `radiometry` (unit, scale, offset), so that the tiles
    keep their physical meaning when the folder is read back (`db.results_import`). With
    `anomalies`, the results' anomalies go into `anomalies.geojson` (by building, with the
    top-level building id). Returns the `report.json` document.
    """
    t0 = started if started is not None else time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    step = progress or (lambda done, total: None)
    step(0, 4)
    for r in results:
        for tile in r.tiles:
            if tile.dn.size:
                write_tile(out, tile)
    if display:
        rng = value_range(results)
        for r in results:
            for tile in r.tiles:
                write_display_tile(
                    out, tile if tile.dn.size else read_tile(out, tile.name), r.radiometry, rng
                )
    step(1, 4)
    by_id = {r.building_id: r for r in results}
    order = {b.id: k for k, b in enumerate(buildings)}
    write_textured_gml(out / "textured.gml", buildings, by_id, srs_name, display)
    step(2, 4)
    write_json(out / "orientation.json", orientation_document(manifest, priors, results, mounting))
    if anomalies:
        features = [
            anomaly_feature(replace(a, building_id=r.building_id))
            for r in sorted(results, key=lambda r: order.get(r.building_id, len(order)))
            for a in r.anomalies
        ]
        write_json(out / "anomalies.geojson", anomalies_document(features, srs_name))
    step(3, 4)
    timings = timings_s if timings_s is not None else {}
    timings["write"] = time.perf_counter() - t0 + write_time_offset_s
    stage_units: dict[str, float] = {}
    for r in results:
        for key, val in r.timings_s.items():
            stage_units[key] = stage_units.get(key, 0.0) + float(val)
    frames_of = frames_of or {}
    doc: dict[str, Any] = {
        "format": REPORT_FORMAT,
        "theme": theme,
        "resolution_px_per_m": texel.resolution_px_per_m,
        "texel": options_to_dict(texel),
        "frames": len(manifest.frames),
        "buildings_processed": len(results),
        "buildings_textured": sum(1 for r in results if r.appearance is not None),
        **radiometry_document(radiometry or next((r.radiometry for r in results), None)),
        **dict(job or {}),
        "calibration": dict(calibration) if calibration is not None else {"run": False},
        "timings_s": dict(timings),
        "unit_stage_timings_s": stage_units,
        "buildings": [
            building_report(
                r, frames_of.get(r.building_id, len({f for s in r.surfaces for f in s.frames_used}))
            )
            for r in sorted(results, key=lambda r: order.get(r.building_id, len(order)))
        ],
    }
    write_json(out / "report.json", doc)
    step(4, 4)
    return doc

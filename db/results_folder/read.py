"""Reading a results folder back.

In: a results folder written by `citytherm run` (`textured.gml`, `textures/*.png`,
`report.json`, `orientation.json`, `anomalies.geojson` when present). Out:

- `iter_surface_textures`: per textured polygon its `TexelGrid` (recomputed from the polygon with
  the texel options the job wrote into `report.json`: grids are deterministic) and its float32
  texture `(H, W)` (NaN = DN 0), cut out of the atlas tile where the texture coordinates place
  it. Used by the demo, the bench and tests to compare results with a synthetic scene's ground
  truth.
- `read_results_folder` / `read_building_results`: the job's `BuildingResult`s rebuilt from the
  files (appearance, 16-bit tiles, radiometry, statistics, poses, anomalies, unit timings) and
  the prior poses: what `db.results_import` stores in the database, the same rows the units'
  results would give (every number round-trips exactly through the files).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path, PurePosixPath
from typing import Any

import cv2
import numpy as np

from db.citygml import CityGMLError
from db.citygml.reader import iter_buildings, read_model
from workers.pipeline.geometry.citymodel import Appearance, Building, ParameterizedTexture, Polygon
from workers.pipeline.geometry.manifest import Radiometry
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.options import options_from_dict
from workers.pipeline.results import Anomaly, BuildingResult, FramePose, SurfaceStats, TextureTile
from workers.pipeline.texture.texel import TexelGrid, TexelOptions, texel_grid


class ResultsReadError(ValueError):
    """A results folder that does not read back (names the file)."""


@dataclass(frozen=True, eq=False)
class SurfaceTextureFile:
    """One textured polygon of a results folder."""

    building: Building
    polygon: Polygon
    grid: TexelGrid
    value: np.ndarray


def _tile(out_dir: Path, uri: str, cache: dict[str, np.ndarray]) -> np.ndarray:
    if uri not in cache:
        dn = cv2.imread(str(out_dir / uri), cv2.IMREAD_UNCHANGED)
        if dn is None or dn.dtype != np.uint16 or dn.ndim != 2:
            raise ResultsReadError(f"{uri}: not a single-channel 16-bit PNG")
        cache[uri] = dn
    return cache[uri]


def texel_options(report: dict) -> TexelOptions:
    """The texel-grid options a job wrote into its `report.json` (`texel`; older reports give
    only `resolution_px_per_m`, the other options were the defaults then)."""
    try:
        if "texel" in report:
            return options_from_dict(TexelOptions, report["texel"])
        return TexelOptions(resolution_px_per_m=float(report["resolution_px_per_m"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ResultsReadError(f"report.json: texel options: {exc}") from exc


def surface_resolutions(report: dict) -> dict[str, float]:
    """Texels per metre of each surface whose grid the job laid coarser or finer than the job's
    resolution (`report.json` surfaces' `resolution_px_per_m`; older reports have none)."""
    out: dict[str, float] = {}
    for b in report.get("buildings", []):
        for s in b.get("surfaces", []):
            r = s.get("resolution_px_per_m")
            if isinstance(r, int | float) and np.isfinite(r) and r > 0:
                out[str(s["id"])] = float(r)
    return out


def iter_surface_textures(
    out_dir: str | Path, radiometry: Radiometry, theme: str | None = None
) -> Iterator[SurfaceTextureFile]:
    """Yield every textured polygon of the results folder `out_dir` with its texture.

    `theme` defaults to the job's (`report.json`); the texel grids are laid with the options the
    report gives (`texel_options`), never with defaults.
    """
    out = Path(out_dir)
    try:
        rep = json.loads((out / "report.json").read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ResultsReadError(f"{out / 'report.json'}: {exc}") from exc
    theme = theme or rep["theme"]
    opts = texel_options(rep)
    per_surface = surface_resolutions(rep)
    _, buildings = read_model(out / "textured.gml")
    cache: dict[str, np.ndarray] = {}
    for b in buildings:
        owner = {p.id: part.id for part in b.iter_buildings() for p in part.polygons}
        polys = {p.id: p for p in b.iter_polygons()}
        for app in b.appearances:
            if app.theme != theme:
                continue
            for tex in app.surface_data:
                if not isinstance(tex, ParameterizedTexture):
                    continue
                dn = _tile(out, tex.image_uri, cache)
                H, W = dn.shape
                for target in tex.targets:
                    poly = polys.get(target.polygon_id)
                    if poly is None:
                        raise ResultsReadError(f"textured.gml: target #{target.polygon_id} is not a polygon")
                    r = per_surface.get(poly.id)
                    own = opts if r is None else replace(opts, resolution_px_per_m=r)
                    grid = texel_grid(poly, owner[poly.id], own)
                    if grid is None:
                        continue
                    st = target.ring_coords[poly.exterior.id]
                    xy = grid.raster_xy(poly.exterior.coords)
                    col = np.median(st[:, 0] * W - xy[:, 0])
                    row = np.median((1 - st[:, 1]) * H - xy[:, 1])
                    r0, c0 = round(float(row)), round(float(col))
                    h, w = grid.shape
                    block = dn[r0 : r0 + h, c0 : c0 + w]
                    if block.shape != (h, w):
                        raise ResultsReadError(f"{tex.image_uri}: polygon {poly.id} falls outside the tile")
                    value = radiometry.physical(block)
                    value[block == 0] = np.nan
                    yield SurfaceTextureFile(building=b, polygon=poly, grid=grid, value=value)


# --- a results folder back as building results (the database import) -------------------------


@dataclass(frozen=True, eq=False)
class ResultsFolder:
    """A results folder read back, everything but the tile pixels (`building_result` loads those
    per building, so a city-sized folder never sits in memory at once).

    Attributes:
        path: the folder.
        report: `report.json` as read.
        theme: the job's appearance theme (`report.json` `theme`).
        radiometry: the tiles' radiometry (`report.json` `radiometry`).
        building_ids: the buildings the job processed (`report.json` `buildings`), report order.
        failed: `(building id, error)` of the units that failed (`report.json` `failed`).
        priors: frame index -> the manifest-only prior pose (`orientation.json` `prior`).
        mounting: `orientation.json` `mounting`.
        appearances: building id -> the job's appearance of `theme` (`textured.gml`; buildings
            with nothing observed have none).
    """

    path: Path
    report: dict[str, Any]
    theme: str
    radiometry: Radiometry
    building_ids: tuple[str, ...]
    failed: tuple[tuple[str, str], ...]
    priors: dict[int, Pose]
    mounting: dict[str, Any]
    appearances: dict[str, Appearance]
    _surfaces: dict[str, tuple[SurfaceStats, ...]]
    _poses: dict[str, tuple[FramePose, ...]]
    _anomalies: dict[str, tuple[Anomaly, ...]]
    _timings: dict[str, dict[str, float]]

    def polygon_ids(self, building_id: str) -> set[str]:
        """Every polygon id the building's results refer to (statistics, texture targets,
        anomalies): all must be polygons of that building in the model they go into."""
        ids = {s.polygon_id for s in self._surfaces[building_id]}
        app = self.appearances.get(building_id)
        if app is not None:
            ids |= {
                t.polygon_id
                for sd in app.surface_data
                if isinstance(sd, ParameterizedTexture)
                for t in sd.targets
            }
        ids |= {a.polygon_id for a in self._anomalies.get(building_id, ()) if a.polygon_id}
        return ids

    def tile_names(self, building_id: str) -> list[str]:
        """The tiles the building's appearance uses, in its order."""
        app = self.appearances.get(building_id)
        data = app.surface_data if app is not None else ()
        return list(dict.fromkeys(sd.image_uri for sd in data if isinstance(sd, ParameterizedTexture)))

    def building_result(self, building_id: str) -> BuildingResult:
        """The `BuildingResult` of one processed building, tiles read from `textures/`."""
        if building_id not in self._surfaces:
            raise ResultsReadError(f"{self.path / 'report.json'}: building {building_id!r} not in the report")
        cache: dict[str, np.ndarray] = {}
        tiles = tuple(TextureTile(n, _tile(self.path, n, cache)) for n in self.tile_names(building_id))
        return BuildingResult(
            building_id=building_id,
            appearance=self.appearances.get(building_id),
            tiles=tiles,
            radiometry=self.radiometry,
            surfaces=self._surfaces[building_id],
            poses=self._poses.get(building_id, ()),
            anomalies=self._anomalies.get(building_id, ()),
            timings_s=self._timings.get(building_id, {}),
        )

    def iter_building_results(self) -> Iterator[BuildingResult]:
        """`building_result` of every processed building, report order."""
        for bid in self.building_ids:
            yield self.building_result(bid)


def _load_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise ResultsReadError(f"{path}: missing (not a citytherm results folder?)") from exc
    except (OSError, ValueError) as exc:
        raise ResultsReadError(f"{path}: {exc}") from exc


def _get(doc: Any, key: str, where: str, kind: type | tuple[type, ...]) -> Any:
    """`doc[key]`, which must be a `kind`; else an error naming `where` and the field."""
    if not isinstance(doc, dict) or key not in doc:
        raise ResultsReadError(f"{where}: field {key!r} missing")
    value = doc[key]
    if not isinstance(value, kind) or (isinstance(value, bool) and kind in (int, float, (int, float))):
        raise ResultsReadError(f"{where}: field {key!r} has the wrong type ({type(value).__name__})")
    return value


def _num(v: Any) -> float:
    """A JSON number back to float (the writer wrote NaN as null)."""
    return float("nan") if v is None else float(v)


def report_radiometry(report: dict[str, Any], where: str = "report.json") -> Radiometry:
    """The tiles' radiometry a job wrote into its `report.json` (`radiometry`: unit, scale,
    offset). Reports of older versions have none: those folders cannot be put into the database
    (their DNs would have no physical meaning there)."""
    if "radiometry" not in report:
        raise ResultsReadError(
            f"{where}: field 'radiometry' missing (written by an older citytherm): run the job again"
        )
    rad = _get(report, "radiometry", where, dict)
    try:
        out = Radiometry(unit=str(rad["unit"]), scale=float(rad["scale"]), offset=float(rad["offset"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ResultsReadError(f"{where}: field 'radiometry': {exc!r}") from exc
    if out.unit not in ("K", "degC", "counts") or not np.isfinite(out.scale) or out.scale <= 0:
        raise ResultsReadError(f"{where}: field 'radiometry': unit {out.unit!r}, scale {out.scale} not valid")
    return out


def _surface_stats(entry: dict[str, Any], where: str) -> tuple[SurfaceStats, ...]:
    out = []
    for k, s in enumerate(_get(entry, "surfaces", where, list)):
        w = f"{where} surface {k}"
        try:
            out.append(
                SurfaceStats(
                    polygon_id=str(_get(s, "id", w, str)),
                    building_id=str(_get(s, "building", w, str)),
                    surface_class=str(_get(s, "class", w, str)),
                    texels_total=int(_get(s, "texels_total", w, int)),
                    texels_observed=int(_get(s, "texels_observed", w, int)),
                    frames_used=tuple(int(f) for f in _get(s, "frames_used", w, list)),
                    mean_resolution_m=_num(s.get("mean_resolution_m")),
                    mean_view_angle_deg=_num(s.get("mean_view_angle_deg")),
                    temperature={str(key): _num(v) for key, v in _get(s, "temperature", w, dict).items()},
                    resolution_px_per_m=_num(s.get("resolution_px_per_m")),
                    best_resolution_m=_num(s.get("best_resolution_m")),
                    mean_observations=_num(s.get("mean_observations")),
                    reason=str(s.get("reason", "")),
                    typical=_num(s.get("typical")),
                    spread=_num(s.get("spread")),
                    hot_share=_num(s.get("hot_share")),
                    window_share=_num(s.get("window_share")),
                    heat_loss_index=_num(s.get("heat_loss_index")),
                    windows=int(s.get("windows") or 0),
                    leaks=int(s.get("leaks") or 0),
                )
            )
        except (TypeError, ValueError) as exc:
            raise ResultsReadError(f"{w}: {exc}") from exc
    return tuple(out)


def _orientation(
    doc: dict[str, Any], where: str, processed: set[str]
) -> tuple[dict[int, Pose], dict[str, tuple[FramePose, ...]], dict[str, Any]]:
    """(priors by frame, refined poses by building, mounting) of `orientation.json`."""
    priors: dict[int, Pose] = {}
    poses: dict[str, list[FramePose]] = {}
    for k, f in enumerate(_get(doc, "frames", where, list)):
        w = f"{where} frame {k}"
        try:
            index = int(_get(f, "index", w, int))
            priors[index] = Pose.from_dict(_get(f, "prior", w, dict))
            for p in _get(f, "refined", w, list):
                bid = str(_get(p, "building", w, str))
                if bid not in processed:
                    raise ResultsReadError(f"{w}: pose for building {bid!r}, which report.json does not list")
                poses.setdefault(bid, []).append(
                    FramePose(
                        frame=index,
                        building_id=bid,
                        pose=Pose.from_dict(p),
                        status=str(_get(p, "status", w, str)),
                        rms_px=_num(p.get("rms_px")),
                        matches=int(p.get("matches") or 0),
                    )
                )
        except (KeyError, TypeError, ValueError) as exc:
            raise ResultsReadError(f"{w}: {exc!r}") from exc
    mounting = doc.get("mounting") or {}
    return priors, {b: tuple(v) for b, v in poses.items()}, dict(mounting)


def _anomalies(path: Path, processed: set[str]) -> dict[str, tuple[Anomaly, ...]]:
    """Heat-leak candidates of `anomalies.geojson` by building (none when the file is absent)."""
    if not path.is_file():
        return {}
    doc = _load_json(path)
    out: dict[str, list[Anomaly]] = {}
    for k, feat in enumerate(_get(doc, "features", str(path), list)):
        w = f"{path} feature {k}"
        try:
            props = _get(feat, "properties", w, dict)
            bid = str(_get(props, "building", w, str))
            if bid not in processed:
                raise ResultsReadError(f"{w}: building {bid!r}, which report.json does not list")
            rings = (feat.get("geometry") or {}).get("coordinates") or []
            outline = np.asarray(rings[0], dtype=np.float64).reshape(-1, 3) if rings else np.zeros((0, 3))
            out.setdefault(bid, []).append(
                Anomaly(
                    building_id=bid,
                    polygon_id=props.get("surface"),
                    outline=outline,
                    centre=np.asarray(props["centre"], dtype=np.float64).reshape(3),
                    area_m2=float(props["area_m2"]),
                    peak_delta_k=float(props["peak_delta_k"]),
                    mean_delta_k=float(props["mean_delta_k"]),
                    kind=str(props.get("kind") or "leak"),
                    id=str(props.get("id") or ""),
                    frames=int(props.get("frames") or 0),
                    best_resolution_m=_num(props.get("best_resolution_m")),
                    confidence=_num(props.get("confidence")),
                )
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ResultsReadError(f"{w}: {exc!r}") from exc
    return {b: tuple(v) for b, v in out.items()}


def _safe_tile_name(name: str, where: str) -> str:
    """A tile name must stay inside the results folder (never read elsewhere)."""
    p = PurePosixPath(name)
    if p.is_absolute() or ".." in p.parts or not p.parts or ":" in name or "\\" in name:
        raise ResultsReadError(f"{where}: imageURI {name!r} is not a relative path inside the results folder")
    return name


def _job_appearances(path: Path, theme: str, tiles_of: dict[str, set[str]]) -> dict[str, Appearance]:
    """The job's appearance of each processed building in `textured.gml`: of `theme`, its images
    among the building's tiles in `report.json` (an appearance of the same theme that came with
    the input model, e.g. an earlier job's exported textures, is not the job's)."""
    try:
        buildings = iter_buildings(path)
        out: dict[str, Appearance] = {}
        for b in buildings:
            if b.id not in tiles_of:
                continue
            for app in b.appearances:  # the writer puts the job's after the input's own
                uris = {sd.image_uri for sd in app.surface_data if isinstance(sd, ParameterizedTexture)}
                if app.theme == theme and uris and uris <= tiles_of[b.id]:
                    out[b.id] = app
    except CityGMLError as exc:
        raise ResultsReadError(f"{path}: {exc}") from exc
    for bid, app in out.items():
        for sd in app.surface_data:
            if isinstance(sd, ParameterizedTexture):
                _safe_tile_name(sd.image_uri, f"{path} building {bid!r}")
    return out


def read_results_folder(folder: str | Path) -> ResultsFolder:
    """Read a results folder written by `citytherm run` (or the service) back: everything a
    `BuildingResult` holds except the tile pixels, checked (every referenced tile exists).

    Sources: `report.json` (theme, radiometry, processed and failed buildings, per-surface
    statistics, unit timings), `orientation.json` (prior and refined poses), `textured.gml` (the
    job's appearance of each building: theme `theme`, images among the building's tiles),
    `textures/` (checked here, read by `ResultsFolder.building_result`) and `anomalies.geojson`
    when present. Raises `ResultsReadError` naming the file and field."""
    out = Path(folder)
    if not out.is_dir():
        raise ResultsReadError(f"{out}: not a folder")
    where = str(out / "report.json")
    report = _load_json(out / "report.json")
    if not isinstance(report, dict):
        raise ResultsReadError(f"{where}: not a JSON object")
    theme = _get(report, "theme", where, str)
    # a job without results writes no radiometry, and needs none: there are no tiles
    no_tiles = "radiometry" not in report and not report.get("buildings")
    radiometry = Radiometry() if no_tiles else report_radiometry(report, where)
    surfaces: dict[str, tuple[SurfaceStats, ...]] = {}
    timings: dict[str, dict[str, float]] = {}
    tiles_of: dict[str, set[str]] = {}
    for k, entry in enumerate(_get(report, "buildings", where, list)):
        w = f"{where} buildings[{k}]"
        bid = _get(entry, "id", w, str)
        if bid in surfaces:
            raise ResultsReadError(f"{w}: building {bid!r} listed twice")
        surfaces[bid] = _surface_stats(entry, f"{w} ({bid})")
        timings[bid] = {str(key): float(v) for key, v in (entry.get("timings_s") or {}).items()}
        tiles_of[bid] = {str(t) for t in (entry.get("tiles") or [])}
    failed = tuple(
        (str(_get(f, "id", f"{where} failed", str)), str(f.get("error", "")))
        for f in report.get("failed") or []
    )
    processed = set(surfaces)
    orientation = out / "orientation.json"
    priors, poses, mounting = _orientation(_load_json(orientation), str(orientation), processed)
    gml = out / "textured.gml"
    if not gml.is_file():
        raise ResultsReadError(f"{gml}: missing (not a citytherm results folder?)")
    appearances = _job_appearances(gml, theme, tiles_of)
    rf = ResultsFolder(
        path=out,
        report=report,
        theme=theme,
        radiometry=radiometry,
        building_ids=tuple(surfaces),
        failed=failed,
        priors=priors,
        mounting=mounting,
        appearances=appearances,
        _surfaces=surfaces,
        _poses=poses,
        _anomalies=_anomalies(out / "anomalies.geojson", processed),
        _timings=timings,
    )
    for bid in rf.building_ids:
        for name in rf.tile_names(bid):
            if not (out / name).is_file():
                raise ResultsReadError(f"{out / name}: missing (texture of building {bid!r} in textured.gml)")
    return rf


def read_building_results(folder: str | Path) -> tuple[ResultsFolder, list[BuildingResult]]:
    """`read_results_folder` and every building's `BuildingResult` with its tiles (small folders:
    tests, scripts; the database import reads building by building)."""
    rf = read_results_folder(folder)
    return rf, list(rf.iter_building_results())

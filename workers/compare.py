"""`citytherm compare`: the change between two texturing jobs on the same city model (e.g. two
winters), per facade and as ΔT textures.

In: two jobs, A (the earlier survey) and B, each as a `Survey`: from a results folder
(`survey_from_folder`, `db.results_folder.read`) or from the database (`workers.compare_db`).
Out: a folder with

- `change.json` (`citytherm-change/1`): the jobs, the ΔT tiles' radiometry, and per building and
  surface observed by both: `typical_a`, `typical_b` (kelvin), `delta_typical_k` (B − A),
  `normalised_delta_k` (when both surveys give the air temperature;
  `workers.pipeline.change.normalised_delta`), `observed_both_share`, `texels`, `texels_both`,
  `delta_median_k`, `delta_mean_k`, `delta_p05_k`, `delta_p95_k` (over the texels observed in
  both), `resolution_px_per_m` (the common grid's);
- `change.gml`: the compared buildings with one CityGML 2.0 appearance of theme `thermal-change`
  whose textures (`textures/*.png`, 16-bit, `value = DN · 0.001 − 32.0` kelvin, DN 0 = not observed
  in both) hold `B − A`.

Everything is written into a temporary sibling folder first and moved into place at the end:
bad input (`CompareError`, naming the file, field or job) leaves the output folder as it was.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from db.citygml import CityGMLError
from db.citygml.reader import read_model
from db.results_folder.read import ResultsReadError, read_results_folder
from db.results_folder.write import write_json, write_textured_gml, write_tile
from db.sequence_conditions import parse_conditions
from workers.pipeline.change import (
    DELTA_RADIOMETRY,
    ChangeError,
    ChangeOptions,
    SurfaceTexture,
    kelvin,
    normalised_delta,
    surface_change,
)
from workers.pipeline.geometry.citymodel import (
    Appearance,
    Building,
    ParameterizedTexture,
    Polygon,
    TextureTarget,
)
from workers.pipeline.geometry.manifest import Conditions
from workers.pipeline.results import BuildingResult, SurfaceStats, TextureTile
from workers.pipeline.texture.atlas import build_atlas

CHANGE_FORMAT = "citytherm-change/1"
CHANGE_THEME = "thermal-change"
OUTPUTS = ("change.json", "change.gml", "textures")


class CompareError(ValueError):
    """Two jobs that cannot be compared, or an output folder that cannot take the result."""


@dataclass(frozen=True, eq=False)
class Survey:
    """One side of a comparison.

    Attributes:
        source: how the job was named: `{"folder": ...}` or `{"job": ..., "database": ...}`.
        theme: the job's appearance theme.
        city_model: the city model's name or file, as the job records it (None: unknown).
        conditions: the survey's conditions (air temperature), when its manifest gave them.
        building_ids: the top-level buildings the job textured, in its order.
        load: building id -> the job's `BuildingResult` (tiles included).
        extra: further members for `change.json` (times).
    """

    source: dict[str, Any]
    theme: str
    city_model: str | None
    conditions: Conditions | None
    building_ids: tuple[str, ...]
    load: Callable[[str], BuildingResult]
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def air_temperature_k(self) -> float | None:
        """The survey's outside air temperature, kelvin (None: not given)."""
        return None if self.conditions is None else self.conditions.air_temperature_k

    def document(self) -> dict[str, Any]:
        """The job's member of `change.json`."""
        cond = self.conditions.to_dict() if self.conditions is not None else None
        return {
            **self.source,
            "theme": self.theme,
            "city_model": self.city_model,
            "conditions": cond,
            **self.extra,
        }


def conditions_of(doc: Any, where: str) -> Conditions | None:
    """`Conditions` of a `conditions` JSON value (None when absent); `CompareError` naming
    `where` and the field when it does not parse."""
    if doc is None:
        return None
    try:
        return parse_conditions(doc)
    except ValueError as exc:
        raise CompareError(f"{where}: {exc}") from None


# -- one building -------------------------------------------------------------------------------


def _textures(r: BuildingResult) -> dict[str, tuple[np.ndarray, TextureTarget]]:
    """Polygon id -> (its tile's DNs `(H, W)` uint16, its target) of the job's appearance."""
    tiles = {t.name: t.dn for t in r.tiles}
    out: dict[str, tuple[np.ndarray, TextureTarget]] = {}
    for sd in r.appearance.surface_data if r.appearance is not None else ():
        if isinstance(sd, ParameterizedTexture) and sd.image_uri in tiles:
            for target in sd.targets:
                out[target.polygon_id] = (tiles[sd.image_uri], target)
    return out


def _surface_texture(
    poly: Polygon, r: BuildingResult, tex: tuple[np.ndarray, TextureTarget], s: SurfaceStats
) -> SurfaceTexture | None:
    """One job's `SurfaceTexture` of `poly` (None: no texture coordinates for its exterior)."""
    dn, target = tex
    st = target.ring_coords.get(poly.exterior.id)
    if st is None or len(st) != len(poly.exterior.coords):
        return None
    return SurfaceTexture(
        dn=dn,
        st=np.asarray(st, np.float64),
        radiometry=r.radiometry,
        resolution_px_per_m=s.resolution_px_per_m,
    )


def typical_k(s: SurfaceStats, unit: str) -> tuple[float, str]:
    """The surface's typical temperature in kelvin and where it comes from: `typical` (the
    anomaly stage's robust value), else the median of the observed texels (`median`: results
    without the anomaly stage)."""
    if math.isfinite(s.typical):
        return float(kelvin(s.typical, unit)), "typical"
    med = s.temperature.get("median", float("nan"))
    return (float(kelvin(med, unit)), "median") if math.isfinite(med) else (float("nan"), "none")


def building_change(
    building: Building,
    ra: BuildingResult,
    rb: BuildingResult,
    air: tuple[float | None, float | None],
    options: ChangeOptions,
) -> tuple[dict[str, Any], tuple[TextureTile, ...], Appearance | None]:
    """Per-surface figures (`change.json`'s building entry), ΔT tiles and their appearance (None:
    no texel observed by both) for one building observed by both jobs; `air`: the surveys' air
    temperatures, kelvin. Raises `ChangeError` naming the polygon."""
    stats_a = {s.polygon_id: s for s in ra.surfaces}
    stats_b = {s.polygon_id: s for s in rb.surfaces}
    tex_a, tex_b = _textures(ra), _textures(rb)
    owner = {p.id: part.id for part in building.iter_buildings() for p in part.polygons}
    surfaces, polys, grids, deltas = [], [], [], []
    for poly in building.iter_polygons():
        sa, sb = stats_a.get(poly.id), stats_b.get(poly.id)
        if sa is None or sb is None or not (sa.texels_observed and sb.texels_observed):
            continue
        ta, how_a = typical_k(sa, ra.radiometry.unit)
        tb, how_b = typical_k(sb, rb.radiometry.unit)
        entry: dict[str, Any] = {
            "id": poly.id,
            "building": owner[poly.id],
            "class": poly.surface_class,
            "typical_a": ta,
            "typical_b": tb,
            "delta_typical_k": tb - ta,
            "normalised_delta_k": normalised_delta(ta, tb, *air),
        }
        if {how_a, how_b} != {"typical"}:
            entry["typical_from"] = [how_a, how_b]
        a = _surface_texture(poly, ra, tex_a[poly.id], sa) if poly.id in tex_a else None
        b = _surface_texture(poly, rb, tex_b[poly.id], sb) if poly.id in tex_b else None
        ch = None
        if a is not None and b is not None:
            ch = surface_change(poly, owner[poly.id], a, b, options)
        if ch is None:
            entry |= {"observed_both_share": 0.0, "texels": sa.texels_total, "texels_both": 0}
        else:
            entry |= {"texels": ch.texels, "texels_both": ch.texels_both, **ch.figures()}
            entry["resolution_px_per_m"] = 1.0 / ch.grid.size
            if ch.texels_both:
                polys.append(poly)
                grids.append(ch.grid)
                deltas.append(ch.delta)
        surfaces.append(entry)
    tiles, app = build_atlas(building.id, polys, grids, deltas, DELTA_RADIOMETRY, CHANGE_THEME)
    doc = {
        "id": building.id,
        "surfaces_compared": len(surfaces),
        "texels_both": int(sum(e["texels_both"] for e in surfaces)),
        "tiles": [t.name for t in tiles],
        "surfaces": surfaces,
    }
    return doc, tiles, app


# -- the whole comparison -----------------------------------------------------------------------


def _same_geometry(ba: Building, bb: Building, where: str) -> None:
    """Refuse two versions of a building whose polygons differ (ids or vertices, 1 mm)."""
    pa, pb = list(ba.iter_polygons()), list(bb.iter_polygons())
    if [p.id for p in pa] != [p.id for p in pb]:
        raise CompareError(f"{where}: building {ba.id} has other polygons than in A: not the same city model")
    for p, q in zip(pa, pb, strict=True):
        if (
            p.exterior.coords.shape != q.exterior.coords.shape
            or np.abs(p.exterior.coords - q.exterior.coords).max() > 1e-3
        ):
            raise CompareError(
                f"{where}: polygon {p.id} of building {ba.id} differs from A's: not the same city model"
            )


def check_output(out: Path) -> None:
    """The output folder must be new, empty or an earlier comparison's (then replaced)."""
    if out.exists() and (not out.is_dir() or any(p.name not in OUTPUTS for p in out.iterdir())):
        raise CompareError(f"{out}: exists and is not an empty folder or a comparison's output")


def _publish(tmp: Path, out: Path) -> None:
    """Move the finished outputs from `tmp` into `out` (replacing an earlier comparison's)."""
    if not out.exists():
        tmp.rename(out)
        return
    for name in OUTPUTS:
        old = out / name
        if old.is_dir():
            shutil.rmtree(old)
        elif old.exists():
            old.unlink()
        if (tmp / name).exists():
            (tmp / name).rename(old)
    shutil.rmtree(tmp, ignore_errors=True)


def compare_surveys(
    a: Survey,
    b: Survey,
    buildings: Iterable[Building],
    srs_name: str | None,
    out_dir: str | Path,
    options: ChangeOptions = ChangeOptions(),
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Compare `b` against `a` over `buildings` (the city model's, as the jobs textured them; those
    both jobs textured are compared) and write the output folder `out_dir` (module docstring).
    Returns the `change.json` document. Raises `CompareError`."""
    out = Path(out_dir)
    check_output(out)
    ids_b = set(b.building_ids)
    common = [bid for bid in a.building_ids if bid in ids_b]
    if not common:
        raise CompareError(
            f"A ({a.city_model or a.source}) and B ({b.city_model or b.source}) textured no building in "
            "common: not the same city model, or surveys of different streets"
        )
    by_id = {bb.id: bb for bb in buildings if bb.id in ids_b}
    air = (a.air_temperature_k, b.air_temperature_k)
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        entries, written, results = [], [], {}
        for k, bid in enumerate(common):
            if bid not in by_id:
                raise CompareError(f"building {bid}: textured by both jobs but not in the city model given")
            try:
                doc, tiles, app = building_change(by_id[bid], a.load(bid), b.load(bid), air, options)
            except ChangeError as exc:
                raise CompareError(f"building {bid}: {exc}") from None
            for t in tiles:
                write_tile(tmp, t)
            if app is not None:
                written.append(by_id[bid])
                results[bid] = BuildingResult(bid, app, (), DELTA_RADIOMETRY, ())
            entries.append(doc)
            if progress is not None:
                progress(k + 1, len(common))
        write_textured_gml(
            tmp / "change.gml", [_bare(bb) for bb in written], results, srs_name, display=False
        )
        document = change_document(a, b, entries)
        write_json(tmp / "change.json", document)
        _publish(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return document


def _bare(b: Building) -> Building:
    """The building without the appearances it came with (change.gml holds `thermal-change` only)."""
    return replace(b, appearances=(), parts=tuple(_bare(p) for p in b.parts))


def change_document(a: Survey, b: Survey, buildings: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The `change.json` document (module docstring)."""
    surfaces = [s for bd in buildings for s in bd["surfaces"]]
    d = np.array([s["delta_typical_k"] for s in surfaces], dtype=np.float64)
    n = np.array(
        [s["normalised_delta_k"] for s in surfaces if s["normalised_delta_k"] is not None], np.float64
    )
    return {
        "format": CHANGE_FORMAT,
        "a": a.document(),
        "b": b.document(),
        "delta": "B - A",
        "theme": CHANGE_THEME,
        "radiometry": {"unit": "K", "scale": DELTA_RADIOMETRY.scale, "offset": DELTA_RADIOMETRY.offset},
        "normalised": a.air_temperature_k is not None and b.air_temperature_k is not None,
        "summary": {
            "buildings": len(buildings),
            "surfaces": len(surfaces),
            "texels_both": int(sum(bd["texels_both"] for bd in buildings)),
            "median_delta_typical_k": float(np.nanmedian(d)) if np.isfinite(d).any() else None,
            "median_normalised_delta_k": float(np.median(n)) if n.size else None,
        },
        "buildings": list(buildings),
    }


# -- results folders ----------------------------------------------------------------------------


def survey_from_folder(folder: str | Path) -> tuple[Survey, dict[str, Building], str | None]:
    """A results folder as a `Survey`, its textured buildings by id (`textured.gml`) and the
    model's `srsName`. Raises `CompareError` naming the file and field."""
    path = Path(folder)
    try:
        rf = read_results_folder(path)
        header, buildings = read_model(path / "textured.gml")
    except ResultsReadError as exc:
        raise CompareError(str(exc)) from None
    except (CityGMLError, OSError) as exc:
        raise CompareError(f"{path / 'textured.gml'}: {exc}") from None
    where = str(path / "report.json")
    if rf.building_ids and rf.radiometry.unit not in ("K", "degC"):
        raise CompareError(f"{where}: radiometry unit {rf.radiometry.unit!r} carries no temperature")
    textured = tuple(bid for bid in rf.building_ids if bid in rf.appearances)
    survey = Survey(
        source={"folder": str(path)},
        theme=rf.theme,
        city_model=rf.report.get("city_model"),
        conditions=conditions_of(rf.report.get("conditions"), f"{where}: field 'conditions'"),
        building_ids=textured,
        load=rf.building_result,
    )
    return survey, {b.id: b for b in buildings}, header.srs_name


def compare_folders(
    folder_a: str | Path,
    folder_b: str | Path,
    out_dir: str | Path,
    options: ChangeOptions = ChangeOptions(),
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """`compare_surveys` of two results folders (A the earlier survey). The buildings both
    textured must have the same polygons in both `textured.gml` files. Returns `change.json`."""
    check_output(Path(out_dir))
    a, blds_a, srs = survey_from_folder(folder_a)
    b, blds_b, _ = survey_from_folder(folder_b)
    for bid, ba in blds_a.items():
        if bid in blds_b:
            _same_geometry(ba, blds_b[bid], f"{Path(folder_b) / 'textured.gml'}")
    return compare_surveys(a, b, blds_a.values(), srs, out_dir, options, progress)


def read_change(folder: str | Path) -> dict[str, Any]:
    """`change.json` of a comparison's output folder (tests, scripts)."""
    return json.loads((Path(folder) / "change.json").read_text(encoding="utf-8"))

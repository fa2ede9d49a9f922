"""What the 3D Tiles export reads: a folder with `textured.gml` and its 16-bit texture tiles,
the theme, the radiometry and per-surface figures.

In: a results folder (`docs/results-format.md`: `report.json` gives theme, radiometry and the
surfaces' statistics), or a folder the database export wrote (`db.export.export_citygml`) with a
`tiles3d-source.json` beside it (`SOURCE_FORMAT`: theme, radiometry, surface figures from the
database; `db.tiles3d.database`). Out: a `ThermalSource`: buildings streamed from `textured.gml`
(any number of passes), tiles read by URI (16-bit, checked to stay inside the folder), the
`ValueScale` and every polygon's `SurfaceFigures` in its unit (kelvin for temperatures).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import cv2
import numpy as np

from db.citygml import CityGMLError, open_model
from db.citygml.reader import iter_buildings
from db.results_folder.read import ResultsReadError, report_radiometry
from db.tiles3d.content import SurfaceFigures
from db.tiles3d.images import ValueScale
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.manifest import Radiometry

__all__ = ["SOURCE_FORMAT", "SourceError", "ThermalSource", "folder_source", "write_source_file"]

SOURCE_FORMAT = "citytherm-3dtiles-source/1"
SOURCE_FILE = "tiles3d-source.json"


class SourceError(ValueError):
    """A folder the export cannot read (names the file)."""


def _num(v: Any) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return math.nan
    return f if math.isfinite(f) else math.nan


@dataclass(frozen=True, eq=False)
class ThermalSource:
    """A textured model to export.

    Attributes:
        folder: the folder `textured.gml` and the texture URIs are relative to.
        theme: the appearance theme whose textures are exported.
        srs_name: the model CRS as written in `textured.gml`.
        values: DN -> value (kelvin or counts) of the tiles.
        figures: polygon `gml:id` -> its figures, in `values.unit`.
        label: where it came from (for messages and `asset.extras`).
    """

    folder: Path
    theme: str
    srs_name: str
    values: ValueScale
    figures: Mapping[str, SurfaceFigures]
    label: str

    @property
    def gml(self) -> Path:
        """The CityGML file."""
        return self.folder / "textured.gml"

    def buildings(self) -> Iterator[Building]:
        """The model's top-level buildings, streamed (document order)."""
        return iter_buildings(self.gml, huge_tree=True)

    def read_tile(self, uri: str) -> np.ndarray:
        """The 16-bit texture tile at `uri` (relative to the folder) as `(H, W)` uint16."""
        p = PurePosixPath(uri)
        if p.is_absolute() or ".." in p.parts or ":" in uri or "\\" in uri:
            raise SourceError(f"{self.gml}: imageURI {uri!r} is not a relative path inside the folder")
        dn = cv2.imread(str(self.folder / uri), cv2.IMREAD_UNCHANGED)
        if dn is None or dn.dtype != np.uint16 or dn.ndim != 2:
            raise SourceError(f"{self.folder / uri}: not a single-channel 16-bit PNG")
        return dn


def _srs_name(gml: Path) -> str:
    try:
        header, buildings, _ = open_model(gml, huge_tree=True)
        srs = header.srs_name
        if not srs:
            first = next(iter(buildings), None)
            srs = first.srs_name if first is not None else None
    except (CityGMLError, OSError) as exc:
        raise SourceError(f"{gml}: {exc}") from exc
    if not srs:
        raise SourceError(f"{gml}: names no CRS (srsName): cannot place it on the globe")
    return srs


def _report_figures(report: dict[str, Any], values: ValueScale, unit: str) -> dict[str, SurfaceFigures]:
    """Surface figures of a `report.json` (temperatures in the radiometry `unit`)."""
    out: dict[str, SurfaceFigures] = {}
    for b in report.get("buildings") or []:
        for s in b.get("surfaces") or []:
            t = s.get("temperature") or {}

            def conv(v: Any) -> float:
                return values.to_unit(_num(v), unit)

            out[str(s.get("id"))] = SurfaceFigures(
                mean=conv(t.get("mean")),
                typical=conv(s.get("typical")),
                p05=conv(t.get("p05")),
                p95=conv(t.get("p95")),
                observed_share=_num(s.get("observed_share")),
            )
    return out


def write_source_file(
    folder: Path, theme: str, radiometry: Radiometry, figures: Mapping[str, SurfaceFigures]
) -> Path:
    """Write `tiles3d-source.json` (theme, radiometry, figures in the ValueScale unit) into a
    folder the database export wrote."""
    doc = {
        "format": SOURCE_FORMAT,
        "theme": theme,
        "radiometry": {"unit": radiometry.unit, "scale": radiometry.scale, "offset": radiometry.offset},
        "surfaces": {
            k: [None if math.isnan(x) else x for x in (f.mean, f.typical, f.p05, f.p95, f.observed_share)]
            for k, f in figures.items()
        },
    }
    path = folder / SOURCE_FILE
    path.write_text(json.dumps(doc, allow_nan=False), encoding="utf-8")
    return path


def folder_source(folder: str | Path, theme: str | None = None) -> ThermalSource:
    """The `ThermalSource` of a results folder or of a database export folder (see the module
    docstring); `theme` defaults to the job's. Raises `SourceError` naming the file."""
    out = Path(folder)
    gml = out / "textured.gml"
    if not gml.is_file():
        raise SourceError(f"{gml}: missing (not a citytherm results folder?)")
    src, rep = out / SOURCE_FILE, out / "report.json"
    path = src if src.is_file() else rep
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise SourceError(f"{rep}: missing (not a citytherm results folder?)") from exc
    except (OSError, ValueError) as exc:
        raise SourceError(f"{path}: {exc}") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("theme"), str):
        raise SourceError(f"{path}: no job theme")
    try:
        radiometry = report_radiometry(doc, str(path))
    except ResultsReadError as exc:
        raise SourceError(str(exc)) from exc
    values = ValueScale.of(radiometry)
    if path == src:
        if doc.get("format") != SOURCE_FORMAT:
            raise SourceError(f"{path}: format {doc.get('format')!r}, expected {SOURCE_FORMAT!r}")
        figures = {
            str(k): SurfaceFigures(*(_num(x) for x in v)) for k, v in (doc.get("surfaces") or {}).items()
        }
    else:
        figures = _report_figures(doc, values, radiometry.unit)
    return ThermalSource(
        folder=out,
        theme=theme or doc["theme"],
        srs_name=_srs_name(gml),
        values=values,
        figures=figures,
        label=str(out),
    )

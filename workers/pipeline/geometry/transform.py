"""City model coordinates from one projected CRS into another, heights kept.

In: the CRS names of a model and of a target (as written in CityGML: `EPSG:25833`,
`urn:ogc:def:crs,crs:EPSG:6.12:25833,crs:EPSG:6.12:5783`, AdV URNs; `crs.resolve_crs`), buildings
or points `(N, 3)` in the source CRS (metres, z up). Out: the same in the target CRS. The
horizontal coordinates are transformed with pyproj (e.g. ETRS89 / UTM 33N to ETRS89 / UTM 32N);
heights are kept as they are, which is exact when both CRSs share the height system (or the
target names none). A change of height system (DHHN92 to DHHN2016, ellipsoidal to normal
heights) needs geoid grids that are not available offline: `CrsTransformError` says so.
Texture coordinates are per ring vertex and do not change.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
import pyproj

from workers.pipeline.geometry.citymodel import Appearance, Building, GeoreferencedTexture, Polygon, Ring
from workers.pipeline.geometry.crs import horizontal_crs, vertical_epsg


class CrsTransformError(ValueError):
    """A transformation that cannot be made exactly offline (names both CRSs)."""


@dataclass(frozen=True)
class CrsTransform:
    """Horizontal transformation between two CRSs, heights kept (see the module docstring).

    Attributes:
        source: CRS name of the input coordinates, as written.
        target: CRS name of the output coordinates, as written.
        decimals: round the transformed horizontal coordinates to this many decimals (metres for
            a projected target); None: not rounded. With 6 (a micrometre, far below any survey's
            accuracy and above PROJ's round-trip error of about 2 nm), coordinates transformed
            there and back come out with the digits they were written with.
    """

    source: str
    target: str
    decimals: int | None = None

    def __post_init__(self) -> None:
        src_v, dst_v = vertical_epsg(self.source), vertical_epsg(self.target)
        if src_v is not None and dst_v is not None and src_v != dst_v:
            raise CrsTransformError(
                f"heights in EPSG:{src_v} ({self.source}) cannot be converted to EPSG:{dst_v} "
                f"({self.target}) without geoid grids; import the model into a database of its own "
                "height system"
            )

    def _transformer(self) -> pyproj.Transformer:
        return _pyproj_transformer(horizontal_crs(self.source), horizontal_crs(self.target))

    @property
    def identity(self) -> bool:
        """True when both CRSs have the same horizontal CRS (nothing to transform)."""
        return horizontal_crs(self.source) == horizontal_crs(self.target)

    def points(self, xyz: np.ndarray) -> np.ndarray:
        """`(N, 3)` (or `(N, 2)`) source coordinates -> the same shape in the target CRS."""
        xyz = np.asarray(xyz, dtype=np.float64)
        if self.identity:
            return xyz.copy()
        out = xyz.copy()
        x, y = self._transformer().transform(xyz[..., 0], xyz[..., 1])
        out[..., 0], out[..., 1] = x, y
        if self.decimals is not None:
            out[..., :2] = np.round(out[..., :2], self.decimals)
        if not np.all(np.isfinite(out[..., :2])):
            raise CrsTransformError(f"coordinates outside the area of {self.source} -> {self.target}")
        return out


@lru_cache(maxsize=16)
def _pyproj_transformer(source: str, target: str) -> pyproj.Transformer:
    """One pyproj transformer per pair of horizontal CRSs (creating one takes milliseconds)."""
    return pyproj.Transformer.from_crs(source, target, always_xy=True)


def transform_building(building: Building, transform: CrsTransform, *, set_srs: bool = True) -> Building:
    """`building` (with its parts) in the target CRS: every ring's vertices transformed (all rings
    of the building in one call), `srs_name` set to the target (kept as it was with
    `set_srs=False`: the database keeps the names as read); ids, attributes and appearances
    kept (a `GeoreferencedTexture`'s reference point is transformed too)."""
    if transform.identity:
        return _with_srs(building, transform.target) if set_srs else building
    rings = [r for p in building.iter_polygons() for r in p.rings]
    if not rings:
        return _with_srs(building, transform.target)
    sizes = [len(r.coords) for r in rings]
    moved = np.split(transform.points(np.concatenate([r.coords for r in rings])), np.cumsum(sizes)[:-1])
    new_coords = {id(r): c for r, c in zip(rings, moved, strict=True)}
    return _rebuild(building, new_coords, transform, set_srs)


def _ring(r: Ring, new_coords: dict[int, np.ndarray]) -> Ring:
    return replace(r, coords=new_coords[id(r)])


def _polygon(p: Polygon, new_coords: dict[int, np.ndarray]) -> Polygon:
    interiors = tuple(_ring(r, new_coords) for r in p.interiors)
    return replace(p, exterior=_ring(p.exterior, new_coords), interiors=interiors)


def _appearance(a: Appearance, transform: CrsTransform) -> Appearance:
    data = []
    for sd in a.surface_data:
        if isinstance(sd, GeoreferencedTexture) and sd.reference_point is not None:
            pt = transform.points(np.asarray(sd.reference_point, float)[None])[0]
            sd = replace(sd, reference_point=tuple(float(v) for v in pt))
        data.append(sd)
    return replace(a, surface_data=tuple(data))


def _rebuild(
    b: Building, new_coords: dict[int, np.ndarray], transform: CrsTransform, set_srs: bool
) -> Building:
    return replace(
        b,
        polygons=tuple(_polygon(p, new_coords) for p in b.polygons),
        parts=tuple(_rebuild(part, new_coords, transform, set_srs) for part in b.parts),
        appearances=tuple(_appearance(a, transform) for a in b.appearances),
        srs_name=transform.target if set_srs else b.srs_name,
    )


def _with_srs(b: Building, srs_name: str) -> Building:
    return replace(b, srs_name=srs_name, parts=tuple(_with_srs(p, srs_name) for p in b.parts))

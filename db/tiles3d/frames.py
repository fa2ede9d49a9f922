"""Coordinate frames of the 3D Tiles export: model CRS -> ECEF (EPSG:4978) -> a local
east-north-up frame -> glTF's y-up frame.

In: points `(N, 3)` float64 in the city model's CRS (as written in CityGML: `EPSG:25832`, OGC
compound URNs, AdV URNs; `workers.pipeline.geometry.crs.resolve_crs`), metres, z up. Out: ECEF
points `(N, 3)` float64 (metres, WGS 84 geocentric), the local frame's 4×4 matrices.

Heights: the transformation is pyproj's best *available* one from the model's 3D CRS (a compound
CRS when the name carries a height system) to EPSG:4978. Normal heights (DHHN92, DHHN2016) need
the quasigeoid grid (e.g. `de_bkg_gcg2016.tif`) to become ellipsoidal heights; where PROJ has no
such grid offline, pyproj falls back to a "ballpark" operation that takes the heights as
ellipsoidal (Germany: 36-50 m too low against WGS 84 terrain). `EcefTransform.exact` says which
case applies and `geoid_undulation_m` adds a constant undulation instead (docs/3dtiles.md).
A model CRS without a height system (`EPSG:25832`) has its heights taken as ellipsoidal.

Frames (names `target_from_source`): `ecef_from_enu` (4×4) places the local east-north-up frame
at an origin; glTF content is y-up and 3D Tiles turns it z-up at run time with
`Y_UP_TO_Z_UP`, so a GLB vertex `p` lands at `tile_transform · Y_UP_TO_Z_UP · p` (ECEF).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pyproj

from workers.pipeline.geometry.crs import resolve_crs

__all__ = ["Y_UP_TO_Z_UP", "EcefTransform", "column_major", "ecef_from_enu", "ecef_transform", "yup"]

#: glTF y-up -> 3D Tiles z-up: (x, y, z) -> (x, -z, y), applied by 3D Tiles runtimes to glTF content.
Y_UP_TO_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


@dataclass(frozen=True, eq=False)
class EcefTransform:
    """Model CRS -> ECEF.

    Attributes:
        srs_name: the model CRS as written.
        transformer: pyproj transformer (always_xy) from the model's 3D CRS to EPSG:4978.
        exact: True when pyproj's best operation is available (heights converted as the CRS says),
            False when it fell back to a ballpark one (missing geoid grid: heights as ellipsoidal).
        operation: pyproj's description of the operation used.
        geoid_undulation_m: constant added to every height before the transformation, metres.
    """

    srs_name: str
    transformer: pyproj.Transformer
    exact: bool
    operation: str
    geoid_undulation_m: float = 0.0

    def points(self, xyz: np.ndarray) -> np.ndarray:
        """`(N, 3)` model coordinates -> `(N, 3)` float64 ECEF metres."""
        p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
        x, y, z = self.transformer.transform(p[:, 0], p[:, 1], p[:, 2] + self.geoid_undulation_m)
        return np.stack([np.asarray(x), np.asarray(y), np.asarray(z)], axis=-1)


@lru_cache(maxsize=32)
def _transform(srs_name: str) -> tuple[pyproj.Transformer, bool, str]:
    crs = resolve_crs(srs_name)
    if not crs.is_compound and len(crs.axis_info) == 2:
        crs = crs.to_3d()  # heights without a height system: ellipsoidal
    with warnings.catch_warnings():  # a missing grid is reported by `exact`, not as a warning
        warnings.simplefilter("ignore", UserWarning)
        group = pyproj.transformer.TransformerGroup(crs, "EPSG:4978", always_xy=True)
    if not group.transformers:
        raise ValueError(f"no transformation from {srs_name!r} to ECEF (EPSG:4978)")
    best = group.transformers[0]
    exact = bool(group.best_available) and "ballpark" not in best.description.lower()
    return best, exact, best.description


def ecef_transform(srs_name: str, geoid_undulation_m: float | None = None) -> EcefTransform:
    """The model CRS -> ECEF transformation (see the module docstring); `geoid_undulation_m`
    (metres, default 0) is added to the heights, for models whose geoid grid PROJ lacks."""
    t, exact, op = _transform(srs_name)
    return EcefTransform(srs_name, t, exact, op, float(geoid_undulation_m or 0.0))


def ecef_from_enu(origin_ecef: np.ndarray) -> np.ndarray:
    """4×4 `ecef_from_enu` of the east-north-up frame at `origin_ecef` `(3,)` (WGS 84 ellipsoid):
    columns east, north, up, origin.

    >>> m = ecef_from_enu(np.array([6378137.0, 0.0, 0.0]))
    >>> (m[:3, :3].round(12) + 0.0).tolist()  # at (0°, 0°): east = y, north = z, up = x
    [[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    """
    o = np.asarray(origin_ecef, dtype=np.float64)
    lon, lat, _ = _to_geodetic().transform(o[0], o[1], o[2], radians=True)
    sl, cl, sp, cp = np.sin(lon), np.cos(lon), np.sin(lat), np.cos(lat)
    east = np.array([-sl, cl, 0.0])
    north = np.array([-sp * cl, -sp * sl, cp])
    up = np.array([cp * cl, cp * sl, sp])
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = east, north, up, o
    return m


@lru_cache(maxsize=1)
def _to_geodetic() -> pyproj.Transformer:
    return pyproj.Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True)


def yup(p_zup: np.ndarray) -> np.ndarray:
    """Points or vectors `(N, 3)` of a z-up frame -> glTF y-up: (x, y, z) -> (x, z, -y), the
    inverse of `Y_UP_TO_Z_UP`."""
    p = np.asarray(p_zup)
    return np.stack([p[:, 0], p[:, 2], -p[:, 1]], axis=-1)


def column_major(m: np.ndarray) -> list[float]:
    """A 4×4 matrix as the 16 numbers of a 3D Tiles / glTF `transform` (column-major)."""
    return [float(v) for v in np.asarray(m, dtype=np.float64).T.reshape(-1)]

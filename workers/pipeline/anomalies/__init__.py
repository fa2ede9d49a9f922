"""Anomalies: typical temperature, windows, linear thermal bridges and heat-leak candidates of
one surface texture (Hoegner & Stilla), with 3D outlines and per-facade figures.

In: a surface's `texture.texel.TexelGrid` (model CRS, metres) and its fused
`texture.fused.SurfaceTexture` (values in kelvin, NaN = not observed, kept observations' frames
and resolutions), `AnomalyOptions`. Out: a `SurfaceAnalysis`: typical value, spread, hot share,
window share, heat-loss index, the anomalies as `results.Anomaly` (kinds "window", "leak",
"bridge"; closed 3D rings on the surface plane) and a `(H, W)` label raster. Pure numpy/OpenCV;
the method, its rules and the figures' formulas and limits: `docs/anomalies.md`.

Entry points: `analyse_surface(grid, texture, options) -> SurfaceAnalysis` (one polygon) and
`analyse_building(grids, textures, options) -> list[SurfaceAnalysis]` (a building unit's
polygons, coplanar adjacent ones analysed together as one facade; one result per polygon).

Modules, one per step:
- `options`: `AnomalyOptions`, `AnomalyError`.
- `typical`: robust typical value and spread, edge band, frames per texel, smoothing.
- `windows`: rectangle-like blobs in a regular structure (`find_windows`).
- `lines`: row/column profiles of linear bridges (pipes, slabs, corners; `line_profiles`).
- `leaks`: leak candidates with half-maximum outlines (`find_leaks`).
- `outline`: texel regions to closed 3D rings (`outline`).
- `figures`: hot share, window share, heat-loss index.
- `analysis`: `analyse_surface`, `SurfaceAnalysis`.
- `building`: facades across polygons (`facade_groups`, `analyse_building`).
"""

from workers.pipeline.anomalies.analysis import SurfaceAnalysis, analyse_surface
from workers.pipeline.anomalies.building import analyse_building, facade_groups
from workers.pipeline.anomalies.options import AnomalyError, AnomalyOptions

__all__ = [
    "AnomalyError",
    "AnomalyOptions",
    "SurfaceAnalysis",
    "analyse_building",
    "analyse_surface",
    "facade_groups",
]

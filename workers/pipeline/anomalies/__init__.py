"""Anomalies: typical temperature, windows, linear thermal bridges and heat-leak candidates of
one surface texture (Hoegner & Stilla), with 3D outlines and per-facade figures.

In: a surface's `texture.texel.TexelGrid` (model CRS, metres) and its fused
`texture.fused.SurfaceTexture` (values in kelvin, NaN = not observed, kept observations' frames
and resolutions), `AnomalyOptions`. Out: a `SurfaceAnalysis`: typical value, spread, hot share,
window share, heat-loss index, the anomalies as `results.Anomaly` (kinds "window", "leak",
"bridge"; closed 3D rings on the surface plane) and a `(H, W)` label raster. Pure numpy/OpenCV;
the method, its rules and the figures' formulas and limits: `docs/anomalies.md`.

Entry point: `analyse_surface(grid, texture, options) -> SurfaceAnalysis`.

Modules, one per step:
- `options`: `AnomalyOptions`, `AnomalyError`.
- `typical`: robust typical value and spread, edge band, frames per texel, smoothing.
- `windows`: rectangle-like blobs in a regular structure (`find_windows`).
- `lines`: row/column profiles of linear bridges (pipes, slabs, corners; `line_profiles`).
- `leaks`: leak candidates with half-maximum outlines (`find_leaks`).
- `outline`: texel regions to closed 3D rings (`outline`).
- `figures`: hot share, window share, heat-loss index.
- `analysis`: `analyse_surface`, `SurfaceAnalysis`.
"""

from workers.pipeline.anomalies.analysis import SurfaceAnalysis, analyse_surface
from workers.pipeline.anomalies.options import AnomalyError, AnomalyOptions

__all__ = ["AnomalyError", "AnomalyOptions", "SurfaceAnalysis", "analyse_surface"]

"""Change between two surveys of the same surface: ΔT textures and per-facade figures.

In: one polygon (model CRS, metres) and, per job (A the earlier survey, B the later), its texture
as the job's atlas holds it (`SurfaceTexture`: the 16-bit tile, the texture coordinates of the
polygon's exterior ring, the radiometry). Out: a `SurfaceChange` on one common texel grid
(`texture.texel.texel_grid` at the finer of the two jobs' resolutions): both jobs' values re-sampled
at its texel centres, the ΔT texture `B − A` in kelvin where both observed (NaN elsewhere) and
its figures. Pure numpy: no file or database I/O (`workers.compare` does that).

Re-sampling. A job's texture coordinates `(s, t)` of the exterior ring's vertices define an affine
map from the polygon's plane to its tile (the atlas lays every surface as a rectangle of its
plane): fitted by least squares over the ring's vertices in the common grid's continuous raster
coordinates, it gives for each common texel centre the job's tile position in pixels (pixel
centres at integers; CityGML `t` runs upwards: row `= (1 − t)·H − 0.5`, column `= s·W − 0.5`).
Values are bilinear where the four neighbours are observed, else the nearest texel's when it is
observed, else unobserved: DN 0 ("not observed") is never interpolated across.

Normalisation by the outside air temperature (`normalised_delta`): with `T_air` of each survey,
`ΔT_norm = (T_B − T_air,B) − (T_A − T_air,A)`, the change of the surface's excess over the air.
It removes the first-order effect of a warmer or colder night; it does not remove wind, sky
(clear or overcast: radiative cooling of roofs), solar load of the preceding day, the thermal
inertia of heavy walls (the wall lags the air by hours), indoor temperature or emissivity and
reflection changes (wet facades), so a normalised change of a few tenths of a kelvin is within
what the weather alone can make.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.citymodel import Polygon
from workers.pipeline.geometry.manifest import Radiometry
from workers.pipeline.texture.texel import TexelGrid, TexelOptions, texel_grid

KELVIN_OFFSET = {"K": 0.0, "degC": 273.15}
#: ΔT tiles: `value = DN · 0.001 − 32.0` kelvin (−32 K .. +33.5 K in 1 mK steps; DN 0 = no value)
DELTA_RADIOMETRY = Radiometry(unit="K", scale=0.001, offset=-32.0)


class ChangeError(ValueError):
    """Two textures that cannot be compared (names the polygon and the reason)."""


@dataclass(frozen=True)
class ChangeOptions:
    """Options of the change stage.

    Attributes:
        sampling: "bilinear" (four observed neighbours, else the nearest observed texel) or
            "nearest".
        max_fit_px: largest residual, in tile pixels, of the affine map plane -> tile at a ring
            vertex; more means the texture coordinates do not belong to this polygon (another
            city model).
        max_side: largest side of the common texel grid (`TexelOptions.max_side`).
    """

    sampling: str = "bilinear"
    max_fit_px: float = 0.5
    max_side: int = 4080

    def __post_init__(self) -> None:
        if self.sampling not in ("bilinear", "nearest"):
            raise ChangeError(f"sampling must be 'bilinear' or 'nearest', got {self.sampling!r}")


@dataclass(frozen=True, eq=False)
class SurfaceTexture:
    """One job's texture of one polygon, as its atlas holds it.

    Attributes:
        dn: `(H, W)` uint16 atlas tile (`value = DN · scale + offset`, 0 = not observed).
        st: `(N, 2)` CityGML texture coordinates of the exterior ring's vertices (closing vertex
            included): `s` right, `t` up, `(0, 0)` the tile's lower-left corner.
        radiometry: the tile's radiometry (`K` or `degC`; `counts` carry no temperature).
        resolution_px_per_m: texels per metre the job laid the surface with (NaN: not recorded,
            then taken from the texture coordinates).
    """

    dn: np.ndarray
    st: np.ndarray
    radiometry: Radiometry
    resolution_px_per_m: float = float("nan")


@dataclass(frozen=True, eq=False)
class SurfaceChange:
    """The change of one surface from A to B on the common grid.

    Attributes:
        grid: the common texel grid (finer of the two jobs' resolutions).
        value_a, value_b: `(H, W)` float32 kelvin re-sampled from each job (NaN: not observed).
        delta: `(H, W)` float32 `B − A` in kelvin where both observed inside the polygon, else NaN.
        texels: texels of the grid inside the polygon; texels_both: of those, observed in both.
    """

    grid: TexelGrid
    value_a: np.ndarray
    value_b: np.ndarray
    delta: np.ndarray
    texels: int
    texels_both: int

    @property
    def observed_both_share(self) -> float:
        """Share of the polygon's texels observed in both surveys (0-1)."""
        return self.texels_both / self.texels if self.texels else 0.0

    def figures(self) -> dict[str, float | None]:
        """`delta_median_k`, `delta_mean_k`, `delta_p05_k`, `delta_p95_k` over the texels
        observed in both (None when there is none) and `observed_both_share`."""
        d = self.delta[np.isfinite(self.delta)].astype(np.float64)
        out: dict[str, float | None] = {"observed_both_share": self.observed_both_share}
        if d.size == 0:
            return out | dict.fromkeys(("delta_median_k", "delta_mean_k", "delta_p05_k", "delta_p95_k"))
        p05, p50, p95 = np.percentile(d, [5, 50, 95])
        return out | {
            "delta_median_k": float(p50),
            "delta_mean_k": float(d.mean()),
            "delta_p05_k": float(p05),
            "delta_p95_k": float(p95),
        }


def kelvin(value: float | np.ndarray, unit: str) -> float | np.ndarray:
    """A temperature in `unit` (`K`, `degC`) in kelvin; `counts` raise `ChangeError`.

    >>> kelvin(-3.5, "degC")
    269.65
    """
    if unit not in KELVIN_OFFSET:
        raise ChangeError(f"radiometry unit {unit!r} carries no temperature: surveys cannot be compared")
    return value + KELVIN_OFFSET[unit] if KELVIN_OFFSET[unit] else value


def normalised_delta(t_a: float, t_b: float, air_a: float | None, air_b: float | None) -> float | None:
    """`(T_B − T_air,B) − (T_A − T_air,A)` in kelvin (all in kelvin); None when an air temperature
    or a surface temperature is missing.

    >>> normalised_delta(275.0, 276.0, 270.0, 272.0)
    -1.0
    """
    if air_a is None or air_b is None or not (math.isfinite(t_a) and math.isfinite(t_b)):
        return None
    return (t_b - air_b) - (t_a - air_a)


def tile_from_raster(
    grid: TexelGrid, ring: np.ndarray, st: np.ndarray, tile_shape: tuple[int, int]
) -> np.ndarray:
    """The affine map `(2, 3)` from `grid`'s continuous raster coordinates `(x, y, 1)` to tile
    pixel coordinates `(column, row)` (pixel centres at integers), fitted over the ring's
    vertices `ring (N, 3)` (world) and their texture coordinates `st (N, 2)`.

    Raises `ChangeError` when fewer than 3 distinct vertices span the plane.
    """
    H, W = tile_shape
    xy = grid.raster_xy(np.asarray(ring, dtype=np.float64))
    st = np.asarray(st, dtype=np.float64)
    if len(st) != len(xy):
        raise ChangeError(f"polygon {grid.polygon_id}: {len(st)} texture coordinates for {len(xy)} vertices")
    uv = np.stack([st[:, 0] * W - 0.5, (1.0 - st[:, 1]) * H - 0.5], axis=1)
    X = np.column_stack([xy, np.ones(len(xy))])
    if np.linalg.matrix_rank(X[:, :2] - X[:, :2].mean(axis=0), tol=1e-9) < 2:
        raise ChangeError(f"polygon {grid.polygon_id}: its ring spans no plane")
    A, *_ = np.linalg.lstsq(X, uv, rcond=None)
    return A.T


def sample_tile(
    dn: np.ndarray, uv: np.ndarray, radiometry: Radiometry, sampling: str = "bilinear"
) -> np.ndarray:
    """Physical values `(N,)` float64 of tile `dn (H, W)` at pixel positions `uv (N, 2)`
    `(column, row)`, pixel centres at integers; NaN where not observed (DN 0 or outside).

    Bilinear where the four neighbours are observed, else the nearest texel when observed;
    `sampling="nearest"`: the nearest texel only. Unobserved texels never enter a value.
    """
    H, W = dn.shape
    u, v = uv[:, 0], uv[:, 1]

    def at(r: np.ndarray, c: np.ndarray) -> np.ndarray:
        inside = (r >= 0) & (r < H) & (c >= 0) & (c < W)
        out = np.zeros(r.shape, np.float64)
        out[inside] = dn[r[inside], c[inside]]
        return out

    rn, cn = np.floor(v + 0.5).astype(np.int64), np.floor(u + 0.5).astype(np.int64)
    near = at(rn, cn)
    val = np.where(near > 0, near, np.nan)
    if sampling == "bilinear":
        r0, c0 = np.floor(v).astype(np.int64), np.floor(u).astype(np.int64)
        fy, fx = v - r0, u - c0
        q = [at(r0, c0), at(r0, c0 + 1), at(r0 + 1, c0), at(r0 + 1, c0 + 1)]
        full = (q[0] > 0) & (q[1] > 0) & (q[2] > 0) & (q[3] > 0)
        bil = (q[0] * (1 - fx) + q[1] * fx) * (1 - fy) + (q[2] * (1 - fx) + q[3] * fx) * fy
        val = np.where(full, bil, val)
    return val * radiometry.scale + radiometry.offset


def _resolution(tex: SurfaceTexture, A: np.ndarray, size: float, polygon_id: str, name: str) -> float:
    """Texels per metre of a job's texture from the affine map `A` (tile pixels per probe texel
    of edge `size` metres): the recorded resolution when it agrees to 1 %, else the map's. Texels
    are square: a map that stretches one axis more than the other (by over 1 %) belongs to
    another polygon (`ChangeError`)."""
    sv = np.linalg.svd(A[:, :2], compute_uv=False)
    if sv[1] <= 0 or sv[0] / sv[1] > 1.01:
        raise ChangeError(
            f"polygon {polygon_id}: job {name}'s texture coordinates stretch the polygon unevenly "
            f"({sv[0] / size:.3g} vs {sv[1] / size:.3g} texels/m: not the same city model?)"
        )
    mapped = float(np.sqrt(sv[0] * sv[1])) / size
    rec = tex.resolution_px_per_m
    if math.isfinite(rec) and rec > 0 and abs(rec / mapped - 1.0) < 0.01:
        return float(rec)
    return mapped


def _fitted_map(
    grid: TexelGrid, ring: np.ndarray, tex: SurfaceTexture, name: str, max_fit_px: float
) -> np.ndarray:
    """`tile_from_raster` of one job, refused (`ChangeError`) when it misses a ring vertex's
    texture coordinates by more than `max_fit_px` tile pixels (another polygon's texture)."""
    A = tile_from_raster(grid, ring, tex.st, tex.dn.shape)
    fitted = np.column_stack([grid.raster_xy(ring), np.ones(len(ring))]) @ A.T
    H, W = tex.dn.shape
    given = np.stack([tex.st[:, 0] * W - 0.5, (1.0 - tex.st[:, 1]) * H - 0.5], axis=1)
    off = float(np.max(np.linalg.norm(fitted - given, axis=1)))
    if off > max_fit_px:
        raise ChangeError(
            f"polygon {grid.polygon_id}: job {name}'s texture coordinates are {off:.2f} px off the "
            "polygon's shape (not the same city model?)"
        )
    return A


def surface_change(
    polygon: Polygon,
    building_id: str,
    a: SurfaceTexture,
    b: SurfaceTexture,
    options: ChangeOptions = ChangeOptions(),
) -> SurfaceChange | None:
    """ΔT `B − A` of one polygon on a common grid at the finer of the two resolutions (see the
    module docstring); None when the polygon holds no texel grid (sliver). Raises `ChangeError`
    when a job's texture coordinates do not fit the polygon (off by more than
    `options.max_fit_px` tile pixels at a vertex, or stretched unevenly) or a radiometry carries
    no temperature."""
    ring = polygon.exterior.coords
    probe = texel_grid(polygon, building_id, TexelOptions(resolution_px_per_m=1.0, max_side=options.max_side))
    if probe is None:
        return None
    maps = [_fitted_map(probe, ring, t, n, options.max_fit_px) for t, n in ((a, "A"), (b, "B"))]
    res = max(
        _resolution(t, A, probe.size, polygon.id, n) for t, A, n in zip((a, b), maps, "AB", strict=True)
    )
    grid = texel_grid(polygon, building_id, TexelOptions(resolution_px_per_m=res, max_side=options.max_side))
    if grid is None:
        return None
    rows, cols = grid.masked_indices()
    xy = np.column_stack([cols + 0.5, rows + 0.5, np.ones(len(rows))])
    values = []
    for tex in (a, b):
        A = tile_from_raster(grid, ring, tex.st, tex.dn.shape)
        full = np.full(grid.shape, np.nan, np.float32)
        full[rows, cols] = kelvin(
            sample_tile(tex.dn, xy @ A.T, tex.radiometry, options.sampling), tex.radiometry.unit
        )
        values.append(full)
    va, vb = values
    delta = (vb - va).astype(np.float32)  # NaN wherever either is NaN, and outside the mask
    return SurfaceChange(
        grid=grid,
        value_a=va,
        value_b=vb,
        delta=delta,
        texels=grid.n_texels,
        texels_both=int(np.isfinite(delta).sum()),
    )

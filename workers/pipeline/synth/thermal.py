"""Ground-truth thermal scene: a deterministic surface temperature field for a set of buildings.

In: buildings (`citymodel.Building`, model CRS, metres), the polygon order of a `SceneMesh`
(optional), one seed and a `ThermalOptions`. Out: temperatures in kelvin (float32) at any 3D
point on a polygon, on the ground plane, or along a sky direction; the list of planted leak
anomalies (`Anomaly`) with their true 3D centres, sizes and half-maximum outlines; the window
rectangles of every wall (`windows`, `anomaly.Window`).

The field of a wall is built in wall-local coordinates: `s` along the wall (`geometry.surface_axes`,
metres from the polygon's centroid) and `h` = height above the building's lowest vertex. It sums:
a base temperature per building and surface class (walls warmer than roofs: a winter night), a
fine pattern of a few sinusoids (texture), a window grid per storey (panes colder, frames
warmer), warmer floor-slab lines, warmer building corners (thermal bridges), vertical heating
pipes on some walls, and Gaussian leak blobs (+2…+5 K). Roofs get base, texture and leaks.

Everything a building gets is drawn from `(seed, building id)`, so the temperature of a surface
does not depend on which other buildings are in the scene: a `ThermalScene` built from a subset
of a model (e.g. by the texture benchmarks) agrees with the one that rendered the frames.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import shapely

from workers.pipeline.geometry.citymodel import Building, Polygon
from workers.pipeline.geometry.polygons import fit_plane, open_ring, surface_axes, to_plane_2d
from workers.pipeline.synth.anomaly import Anomaly, Window, half_max_outline, wall_windows
from workers.pipeline.synth.common import SynthError, rng_for
from workers.pipeline.synth.shapes import footprint_corners, point_inside
from workers.pipeline.synth.value_noise import value_noise

WALL, ROOF, OTHER = 0, 1, 2
_CLASS_CODE = {"WallSurface": WALL, "RoofSurface": ROOF}


@dataclass(frozen=True)
class ThermalOptions:
    """Parameters of the temperature field (kelvin, metres). Defaults: a winter night."""

    wall_k: float = 276.0  # mean wall temperature
    roof_k: float = 271.0  # mean roof temperature (colder: radiates to the sky)
    other_k: float = 274.0  # ground surfaces, floors, unclassified non-vertical surfaces
    building_sigma_k: float = 1.5  # spread of the per-building base temperatures
    surface_sigma_k: float = 0.3  # extra spread per polygon
    ground_k: float = 272.5  # ground plane mean
    ground_amplitude_k: float = 0.6  # ground texture amplitude (sum of sinusoids)
    sky_zenith_k: float = 235.0
    sky_horizon_k: float = 262.0
    storey_height_m: tuple[float, float] = (2.8, 3.4)  # per building, uniform in range
    window_spacing_m: tuple[float, float] = (2.4, 3.6)  # column pitch per building
    window_width_m: float = 1.2
    window_height_m: float = 1.4
    window_sill_m: float = 0.9  # above the storey's floor
    window_margin_m: float = 0.3  # windows keep this distance from the polygon's outline
    window_delta_k: float = -2.5  # pane against the wall (glass mirrors the cold sky)
    frame_delta_k: float = 1.2  # frame against the wall
    frame_width_m: float = 0.08
    slab_delta_k: float = 0.8  # floor-slab line peak
    slab_width_m: float = 0.15  # Gaussian sigma of a slab line
    corner_delta_k: float = 1.5  # building corner peak
    corner_width_m: float = 0.35  # Gaussian sigma of a corner
    pipe_probability: float = 0.25  # share of walls (wider than 4 m) with a heating pipe
    pipe_delta_k: float = 2.5
    pipe_width_m: float = 0.08  # Gaussian sigma of a pipe
    texture_amplitude_k: float = 0.2  # amplitude of each sinusoid
    texture_wavelength_m: tuple[float, float] = (0.5, 3.0)
    n_sinusoids: int = 3
    leaks_per_building: float = 1.0  # Poisson mean
    leak_peak_k: tuple[float, float] = (2.0, 5.0)
    leak_sigma_m: tuple[float, float] = (0.3, 0.8)
    leak_roof_share: float = 0.25  # share of leaks placed on roofs
    features: bool = True  # False: base temperatures only (flat surfaces, for geometry tests)
    facade_details: bool = True  # False: no windows, slabs, corners, pipes (homogeneous walls)
    facade_noise_k: float = 0.0  # fine random texture fixed on every surface (value noise), K
    facade_noise_cell_m: float = 0.25  # its cell size


def _class_code(poly: Polygon, normal: np.ndarray) -> int:
    code = _CLASS_CODE.get(poly.surface_class)
    if code is not None:
        return code
    if poly.surface_class == "GroundSurface":
        return OTHER
    if abs(normal[2]) < 0.5:
        return WALL
    return ROOF if normal[2] > 0 else OTHER


def _stable(text: str) -> int:
    return zlib.crc32(text.encode())


class ThermalScene:
    """The temperature field of a scene (see the module docstring).

    Args:
        buildings: top-level buildings (parts included through `iter_polygons`).
        polygon_ids: the polygon order used by `temperature`'s `polygon_index` (a `SceneMesh`'s
            `polygon_ids`); default: the order of `build_scene_mesh(buildings)`.
        seed: the scene seed.
        options: field parameters.
    """

    def __init__(
        self,
        buildings: Iterable[Building],
        polygon_ids: Sequence[str] | None = None,
        seed: int = 0,
        options: ThermalOptions | None = None,
    ) -> None:
        self.seed = int(seed)
        self.options = options or ThermalOptions()
        blds = list(buildings)
        owner: dict[str, tuple[Polygon, int]] = {}
        order: list[str] = []
        for bi, b in enumerate(blds):
            for poly in b.iter_polygons():
                owner.setdefault(poly.id, (poly, bi))
                order.append(poly.id)
        ids = tuple(polygon_ids) if polygon_ids is not None else tuple(order)
        missing = [pid for pid in ids if pid not in owner]
        if missing:
            raise SynthError(f"polygon_ids: {len(missing)} ids not in the buildings, e.g. {missing[0]!r}")
        self.polygon_ids = ids
        self.building_ids = tuple(b.id for b in blds)
        self.polygon_building = tuple(blds[owner[pid][1]].id for pid in ids)
        self._index = {pid: i for i, pid in reversed(list(enumerate(ids)))}
        self.anomalies: tuple[Anomaly, ...] = ()
        self._build_buildings(blds)
        self._build_polygons([owner[pid][0] for pid in ids], np.array([owner[pid][1] for pid in ids]))
        self._build_global()
        self._finalize()

    # -- construction ---------------------------------------------------------------------------
    def _build_buildings(self, blds: list[Building]) -> None:
        o = self.options
        B = len(blds)
        self.b_ground = np.zeros(B)
        self.b_wall = np.zeros(B)
        self.b_roof = np.zeros(B)
        self.b_storey = np.zeros(B)
        self.b_spacing = np.zeros(B)
        self.b_wave = np.zeros((B, max(o.n_sinusoids, 1), 2))  # cycles per metre along (s, h)
        self.b_phase = np.zeros((B, max(o.n_sinusoids, 1)))
        self._corners: list[np.ndarray] = []
        for i, b in enumerate(blds):
            rng = rng_for(self.seed, "thermal-building", _stable(b.id))
            lo, _ = b.bounds()
            self.b_ground[i] = lo[2]
            self.b_wall[i] = o.wall_k + o.building_sigma_k * rng.standard_normal()
            self.b_roof[i] = o.roof_k + o.building_sigma_k * rng.standard_normal()
            self.b_storey[i] = rng.uniform(*o.storey_height_m)
            self.b_spacing[i] = max(rng.uniform(*o.window_spacing_m), o.window_width_m + 0.4)
            lam = rng.uniform(*o.texture_wavelength_m, size=self.b_wave.shape[1])
            ang = rng.uniform(0, np.pi, size=self.b_wave.shape[1])
            self.b_wave[i] = np.stack([np.cos(ang), np.sin(ang)], axis=-1) / lam[:, None]
            self.b_phase[i] = rng.uniform(0, 2 * np.pi, size=self.b_phase.shape[1])
            self._corners.append(footprint_corners(b))

    def _build_polygons(self, polys: list[Polygon], bidx: np.ndarray) -> None:
        o = self.options
        P = len(polys)
        self.p_building = bidx.astype(np.int32)
        self.p_class = np.full(P, OTHER, np.int8)
        self.p_origin = np.zeros((P, 3))
        self.p_s = np.zeros((P, 3))
        self.p_t = np.zeros((P, 3))
        self.p_base = np.zeros(P)
        self.p_slo = np.zeros(P)
        self.p_shi = np.zeros(P)
        self.p_corner = np.zeros((P, 2), bool)
        self.p_pipe = np.full(P, np.nan)
        self.p_win_s0 = np.zeros(P)
        self.p_win_cols = np.zeros(P, np.int32)
        self.p_win_rows = np.zeros(P, np.int32)
        self.p_win_off = np.zeros(P, np.int32)
        self.p_leak_c = np.zeros((P, 3))
        self.p_leak_sigma = np.ones(P)
        self.p_leak_peak = np.zeros(P)
        masks: list[np.ndarray] = []
        n_mask = 0
        shapes: list[shapely.Polygon | None] = [None] * P
        # per building, polygons in order: draws depend on (seed, building, polygon position)
        for bi in np.unique(bidx):
            members = np.flatnonzero(bidx == bi)
            rng = rng_for(self.seed, "thermal-polygons", _stable(self.building_ids[bi]))
            for k in members:
                poly = polys[k]
                plane = fit_plane(poly)
                jitter = rng.standard_normal()
                pipe_u, pipe_pos = rng.uniform(), rng.uniform(0.15, 0.85)
                if plane is None:
                    continue
                n = plane.normal
                ext = open_ring(poly.exterior.coords)
                s_ax, t_ax = surface_axes(n, ext)
                cls = _class_code(poly, n)
                self.p_class[k] = cls
                self.p_origin[k] = plane.centroid
                self.p_s[k], self.p_t[k] = s_ax, t_ax
                base = {WALL: self.b_wall[bi], ROOF: self.b_roof[bi]}.get(cls, o.other_k)
                self.p_base[k] = base + o.surface_sigma_k * jitter
                st = to_plane_2d(ext, plane.centroid, s_ax, t_ax)
                self.p_slo[k], self.p_shi[k] = st[:, 0].min(), st[:, 0].max()
                holes = [to_plane_2d(open_ring(r.coords), plane.centroid, s_ax, t_ax) for r in poly.interiors]
                shp = shapely.Polygon(st, [h for h in holes if len(h) >= 3]).buffer(0)
                shapes[k] = shp
                if cls != WALL or not o.features:
                    continue
                # building corners at the wall's two vertical edges
                corners = self._corners[bi]
                if len(corners):
                    for j, s_end in enumerate((self.p_slo[k], self.p_shi[k])):
                        xy = (plane.centroid + s_end * s_ax)[:2]
                        self.p_corner[k, j] = np.min(np.linalg.norm(corners - xy, axis=1)) < 0.3
                width = self.p_shi[k] - self.p_slo[k]
                if width > 4.0 and pipe_u < o.pipe_probability:
                    self.p_pipe[k] = self.p_slo[k] + pipe_pos * width
                mask, s0, rows, cols = self._window_mask(shp, plane.centroid, t_ax, bi, k)
                self.p_win_s0[k], self.p_win_rows[k], self.p_win_cols[k] = s0, rows, cols
                self.p_win_off[k] = n_mask
                masks.append(mask.ravel())
                n_mask += mask.size
        self.win_mask = np.concatenate(masks) if masks else np.zeros(1, bool)
        if o.features:
            self._plant_leaks(polys, shapes)

    def _window_mask(
        self, shp: shapely.Geometry, centroid: np.ndarray, t_ax: np.ndarray, bi: int, k: int
    ) -> tuple[np.ndarray, float, int, int]:
        """Window grid of wall `k`: mask `(rows, cols)` of windows lying inside the polygon."""
        o = self.options
        pitch, storey = self.b_spacing[bi], self.b_storey[bi]
        width = self.p_shi[k] - self.p_slo[k]
        cols = int(np.floor((width - 2 * o.window_margin_m) / pitch))
        h_top = float(centroid[2] - self.b_ground[bi]) + float(np.max(shapely.get_coordinates(shp)[:, 1]))
        rows = int(np.floor(h_top / storey)) if abs(t_ax[2]) > 0.5 else 0
        if cols < 1 or rows < 1:
            return np.zeros((0, 0), bool), 0.0, 0, 0
        s0 = self.p_slo[k] + 0.5 * (width - cols * pitch)
        c, r = np.meshgrid(np.arange(cols), np.arange(rows))
        s_left = s0 + c * pitch + 0.5 * (pitch - o.window_width_m)
        h_bot = r * storey + o.window_sill_m
        # window corners in the polygon's (s, t) frame (t from h: walls are (near) vertical)
        t_bot = (h_bot - (centroid[2] - self.b_ground[bi])) / t_ax[2]
        t_top = t_bot + o.window_height_m / t_ax[2]
        inner = shp.buffer(-o.window_margin_m)
        ok = np.ones((rows, cols), bool)
        for ds in (0.0, o.window_width_m):
            for tt in (t_bot, t_top):
                ok &= shapely.contains_xy(inner, s_left + ds, tt)
        return ok, float(s0), rows, cols

    def _plant_leaks(self, polys: list[Polygon], shapes: list[shapely.Geometry | None]) -> None:
        o = self.options
        out: list[Anomaly] = []
        for bi, bid in enumerate(self.building_ids):
            rng = rng_for(self.seed, "thermal-leaks", _stable(bid))
            n_leaks = int(rng.poisson(o.leaks_per_building))
            cand = np.flatnonzero((self.p_building == bi) & (self.p_class != OTHER))
            for j in range(n_leaks):
                want = ROOF if rng.uniform() < o.leak_roof_share else WALL
                pool = [k for k in cand if self.p_class[k] == want and self.p_leak_peak[k] == 0]
                pool = pool or [k for k in cand if self.p_leak_peak[k] == 0]
                if not pool:
                    break
                area = np.array([shapes[k].area if shapes[k] is not None else 0.0 for k in pool])
                if area.sum() <= 0:
                    break
                k = pool[int(rng.choice(len(pool), p=area / area.sum()))]
                sigma = float(rng.uniform(*o.leak_sigma_m))
                peak = float(rng.uniform(*o.leak_peak_k))
                st = point_inside(shapes[k], sigma, rng)
                if st is None:
                    continue
                center = self.p_origin[k] + st[0] * self.p_s[k] + st[1] * self.p_t[k]
                self.p_leak_c[k], self.p_leak_sigma[k], self.p_leak_peak[k] = center, sigma, peak
                outline, area = half_max_outline(polys[k], center, sigma)  # truth only, no draws
                out.append(
                    Anomaly(
                        id=f"leak-{bid}-{j}",
                        building_id=bid,
                        polygon_id=self.polygon_ids[k],
                        surface_class=polys[k].surface_class,
                        center=center,
                        sigma_m=sigma,
                        peak_k=peak,
                        outline=outline,
                        area_m2=area,
                    )
                )
        self.anomalies = tuple(out)

    def _build_global(self) -> None:
        rng = rng_for(self.seed, "thermal-ground")
        n = 4
        lam = rng.uniform(1.5, 8.0, size=n)
        ang = rng.uniform(0, np.pi, size=n)
        self.g_wave = np.stack([np.cos(ang), np.sin(ang)], axis=-1) / lam[:, None]
        self.g_phase = rng.uniform(0, 2 * np.pi, size=n)

    def _finalize(self) -> None:
        """Per-polygon parameter tables in a local frame (`origin`) for fast evaluation: float32
        rows `_tab` `(K, P)` (one gather per evaluation, then contiguous vector maths; integers
        below 2²⁴ are exact in float32); leak parameters `_leak` `(5, P)` (gathered where needed)."""
        lo = self.b_ground if len(self.b_ground) else np.zeros(1)
        xy = self.p_origin[:, :2] if len(self.p_origin) else np.zeros((1, 2))
        self.origin = np.floor(np.array([xy[:, 0].min(), xy[:, 1].min(), lo.min()]))  # (3,) world
        po = self.p_origin - self.origin
        b = self.p_building
        wall = self.p_class == WALL
        # v: height above the building's base on walls, the t coordinate elsewhere
        v_axis = np.where(wall[:, None], np.array([0.0, 0.0, 1.0]), self.p_t)
        v_off = np.where(wall, self.b_ground[b] - self.origin[2], np.einsum("ij,ij->i", po, self.p_t))
        wave = 2 * np.pi * self.b_wave[b]  # (P, n, 2)
        rows: list[np.ndarray] = [
            *self.p_s.T,
            np.einsum("ij,ij->i", po, self.p_s),
            *v_axis.T,
            v_off,
            self.p_base,
        ]
        for j in range(self.b_wave.shape[1]):
            rows += [wave[:, j, 0], wave[:, j, 1], self.b_phase[b, j]]
        rows += [
            self.b_storey[b],
            self.b_spacing[b],
            self.p_slo,
            self.p_shi,
            *self.p_corner.T,
            self.p_pipe,
            self.p_win_s0,
            self.p_win_cols,
            self.p_win_rows,
            self.p_win_off,
            wall,
            self.p_leak_peak,
        ]
        if len(self.win_mask) >= 1 << 24:
            raise SynthError("thermal scene too large for the window tables (float32 offsets)")
        self._tab = np.array(rows, dtype=np.float32).reshape(len(rows), -1)
        self._n_sin = self.b_wave.shape[1]
        leak = [self.p_leak_peak, *(self.p_leak_c - self.origin).T, -0.5 / self.p_leak_sigma**2]
        self._leak = np.array(leak, dtype=np.float32).reshape(5, -1)
        self._g_wave = (2 * np.pi * self.g_wave).astype(np.float32)
        g_phase = self.g_phase + 2 * np.pi * (self.g_wave @ self.origin[:2])  # origin-independent
        self._g_phase = np.mod(g_phase, 2 * np.pi).astype(np.float32)

    @cached_property
    def windows(self) -> tuple[Window, ...]:
        """Every window of the walls' window grids as a rectangle (truth; `anomaly.wall_windows`)."""
        return wall_windows(self)

    # -- evaluation -----------------------------------------------------------------------------
    def polygon_index(self, polygon: int | str) -> int:
        """Index of a polygon given by index or id (raises `SynthError` for unknown ids)."""
        if isinstance(polygon, str):
            if polygon not in self._index:
                raise SynthError(f"polygon id {polygon!r} is not in the thermal scene")
            return self._index[polygon]
        return int(polygon)

    def temperature(self, points: np.ndarray, polygon_index: np.ndarray) -> np.ndarray:
        """Surface temperature `(N,)` float32 kelvin at world points `(N, 3)` (float64, model CRS)
        lying on the polygons `polygon_index (N,)` (indices into `polygon_ids`)."""
        X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return self.temperature_local((X - self.origin).astype(np.float32), polygon_index)

    def temperature_local(self, points_local: np.ndarray, polygon_index: np.ndarray) -> np.ndarray:
        """`temperature` for points `(N, 3)` float32 relative to `self.origin` (fast path)."""
        X = np.asarray(points_local, dtype=np.float32).reshape(-1, 3)
        x, y, z = (np.ascontiguousarray(c) for c in X.T)
        return self.temperature_xyz(x, y, z, polygon_index)

    def temperature_xyz(
        self, x: np.ndarray, y: np.ndarray, z: np.ndarray, polygon_index: np.ndarray
    ) -> np.ndarray:
        """`temperature_local` with the coordinates as three `(N,)` float32 arrays."""
        p = np.asarray(polygon_index).reshape(-1)
        if p.dtype != np.int32:
            p = p.astype(np.intp)
        if not (len(p) == len(x) == len(y) == len(z)):
            raise SynthError(f"temperature: {len(x)} points but {len(p)} polygon indices")
        if len(p) == 0:
            return np.zeros(0, np.float32)
        if p.min() < 0 or p.max() >= len(self.polygon_ids):
            raise SynthError("temperature: polygon_index out of range")
        return self.temperature_xyz_unchecked(x, y, z, p)

    def temperature_xyz_unchecked(
        self, x: np.ndarray, y: np.ndarray, z: np.ndarray, p: np.ndarray
    ) -> np.ndarray:
        """`temperature_xyz` for `(N,)` float32 coordinates and valid int32/intp polygon indices
        `(N,)` (the renderer's labels), without input checks."""
        o = self.options
        g = _gather_rows(self._tab, p)  # (K, N) contiguous rows
        T = g[8].copy()
        if not o.features:
            return T
        s = x * g[0] + y * g[1] + z * g[2] - g[3]
        v = x * g[4] + y * g[5] + z * g[6] - g[7]  # height above the base on walls
        amp = np.float32(o.texture_amplitude_k)
        for j in range(self._n_sin):
            T += amp * np.sin(g[9 + 3 * j] * s + g[10 + 3 * j] * v + g[11 + 3 * j])
        wt = g[9 + 3 * self._n_sin :]
        if o.facade_noise_k > 0:
            cell = np.float32(o.facade_noise_cell_m)
            T += np.float32(o.facade_noise_k) * value_noise(s / cell, v / cell, p)
        if o.facade_details:
            T += self._wall_terms(s, v, wt)
        il = np.flatnonzero(wt[12] > 0)
        if len(il):
            lk = np.take(self._leak, p[il], axis=1, mode="clip")
            d2 = (x[il] - lk[1]) ** 2 + (y[il] - lk[2]) ** 2 + (z[il] - lk[3]) ** 2
            T[il] += lk[0] * np.exp(lk[4] * d2)
        return T

    def _wall_terms(self, s: np.ndarray, h: np.ndarray, g: np.ndarray) -> np.ndarray:
        """Windows, slabs, corners and pipes at wall-local `s`, `h` `(N,)` float32 -> increments
        `(N,)` float32 K (zero off walls); `g` = gathered rows of `_tab` from `storey` on."""
        o = self.options
        f32 = np.float32
        storey, pitch, slo, shi, c_lo, c_hi, pipe, s0, cols, rows, off, wall = g[:12]
        q = h / storey
        row = np.floor(q)
        dh = (q - np.round(q)) * storey
        dT = f32(o.slab_delta_k) * np.exp(f32(-0.5 / o.slab_width_m**2) * dh * dh) * (q > 0.5)
        w2 = f32(-0.5 / o.corner_width_m**2)
        corner = c_lo * np.exp(w2 * (s - slo) ** 2) + c_hi * np.exp(w2 * (shi - s) ** 2)
        dT += f32(o.corner_delta_k) * corner
        ip = np.flatnonzero(np.abs(s - pipe) < 5 * o.pipe_width_m)  # NaN (no pipe) compares False
        if len(ip):
            dT[ip] += f32(o.pipe_delta_k) * np.exp(f32(-0.5 / o.pipe_width_m**2) * (s[ip] - pipe[ip]) ** 2)
        # windows
        sr = s - s0
        col = np.floor(sr / pitch)
        u = sr - col * pitch - f32(0.5) * (pitch - f32(o.window_width_m))
        w = h - row * storey - f32(o.window_sill_m)
        cand = np.flatnonzero(
            (u >= 0) & (u <= o.window_width_m) & (w >= 0) & (w <= o.window_height_m)
            & (col >= 0) & (col < cols) & (row >= 0) & (row < rows)
        )  # fmt: skip
        if len(cand):
            idx = (off[cand] + row[cand] * cols[cand] + col[cand]).astype(np.int64)
            cand = cand[self.win_mask[idx]]
            uc, wc = u[cand], w[cand]
            edge = np.minimum(np.minimum(uc, o.window_width_m - uc), np.minimum(wc, o.window_height_m - wc))
            frame = edge < o.frame_width_m
            dT[cand[frame]] += f32(o.frame_delta_k)
            pane = cand[~frame]
            dT[pane] += f32(o.window_delta_k) + f32(0.6) * (w[pane] / f32(o.window_height_m) - f32(0.5))
        return dT * wall

    def surface_temperature(self, polygon: int | str, points: np.ndarray) -> np.ndarray:
        """Temperature `(N,)` float32 K at world points `(N, 3)` on one polygon (index or id)."""
        X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return self.temperature(X, np.full(len(X), self.polygon_index(polygon), np.int64))

    def ground_temperature(self, points: np.ndarray) -> np.ndarray:
        """Temperature `(N,)` float32 K of the ground plane at world points `(N, 3)` (x, y used)."""
        X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return self.ground_temperature_local((X - self.origin).astype(np.float32))

    def ground_temperature_local(self, points_local: np.ndarray) -> np.ndarray:
        """`ground_temperature` for points `(N, 3)` float32 relative to `self.origin`."""
        X = np.asarray(points_local, dtype=np.float32).reshape(-1, 3)
        o = self.options
        T = np.full(len(X), o.ground_k, np.float32)
        if o.features:
            amp = np.float32(0.5 * o.ground_amplitude_k)
            for j in range(len(self._g_phase)):
                g = self._g_wave[j]
                T += amp * np.sin(g[0] * X[:, 0] + g[1] * X[:, 1] + self._g_phase[j])
        return T

    def sky_temperature(self, directions: np.ndarray) -> np.ndarray:
        """Apparent sky temperature `(N,)` float32 K along world unit directions `(N, 3)`:
        `horizon − (horizon − zenith) · sqrt(sin elevation)`."""
        D = np.asarray(directions, dtype=np.float32).reshape(-1, 3)
        o = self.options
        sin_el = np.clip(D[:, 2], 0.0, 1.0)
        return (o.sky_horizon_k - (o.sky_horizon_k - o.sky_zenith_k) * np.sqrt(sin_el)).astype(np.float32)


def _gather_rows(table: np.ndarray, index: np.ndarray) -> np.ndarray:
    """`table[:, index]` `(K, N)`; for spatially coherent indices (image rows cross few polygons)
    as runs: one column per run, repeated (~4× faster than a gather per element)."""
    change = np.flatnonzero(index[1:] != index[:-1]) + 1
    if len(change) > len(index) // 8:
        return np.take(table, index, axis=1, mode="clip")
    starts = np.concatenate(([0], change))
    lengths = np.diff(np.append(starts, len(index)))
    return np.repeat(table[:, index[starts]], lengths, axis=1)

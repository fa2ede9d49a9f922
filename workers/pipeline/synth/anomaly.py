"""Ground-truth thermal anomalies of a synthetic scene: planted leaks and the window grid.

In: nothing but plain data (`thermal.ThermalScene` builds the records; the outline helpers take a
`citymodel.Polygon`). Out: `Anomaly` records (planted leaks: true 3D centre, size, excess in
kelvin, half-maximum outline and its area) and `Window` records (one rectangle per window of a
wall: 3D corner ring, centre, width, height, pane ΔT). All coordinates are world = model CRS,
metres; outlines are closed 3D rings on the polygon's plane, wound like the polygon (right-hand
normal = the polygon's normal).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np
import shapely
from shapely.geometry.polygon import orient

from workers.pipeline.geometry.citymodel import Polygon
from workers.pipeline.geometry.polygons import fit_plane, open_ring, surface_axes, to_plane_2d

#: half-maximum radius of a Gaussian in units of σ: `exp(−r² / 2σ²) = ½` at `r = σ·sqrt(2 ln 2)`
HALF_MAX_SIGMAS = math.sqrt(2.0 * math.log(2.0))


@dataclass(frozen=True, eq=False)
class PlaneFrame:
    """A polygon's plane frame, exactly as `thermal.ThermalScene` lays it.

    Attributes:
        origin: `(3,)` world origin of the plane coordinates (the plane's centroid).
        s_axis, t_axis: `(3,)` unit axes in the plane (`geometry.surface_axes`).
        shape: the polygon (holes included) in plane coordinates `(s, t)`, metres.
    """

    origin: np.ndarray
    s_axis: np.ndarray
    t_axis: np.ndarray
    shape: shapely.Geometry

    def to_plane(self, points: np.ndarray) -> np.ndarray:
        """World points `(N, 3)` -> plane coordinates `(N, 2)` (orthogonal projection)."""
        X = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return to_plane_2d(X, self.origin, self.s_axis, self.t_axis)

    def to_world(self, st: np.ndarray) -> np.ndarray:
        """Plane coordinates `(N, 2)` -> world points `(N, 3)` on the plane."""
        st = np.asarray(st, dtype=np.float64).reshape(-1, 2)
        return self.origin + st[:, :1] * self.s_axis + st[:, 1:2] * self.t_axis


def plane_frame(polygon: Polygon) -> PlaneFrame | None:
    """The plane frame of `polygon` (None for a degenerate polygon)."""
    plane = fit_plane(polygon)
    if plane is None:
        return None
    ext = open_ring(polygon.exterior.coords)
    s_ax, t_ax = surface_axes(plane.normal, ext)
    st = to_plane_2d(ext, plane.centroid, s_ax, t_ax)
    holes = [to_plane_2d(open_ring(r.coords), plane.centroid, s_ax, t_ax) for r in polygon.interiors]
    shp = shapely.Polygon(st, [h for h in holes if len(h) >= 3]).buffer(0)
    return PlaneFrame(plane.centroid, s_ax, t_ax, shp)


def _main_part(geom: shapely.Geometry, at: shapely.Point) -> shapely.Polygon | None:
    """The polygon of `geom` containing `at` (else its largest polygon; None when it has none)."""
    parts = [g for g in getattr(geom, "geoms", [geom]) if isinstance(g, shapely.Polygon) and not g.is_empty]
    if not parts:
        return None
    inside = [g for g in parts if g.covers(at)]
    return max(inside or parts, key=lambda g: g.area)


def half_max_outline(polygon: Polygon, center: np.ndarray, sigma_m: float) -> tuple[np.ndarray, float]:
    """Half-maximum contour of a Gaussian leak on `polygon`: the circle of radius
    `σ·sqrt(2 ln 2)` around `center` `(3,)` in the polygon's plane, clipped to the polygon.

    Returns the closed ring `(N, 3)` (world, wound like the polygon; a 64-gon inscribed in the
    circle where it is not clipped; the part holding the centre when the clip splits the disc)
    and its area in m² (holes of the polygon removed). An empty ring `(0, 3)` and area 0 when
    the polygon is degenerate or the disc misses it.
    """
    frame = plane_frame(polygon)
    if frame is None:
        return np.zeros((0, 3)), 0.0
    c = frame.to_plane(center)[0]
    disc = shapely.Point(c).buffer(HALF_MAX_SIGMAS * float(sigma_m), quad_segs=16)
    part = _main_part(disc.intersection(frame.shape), shapely.Point(c))
    if part is None:
        return np.zeros((0, 3)), 0.0
    part = orient(part, 1.0)  # exterior counter-clockwise in (s, t): right-hand normal = n
    ring = frame.to_world(np.asarray(part.exterior.coords)[:, :2])
    return ring, float(part.area)


@dataclass(frozen=True, eq=False)
class Anomaly:
    """A planted leak: Gaussian blob `peak_k · exp(−d² / 2σ²)` on one polygon.

    Attributes:
        id: `"leak-<n>"`, stable for a seed and building.
        building_id: top-level building id.
        polygon_id: id of the polygon carrying it.
        surface_class: `"WallSurface"`, `"RoofSurface"`, ...
        center: `(3,)` world coordinates (model CRS) of the centre, on the polygon's plane.
        sigma_m: Gaussian sigma, metres; the blob is +peak/e² at `radius_m = 2σ`.
        peak_k: temperature excess at the centre, kelvin.
        outline: `(N, 3)` closed world ring of the half-maximum contour (`half_max_outline`);
            None when unknown (truth files written before it existed).
        area_m2: area inside `outline`, m² (NaN when unknown).
    """

    id: str
    building_id: str
    polygon_id: str
    surface_class: str
    center: np.ndarray
    sigma_m: float
    peak_k: float
    outline: np.ndarray | None = None
    area_m2: float = float("nan")

    @property
    def radius_m(self) -> float:
        """Nominal radius of the anomaly, 2σ, metres."""
        return 2.0 * self.sigma_m

    @property
    def half_max_radius_m(self) -> float:
        """Radius of the half-maximum contour, `σ·sqrt(2 ln 2)` ≈ 1.177σ, metres."""
        return HALF_MAX_SIGMAS * self.sigma_m

    @property
    def delta_k(self) -> float:
        """Excess temperature at the centre over the field without the leak, kelvin (= `peak_k`)."""
        return self.peak_k

    def with_outline(self, polygon: Polygon) -> Anomaly:
        """This leak with its outline and area computed on `polygon` (its carrier)."""
        ring, area = half_max_outline(polygon, self.center, self.sigma_m)
        return replace(self, outline=ring, area_m2=area)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (truth file)."""
        d: dict[str, Any] = {
            "id": self.id,
            "building_id": self.building_id,
            "polygon_id": self.polygon_id,
            "surface_class": self.surface_class,
            "center": [float(v) for v in self.center],
            "sigma_m": self.sigma_m,
            "radius_m": self.radius_m,
            "peak_k": self.peak_k,
            "delta_k": self.delta_k,
            "half_max_radius_m": self.half_max_radius_m,
        }
        if self.outline is not None:
            d["outline"] = np.round(np.asarray(self.outline, float).reshape(-1, 3), 6).tolist()
            d["area_m2"] = float(self.area_m2)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Anomaly:
        """Inverse of `to_dict`; older records without `outline` / `area_m2` load with None / NaN
        (`with_outline` computes them from the polygon)."""
        outline = d.get("outline")
        return cls(
            id=str(d["id"]),
            building_id=str(d["building_id"]),
            polygon_id=str(d["polygon_id"]),
            surface_class=str(d.get("surface_class", "WallSurface")),
            center=np.asarray(d["center"], dtype=np.float64),
            sigma_m=float(d["sigma_m"]),
            peak_k=float(d["peak_k"]),
            outline=None if outline is None else np.asarray(outline, dtype=np.float64).reshape(-1, 3),
            area_m2=float(d["area_m2"]) if d.get("area_m2") is not None else float("nan"),
        )


@dataclass(frozen=True, eq=False)
class Window:
    """One window of a wall's window grid (`ThermalScene`): a rectangle on the wall's plane.

    The field is `delta_k + 0.6·(w/height − ½)` K (w: height above the window's bottom) against
    the wall on the pane and `+frame_delta_k` on a frame band of `frame_width_m` along the inside
    of the rectangle (`ThermalOptions`).

    Attributes:
        id: `"window-<polygon id>-<row>-<col>"`.
        building_id: top-level building id.
        polygon_id: the wall polygon carrying it.
        row, col: storey (from the bottom) and column of the wall's grid.
        outline: `(5, 3)` closed world ring (bottom-left, bottom-right, top-right, top-left,
            bottom-left; left/right along the wall's `s` axis), on the wall's plane.
        center: `(3,)` world centre of the rectangle.
        width_m, height_m: extent along the wall (`s`) and up the wall's plane, metres.
        delta_k: pane temperature against the wall at mid-height, kelvin (`window_delta_k`).
    """

    id: str
    building_id: str
    polygon_id: str
    row: int
    col: int
    outline: np.ndarray
    center: np.ndarray
    width_m: float
    height_m: float
    delta_k: float

    @property
    def area_m2(self) -> float:
        """Area of the rectangle, m²."""
        return self.width_m * self.height_m

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (truth file)."""
        return {
            "id": self.id,
            "building_id": self.building_id,
            "polygon_id": self.polygon_id,
            "row": self.row,
            "col": self.col,
            "outline": np.round(np.asarray(self.outline, float), 6).tolist(),
            "center": [round(float(v), 6) for v in self.center],
            "width_m": self.width_m,
            "height_m": self.height_m,
            "delta_k": self.delta_k,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Window:
        """Inverse of `to_dict`."""
        return cls(
            id=str(d["id"]),
            building_id=str(d["building_id"]),
            polygon_id=str(d["polygon_id"]),
            row=int(d.get("row", 0)),
            col=int(d.get("col", 0)),
            outline=np.asarray(d["outline"], dtype=np.float64).reshape(-1, 3),
            center=np.asarray(d["center"], dtype=np.float64).reshape(3),
            width_m=float(d["width_m"]),
            height_m=float(d["height_m"]),
            delta_k=float(d["delta_k"]),
        )


class _WindowOptions(Protocol):
    """The window fields of `thermal.ThermalOptions` (read-only: a frozen dataclass)."""

    @property
    def window_width_m(self) -> float: ...
    @property
    def window_height_m(self) -> float: ...
    @property
    def window_sill_m(self) -> float: ...
    @property
    def window_delta_k(self) -> float: ...


class WindowTables(Protocol):
    """What `wall_windows` reads of a `thermal.ThermalScene` (its per-building and per-polygon
    tables; a protocol, so that this module does not import `thermal`, which imports it)."""

    options: _WindowOptions
    polygon_ids: Sequence[str]
    building_ids: Sequence[str]
    p_building: np.ndarray
    p_origin: np.ndarray
    p_s: np.ndarray
    p_t: np.ndarray
    p_win_s0: np.ndarray
    p_win_rows: np.ndarray
    p_win_cols: np.ndarray
    p_win_off: np.ndarray
    win_mask: np.ndarray
    b_spacing: np.ndarray
    b_storey: np.ndarray
    b_ground: np.ndarray


def wall_windows(scene: WindowTables) -> tuple[Window, ...]:
    """Every window of the scene's window grids, as the field draws them (`_wall_terms`).

    A wall's window `(row, col)` spans `s ∈ [s0 + col·pitch + ½(pitch − w), … + w]` along the
    wall and `h ∈ [row·storey + sill, … + height]` above the building's base (the polygon's
    `p_win_*` tables, the building's `b_spacing` pitch and `b_storey`); `win_mask` keeps the
    windows lying inside the polygon. Polygon order, then row, then column.
    """
    o = scene.options
    out: list[Window] = []
    for k in np.flatnonzero((scene.p_win_rows > 0) & (scene.p_win_cols > 0)):
        bi = int(scene.p_building[k])
        rows, cols, off = int(scene.p_win_rows[k]), int(scene.p_win_cols[k]), int(scene.p_win_off[k])
        mask = scene.win_mask[off : off + rows * cols].reshape(rows, cols)
        pitch, storey = float(scene.b_spacing[bi]), float(scene.b_storey[bi])
        origin, s_ax, t_ax = scene.p_origin[k], scene.p_s[k], scene.p_t[k]
        h0 = float(origin[2] - scene.b_ground[bi])  # the plane origin's height above the base
        pid, bid = scene.polygon_ids[k], scene.building_ids[bi]
        for r, c in np.argwhere(mask):
            s_lo = float(scene.p_win_s0[k]) + c * pitch + 0.5 * (pitch - o.window_width_m)
            s_hi = s_lo + o.window_width_m
            h_lo = r * storey + o.window_sill_m
            t_lo, t_hi = (h_lo - h0) / t_ax[2], (h_lo + o.window_height_m - h0) / t_ax[2]
            st = np.array([[s_lo, t_lo], [s_hi, t_lo], [s_hi, t_hi], [s_lo, t_hi], [s_lo, t_lo]])
            ring = origin + st[:, :1] * s_ax + st[:, 1:2] * t_ax
            out.append(
                Window(
                    id=f"window-{pid}-{r}-{c}",
                    building_id=bid,
                    polygon_id=pid,
                    row=int(r),
                    col=int(c),
                    outline=ring,
                    center=ring[:4].mean(axis=0),
                    width_m=float(o.window_width_m),
                    height_m=float(abs(t_hi - t_lo)),
                    delta_k=float(o.window_delta_k),
                )
            )
    return tuple(out)

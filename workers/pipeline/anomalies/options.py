"""Options of the anomaly stage (`docs/anomalies.md` explains every rule they steer)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields


class AnomalyError(ValueError):
    """Bad input to the anomaly stage (e.g. an option out of range; the message names it)."""


@dataclass(frozen=True)
class AnomalyOptions:
    """How thermal anomalies are found on one surface texture (kelvin, metres).

    Defaults work on drives (0.1 m texels) and flights (0.2-1 m texels).

    Attributes:
        enabled: run the analysis at all (False: figures NaN, no anomalies).
        k_mad: candidate threshold above typical, in units of the surface's robust spread at
            scales below `spread_scale_m` (noise and texture; gradients, seams and large leaks
            do not count).
        floor_k: absolute floor of that threshold: a texel is a seed when its excess exceeds
            `max(k_mad · fine spread, floor_k)`.
        floor_sigma_m: the leak size (Gaussian σ, m; half-maximum diameter 2.35 σ) that
            `floor_k` is meant for: the imaging blur lowers a leak's peak
            (`analysis.floor_attenuation`: to about 0.7 on flights at 0.4-0.5 m/px, hardly on
            drives), so the floor on the texture is `floor_k` times that share (0: the floor
            applies to the texture as it is). Chosen among 0.3, 0.45 and 0.6 on the bench's
            flights of two seeds (recall against false leaks; `docs/anomalies.md`).
        spread_scale_m: σ of the smoothing removed from the residual before the fine spread.
        min_area_m2: smallest half-maximum area of a reported leak.
        min_texels: smallest number of texels of a reported leak (coarse grids).
        hot_delta_k: `hot_share` counts observed non-window area warmer than typical + this.
        min_frames: regions resting on fewer distinct frames, or whose texels are mostly seen by
            fewer frames than this, are not reported (capped by the texture's kept observations).
        windows: look for windows (regular structures) and set them apart.
        window_delta_k: a pane deviates from typical by at least this (either sign).
        window_coarse_delta_k: on coarse textures (`windows.coarse`), the depth of a cold local
            minimum that makes it a pane candidate (its half-depth region); one shallower than
            `window_delta_k` counts only in a regular group (never alone) and, not accepted,
            does not keep leaks from seeding. The imaging blur there (σ about a texel) leaves
            a 1.2 × 1.4 m pane 0.8-1 K deep in the texture where it is 2.5 K on the wall.
        window_min_m, window_max_m: pane side lengths accepted as a window.
        window_min_texels: a pane must span this many texels per side (else no windows: an
            unresolved grid is not invented); on coarse textures (`windows.coarse`: the
            smallest pane spans fewer) a blurred pane counts by its half-depth extents, which
            must reach `window_min_texels − 1` texels, and only in a regular group or as a
            clean lone pane (`docs/anomalies.md`).
        window_fill: smallest share of its bounding box a pane blob fills (rectangle-likeness).
        window_min_count: windows come in groups: this many similar aligned panes at least.
        window_lone_fill: a cold pane outside any group (a facade seen in part) is a window when
            it fills this share of its box and its sides are 0.6–2.5 m (1: never).
        window_margin_m: window panes dilated by this before leak detection (warm frames).
        edge_band_m: observed texels closer than this to the unobserved area or the polygon
            outline are not seeds (rounded to whole texels: none on coarse textures).
        outline_band_m: a candidate whose maximum lies this close to the polygon's outline (at
            least one texel) is an edge effect (corners, eaves, the silhouette).
        min_observed_texels: fewer observed texels in the polygon: figures NaN, no anomalies.
        bridge_aspect: a region this many times longer than wide is a linear thermal bridge.
        bridge_min_length_m: ... and at least this long.
        line_width_m: a region narrower than this (and 1.5 times longer than wide) is a piece of
            a line (a pipe between windows), not a leak (the smallest synthetic leak's
            half-maximum disk is 0.6 m wide by the same measure).
        line_min_m: a row/column profile (linear bridges along the texel axes) needs this much
            observed length in each half of the row/column.
        line_narrow_m: a shorter row/column (at least 3 texels in each half: the rows of a
            narrow wall) gets only the part of its profile that stands above the profile within
            this distance on either side (a slab line or pipe, σ ≤ 0.15 m; not a leak, σ ≥ 0.3 m;
            `lines.narrow_part`); 0: none (before session 10).
        psf_sigma_px: σ of the camera's optical blur, pixels. With the pixel's area and the
            bilinear resampling it gives the blur of one observation on the surface
            (`analysis.imaging_blur_m`: local resolution × sqrt(psf² + 1/4), foreshortened
            across by the viewing angle); a leak's ΔT is the amplitude of a Gaussian blob fitted
            through that blur (`leaks.fit_blob`: the blur conserves the blob's volume), at most
            3 × the measured one; 0 switches the blob fit off (the measured amplitude and the
            5 × 5 fit's centre are reported). It matters on coarse textures (flights: 0.3–0.6
            m/px), hardly on drives.
        facade_grouping: analyse coplanar adjacent polygons of a building as one facade
            (`building.analyse_building`; False, the default: each polygon alone — on the bench
            grouping gained no window and halved the speed).
        facade_plane_m, facade_angle_deg: coplanar: each polygon's texels within this distance
            of the other's plane, normals and texel axes within this angle.
        smooth_m: σ of the Gaussian smoothing before seeds and outlines, metres (none below a
            third of a texel: coarse textures are smooth already and leaks span few texels).
    """

    enabled: bool = True
    k_mad: float = 4.0
    floor_k: float = 1.2
    floor_sigma_m: float = 0.45
    spread_scale_m: float = 0.6
    min_area_m2: float = 0.1
    min_texels: int = 2
    hot_delta_k: float = 2.0
    min_frames: int = 2
    windows: bool = True
    window_delta_k: float = 1.0
    window_coarse_delta_k: float = 0.8
    window_min_m: float = 0.4
    window_max_m: float = 4.0
    window_min_texels: int = 3
    window_fill: float = 0.85
    window_min_count: int = 2
    window_lone_fill: float = 0.85
    window_margin_m: float = 0.15
    edge_band_m: float = 0.15
    outline_band_m: float = 0.4
    min_observed_texels: int = 20
    bridge_aspect: float = 3.0
    bridge_min_length_m: float = 1.0
    line_width_m: float = 0.35
    line_min_m: float = 1.0
    line_narrow_m: float = 0.3
    smooth_m: float = 0.07
    facade_grouping: bool = False
    facade_plane_m: float = 0.05
    facade_angle_deg: float = 1.0
    psf_sigma_px: float = 0.6

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.type in ("float", float) and not (isinstance(v, int | float) and math.isfinite(v)):
                raise AnomalyError(f"{f.name} must be a finite number, got {v!r}")
        positive = (
            "k_mad",
            "min_area_m2",
            "window_delta_k",
            "window_coarse_delta_k",
            "window_min_m",
            "bridge_min_length_m",
            "spread_scale_m",
        )
        non_negative = (
            "floor_k",
            "floor_sigma_m",
            "hot_delta_k",
            "window_margin_m",
            "edge_band_m",
            "line_min_m",
            "line_narrow_m",
            "line_width_m",
        )
        non_negative += ("smooth_m", "psf_sigma_px", "outline_band_m", "facade_plane_m", "facade_angle_deg")
        for name in positive:
            if getattr(self, name) <= 0:
                raise AnomalyError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in non_negative:
            if getattr(self, name) < 0:
                raise AnomalyError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name, lo in (("min_texels", 1), ("min_frames", 1), ("window_min_texels", 2)):
            if getattr(self, name) < lo:
                raise AnomalyError(f"{name} must be >= {lo}, got {getattr(self, name)}")
        for name, lo in (("window_min_count", 2), ("min_observed_texels", 1)):
            if getattr(self, name) < lo:
                raise AnomalyError(f"{name} must be >= {lo}, got {getattr(self, name)}")
        if self.window_max_m <= self.window_min_m:
            raise AnomalyError(f"window_max_m must exceed window_min_m, got {self.window_max_m}")
        for name in ("window_fill", "window_lone_fill"):
            if not 0 < getattr(self, name) <= 1:
                raise AnomalyError(f"{name} must be in (0, 1], got {getattr(self, name)}")
        if self.bridge_aspect <= 1:
            raise AnomalyError(f"bridge_aspect must be > 1, got {self.bridge_aspect}")

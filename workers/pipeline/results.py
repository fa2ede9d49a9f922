"""Result objects of one building unit: what a unit hands back, what the CLI writes as files
(`docs/results-format.md`) and what the service stores in one database transaction.

In: produced by the texture/orientation stages. Out: plain, picklable frozen dataclasses.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from workers.pipeline.geometry.citymodel import Appearance
from workers.pipeline.geometry.manifest import Radiometry
from workers.pipeline.geometry.pose import Pose


@dataclass(frozen=True, eq=False)
class RefinedPose:
    """The orientation of one frame against one building (`status` "refined" or "prior")."""

    frame: int
    pose: Pose
    status: str
    rms_px: float
    matches: int


@dataclass(frozen=True, eq=False)
class TextureTile:
    """One atlas tile image.

    Attributes:
        name: path relative to the results folder, e.g. `textures/BLDG_0815_0.png` (= `imageURI`).
        dn: `(H, W)` uint16 digital numbers (`value = DN · scale + offset`; 0 = not observed).
    """

    name: str
    dn: np.ndarray


@dataclass(frozen=True, eq=False)
class SurfaceStats:
    """Per-surface texture quality and thermal statistics.

    Attributes:
        polygon_id, building_id: ids (building = the `Building`/`BuildingPart` owning the polygon).
        surface_class: semantic class of the polygon.
        texels_total: texels inside the polygon; texels_observed: of those, with a value.
        frames_used: frame indices that contributed at least one texel.
        mean_resolution_m: mean local resolution of the chosen observations, metres on the surface
            per image pixel (NaN when nothing was observed).
        mean_view_angle_deg: mean angle between the surface normal and the viewing ray, degrees.
        temperature: statistics of observed texels in the radiometry unit: keys `mean`, `median`,
            `std`, `min`, `max`, `p05`, `p25`, `p75`, `p95` (empty when nothing was observed).
        resolution_px_per_m: texels per metre of the surface's grid: the job's, or coarser where
            the frames see the surface only coarsely (`texture.sight.surface_resolution`; NaN:
            not recorded).
        best_resolution_m: finest local resolution among the observations of its texels (m/px).
        mean_observations: mean number of observations a fused texel rests on.
        reason: why a surface that frames see got no or few texels ("" otherwise).
        typical: robust typical value of the surface (median of its observed texels outside
            windows, radiometry unit; NaN: too few texels; `anomalies.typical`).
        spread: robust spread of those texels, 1.4826 · MAD of their residual after linear
            thermal bridges are removed (radiometry unit).
        hot_share: share of the observed area outside windows warmer than `typical` +
            `AnomalyOptions.hot_delta_k` (0-1; NaN: not analysed).
        window_share: share of the observed area covered by detected windows (0-1).
        heat_loss_index: `docs/anomalies.md`: area-weighted mean excess over `typical` of the
            leak candidates, per observed m², kelvin (0: no candidate; NaN: not analysed).
        windows, leaks: numbers of detected windows and leak candidates on the surface.
    """

    polygon_id: str
    building_id: str
    surface_class: str
    texels_total: int
    texels_observed: int
    frames_used: tuple[int, ...] = ()
    mean_resolution_m: float = float("nan")
    mean_view_angle_deg: float = float("nan")
    temperature: Mapping[str, float] = field(default_factory=dict)
    resolution_px_per_m: float = float("nan")
    best_resolution_m: float = float("nan")
    mean_observations: float = float("nan")
    reason: str = ""
    typical: float = float("nan")
    spread: float = float("nan")
    hot_share: float = float("nan")
    window_share: float = float("nan")
    heat_loss_index: float = float("nan")
    windows: int = 0
    leaks: int = 0

    @property
    def observed_share(self) -> float:
        """Observed texels / total texels (0 for an empty grid)."""
        return self.texels_observed / self.texels_total if self.texels_total else 0.0


@dataclass(frozen=True, eq=False)
class FramePose:
    """Orientation of one frame against one top-level building.

    `status` is `"refined"` or `"prior"` (refinement rejected or not run; `pose` is then the prior).
    """

    frame: int
    building_id: str
    pose: Pose
    status: str
    rms_px: float = float("nan")
    matches: int = 0


@dataclass(frozen=True, eq=False)
class Anomaly:
    """A thermal anomaly on one surface: a heat-leak candidate (`kind` "leak"), a detected window
    ("window") or a linear thermal bridge ("bridge": pipes, slab edges, corners).

    Attributes:
        building_id: the `Building`/`BuildingPart` owning the polygon.
        polygon_id: the surface's polygon id.
        outline: `(N, 3)` closed 3D ring on the surface plane, model CRS, metres.
        centre: `(3,)` model CRS (the peak for a leak, the centroid for a window).
        area_m2: area inside the outline, m².
        peak_delta_k, mean_delta_k: contrast of the region (radiometry unit difference: kelvin
            for kelvin/celsius input; signed, windows are usually < 0): for a leak the fitted
            amplitude over its local background (corrected for the blur of coarse textures) and
            the mean excess inside the outline over the surface's typical value; for windows and
            bridges against the typical value (`docs/anomalies.md`).
        kind: "leak", "window" or "bridge".
        id: stable id within a job (`<polygon id>-<kind>-<n>`).
        frames: number of distinct frames that observed the region.
        best_resolution_m: finest local resolution among those observations, m/px.
        confidence: 0-1, how sure the detector is (contrast over noise, area, frames).
    """

    building_id: str
    polygon_id: str
    outline: np.ndarray
    centre: np.ndarray
    area_m2: float
    peak_delta_k: float
    mean_delta_k: float
    kind: str = "leak"
    id: str = ""
    frames: int = 0
    best_resolution_m: float = float("nan")
    confidence: float = float("nan")


@dataclass(frozen=True, eq=False)
class BuildingResult:
    """Everything one building unit produced.

    Attributes:
        building_id: top-level `Building` id.
        appearance: the job's appearance for this building (theme, one `ParameterizedTexture` per
            tile with `image_uri` = tile name and one target per textured polygon), or None when no
            surface was observed.
        tiles: the atlas tiles the appearance points to.
        radiometry: how tile DNs map to physical values.
        surfaces: statistics for every polygon of the building (parts included), observed or not.
        poses: per-frame orientation against this building.
        anomalies: heat-leak candidates found on its surfaces.
        timings_s: seconds per stage inside the unit (e.g. `orient`, `texture`, `atlas`).
        frames_withheld: frames that did not texture the building: refinement left them at
            priors too uncertain for it (`units.withheld_frames`).
        frames_rejected: frames whose observations the texture stage dropped: they contradicted
            the other frames' on the texels they share (a pose off by pixels,
            `texture.consistency`).
    """

    building_id: str
    appearance: Appearance | None
    tiles: tuple[TextureTile, ...]
    radiometry: Radiometry
    surfaces: tuple[SurfaceStats, ...]
    poses: tuple[FramePose, ...] = ()
    anomalies: tuple[Anomaly, ...] = ()
    timings_s: Mapping[str, float] = field(default_factory=dict)
    frames_withheld: tuple[int, ...] = ()
    frames_rejected: tuple[int, ...] = ()


def output_radiometry(radiometry: Radiometry, frame_dtype: np.dtype) -> Radiometry:
    """The radiometry of the output tiles: the sequence's, except for 8-bit frames, whose values
    are kept as they are (scale 1, offset 0; `docs/results-format.md`)."""
    if np.dtype(frame_dtype) == np.uint8:
        return Radiometry(unit=radiometry.unit, scale=1.0, offset=0.0)
    return radiometry

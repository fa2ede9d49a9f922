"""Ground-truth thermal anomalies (planted leaks) of a synthetic scene.

In: nothing (plain data made by `thermal.ThermalScene`). Out: `Anomaly` records with their
true 3D centre (model CRS, metres), size and peak excess temperature (kelvin).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
    """

    id: str
    building_id: str
    polygon_id: str
    surface_class: str
    center: np.ndarray
    sigma_m: float
    peak_k: float

    @property
    def radius_m(self) -> float:
        """Nominal radius of the anomaly, 2σ, metres."""
        return 2.0 * self.sigma_m

    def to_dict(self) -> dict:
        """JSON-ready form (truth file)."""
        return {
            "id": self.id,
            "building_id": self.building_id,
            "polygon_id": self.polygon_id,
            "surface_class": self.surface_class,
            "center": [float(v) for v in self.center],
            "sigma_m": self.sigma_m,
            "radius_m": self.radius_m,
            "peak_k": self.peak_k,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Anomaly:
        """Inverse of `to_dict`."""
        return cls(
            id=str(d["id"]),
            building_id=str(d["building_id"]),
            polygon_id=str(d["polygon_id"]),
            surface_class=str(d.get("surface_class", "WallSurface")),
            center=np.asarray(d["center"], dtype=np.float64),
            sigma_m=float(d["sigma_m"]),
            peak_k=float(d["peak_k"]),
        )

"""Interior orientation: the OpenCV camera model of `sequence-format.md`.

In: camera-frame points `(N, 3)` (OpenCV axes: x right, y down, z along the optical axis) or
pixels `(N, 2)`. Out: pixels `(N, 2)` or unit bearing rays `(N, 3)` in the camera frame.

Pixel convention: pixel centres at integer coordinates, `(0, 0)` is the centre of the top-left
pixel, `u` to the right, `v` down. Distortion is OpenCV's `k1, k2, p1, p2, k3` model applied to
normalised coordinates `(a, b) = (x/z, y/z)`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Camera:
    """A pinhole camera with OpenCV radial-tangential distortion.

    Attributes:
        width, height: image size in pixels.
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in pixels (pixel-centre convention of the spec).
        k1, k2, k3: radial distortion coefficients.
        p1, p2: tangential distortion coefficients.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Camera:
        """Build from the manifest's `camera` object (`model` must be `OPENCV` when given)."""
        keys = ("width", "height", "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
        kw: dict[str, Any] = {k: d[k] for k in keys if k in d}
        kw["width"] = int(kw["width"])
        kw["height"] = int(kw["height"])
        return cls(**kw)

    def to_dict(self) -> dict[str, Any]:
        """The manifest's `camera` object."""
        return {
            "model": "OPENCV",
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "k1": self.k1,
            "k2": self.k2,
            "p1": self.p1,
            "p2": self.p2,
            "k3": self.k3,
        }

    @property
    def K(self) -> np.ndarray:
        """Calibration matrix `(3, 3)` (pixel_from_normalized, no distortion)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        """OpenCV distortion vector `(5,)`: k1, k2, p1, p2, k3."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return bool(np.any(self.dist_coeffs != 0.0))

    @cached_property
    def max_radius2(self) -> float:
        """Largest `r² = a² + b²` (undistorted normalised) up to which the radial model is monotonic.

        Beyond it `r_d = r (1 + k1 r² + k2 r⁴ + k3 r⁶)` folds back, and points far outside the
        field of view would land inside the image: `pixel_from_normalized` returns NaN there.
        The fold is the first positive root `s = r²` of `1 + 3 k1 s + 5 k2 s² + 7 k3 s³`; inf when
        there is none (e.g. no distortion).
        """
        coeffs = np.array([7.0 * self.k3, 5.0 * self.k2, 3.0 * self.k1, 1.0])
        nz = np.flatnonzero(coeffs)
        if nz[0] == 3:
            return float("inf")
        roots = np.roots(coeffs[nz[0] :])
        real = roots[(np.abs(roots.imag) < 1e-12) & (roots.real > 0)].real
        return float(real.min()) if len(real) else float("inf")

    # -- normalised <-> distorted ---------------------------------------------------------------
    def distort(self, ab: np.ndarray) -> np.ndarray:
        """Apply distortion to normalised coordinates `(N, 2)` -> distorted normalised `(N, 2)`."""
        ab = np.asarray(ab, dtype=np.float64)
        a, b = ab[..., 0], ab[..., 1]
        r2 = a * a + b * b
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        ad = a * radial + 2.0 * self.p1 * a * b + self.p2 * (r2 + 2.0 * a * a)
        bd = b * radial + self.p1 * (r2 + 2.0 * b * b) + 2.0 * self.p2 * a * b
        return np.stack([ad, bd], axis=-1)

    def _distort_jacobian(self, ab: np.ndarray) -> np.ndarray:
        """Jacobian of `distort` at `ab` `(N, 2)` -> `(N, 2, 2)`."""
        a, b = ab[..., 0], ab[..., 1]
        r2 = a * a + b * b
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        dradial_dr2 = self.k1 + r2 * (2.0 * self.k2 + 3.0 * r2 * self.k3)
        J = np.empty((*ab.shape[:-1], 2, 2))
        J[..., 0, 0] = radial + 2 * a * a * dradial_dr2 + 2 * self.p1 * b + 6 * self.p2 * a
        J[..., 0, 1] = 2 * a * b * dradial_dr2 + 2 * self.p1 * a + 2 * self.p2 * b
        J[..., 1, 0] = 2 * a * b * dradial_dr2 + 2 * self.p1 * a + 2 * self.p2 * b
        J[..., 1, 1] = radial + 2 * b * b * dradial_dr2 + 6 * self.p1 * b + 2 * self.p2 * a
        return J

    def undistort(self, ab_d: np.ndarray, iterations: int = 30) -> np.ndarray:
        """Invert `distort`: distorted normalised `(N, 2)` -> undistorted normalised `(N, 2)`.

        Newton's method on the 2x2 system per point, started from the distorted coordinates;
        converges to ~1e-14 within a few iterations inside the monotonic range of the model
        (which covers the image for realistic lenses, including k1 = -0.3).
        """
        target = np.asarray(ab_d, dtype=np.float64)
        if not self.has_distortion:
            return target.copy()
        ab = target.copy()
        for _ in range(iterations):
            residual = self.distort(ab) - target
            if np.nanmax(np.abs(residual), initial=0.0) < 1e-15:
                break
            J = self._distort_jacobian(ab)
            det = J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]
            da = (J[..., 1, 1] * residual[..., 0] - J[..., 0, 1] * residual[..., 1]) / det
            db = (-J[..., 1, 0] * residual[..., 0] + J[..., 0, 0] * residual[..., 1]) / det
            ab = ab - np.stack([da, db], axis=-1)
        # no solution on the monotonic branch (pixel beyond the fold): NaN, never a wrong ray
        with np.errstate(invalid="ignore"):
            bad = (np.sum(ab * ab, axis=-1) > self.max_radius2) | (
                np.max(np.abs(self.distort(ab) - target), axis=-1) > 1e-9
            )
        ab[bad] = np.nan
        return ab

    # -- pixels ---------------------------------------------------------------------------------
    def pixel_from_normalized(self, ab: np.ndarray) -> np.ndarray:
        """Undistorted normalised `(N, 2)` -> pixels `(N, 2)` (distortion applied).

        NaN beyond the fold of the distortion model (`r² > max_radius2`), where the model is
        meaningless and would map far off-axis points into the image.
        """
        ab = np.asarray(ab, dtype=np.float64)
        if np.isfinite(self.max_radius2):
            with np.errstate(invalid="ignore"):
                beyond = np.sum(ab * ab, axis=-1) > self.max_radius2
            if np.any(beyond):
                ab = ab.copy()
                ab[beyond] = np.nan
        abd = self.distort(ab)
        return np.stack([self.fx * abd[..., 0] + self.cx, self.fy * abd[..., 1] + self.cy], axis=-1)

    def normalized_from_pixel(self, uv: np.ndarray) -> np.ndarray:
        """Pixels `(N, 2)` -> undistorted normalised `(N, 2)` (distortion removed)."""
        uv = np.asarray(uv, dtype=np.float64)
        abd = np.stack([(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy], axis=-1)
        return self.undistort(abd)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points `(N, 3)` -> pixels `(N, 2)`.

        Points with `z <= 0` (behind the camera) give NaN.
        """
        p = np.asarray(points_cam, dtype=np.float64)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            ab = p[..., :2] / np.where(z > 0, z, np.nan)[..., None]
        return self.pixel_from_normalized(ab)

    def bearing(self, uv: np.ndarray) -> np.ndarray:
        """Pixels `(N, 2)` -> unit rays `(N, 3)` in the camera frame (z > 0)."""
        ab = self.normalized_from_pixel(uv)
        rays = np.concatenate([ab, np.ones((*ab.shape[:-1], 1))], axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean mask `(N,)`: pixel inside the image, at least `margin` pixels from the border.

        The image covers pixel centres 0 .. width-1 and 0 .. height-1.
        """
        uv = np.asarray(uv, dtype=np.float64)
        u, v = uv[..., 0], uv[..., 1]
        with np.errstate(invalid="ignore"):
            return (
                (u >= margin)
                & (u <= self.width - 1 - margin)
                & (v >= margin)
                & (v <= self.height - 1 - margin)
            )

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resampled by `factor` (pixel-centre convention kept)."""
        return Camera(
            width=round(self.width * factor),
            height=round(self.height * factor),
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            k1=self.k1,
            k2=self.k2,
            p1=self.p1,
            p2=self.p2,
            k3=self.k3,
        )

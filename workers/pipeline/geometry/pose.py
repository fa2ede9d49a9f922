"""Exterior orientation: a camera pose in the world frame.

In: world points `(N, 3)` (model CRS, metres, x east, y north, z up). Out: camera-frame points
`(N, 3)` (OpenCV axes) and pixels `(N, 2)` through a `Camera`.

A pose is `R_world_from_cam` (`R_wc` of the spec, camera to world) and the projection centre
`center` (`C`) in world coordinates: `x_c = R_wcᵀ (X − C)`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.camera import Camera


@dataclass(frozen=True, eq=False)
class Pose:
    """Camera pose: `R_world_from_cam` `(3, 3)` and projection centre `center` `(3,)` in world."""

    R_world_from_cam: np.ndarray
    center: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "R_world_from_cam", np.asarray(self.R_world_from_cam, dtype=np.float64))
        object.__setattr__(self, "center", np.asarray(self.center, dtype=np.float64).reshape(3))

    @property
    def R_cam_from_world(self) -> np.ndarray:
        """`(3, 3)` world to camera rotation."""
        return self.R_world_from_cam.T

    def cam_from_world(self, X: np.ndarray) -> np.ndarray:
        """World points `(N, 3)` -> camera-frame points `(N, 3)`."""
        X = np.asarray(X, dtype=np.float64)
        return (X - self.center) @ self.R_world_from_cam

    def world_from_cam(self, x_c: np.ndarray) -> np.ndarray:
        """Camera-frame points `(N, 3)` -> world points `(N, 3)`."""
        return np.asarray(x_c, dtype=np.float64) @ self.R_world_from_cam.T + self.center

    def project(self, camera: Camera, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points `(N, 3)` -> (pixels `(N, 2)`, depth `z_c` `(N,)`); NaN pixels behind the camera."""
        xc = self.cam_from_world(X)
        return camera.project(xc), xc[..., 2]

    def to_dict(self) -> dict[str, list]:
        """`{"center": [x, y, z], "rotation": R_wc rows}` as in `orientation.json`."""
        return {"center": self.center.tolist(), "rotation": self.R_world_from_cam.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> Pose:
        """Inverse of `to_dict`."""
        return cls(np.array(d["rotation"], dtype=np.float64), np.array(d["center"], dtype=np.float64))

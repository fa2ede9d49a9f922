"""The sequence calibration's time-delay search: the camera-to-INS delay τ on a grid.

In: a `Camera`, the scene's `FrameWireframes` and `RayCaster`, the calibration's frames (index,
GNSS/INS prior pose, design `A_i` `(6, 10)`, `calibration_model`), their images, the parameters
θ `(10,)` the other terms are held at. Out: the delay (seconds) whose corrected poses project the
scene wireframe best onto the frames' image gradients (oriented-gradient score,
`oriented_gradient`), all candidate delays of a frame projected at once (`delay_poses`).

Why: τ shows at turns only (`−τ · Ω_i`, `−τ · v_i`), often beyond the Gauss-Newton stage's
search radius, so `calibration` searches it here and adjusts again from there.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Protocol

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import apply_delta
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.calibration_model import delay_poses
from workers.pipeline.orientation.edge_observations import FrameWireframes, image_normals
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.oriented_gradient import downsampled_gradient, oriented_gradient_score
from workers.pipeline.orientation.wireframe import EdgeOptions

__all__ = ["DelayFrame", "delay_search"]


class DelayFrame(Protocol):
    """A frame of the calibration: its index, GNSS/INS prior pose and design `A` `(6, 10)`."""

    @property
    def index(self) -> int: ...

    @property
    def prior(self) -> Pose: ...

    @property
    def A(self) -> np.ndarray: ...


def delay_search(
    camera: Camera, wireframe: FrameWireframes, raycaster: RayCaster, data: Sequence[DelayFrame],
    images: Mapping[int, np.ndarray], theta0: np.ndarray, search_s: float, step_s: float,
    edge_options: EdgeOptions, fit: FrameFitOptions,
) -> float | None:
    """Time delay τ (s) maximising the oriented-gradient score (`oriented_gradient`) of the
    scene wireframe over the frames, the other parameters at `theta0`; None when no frame turns
    or moves enough for τ to matter (a step of `step_s` moves its samples less than half a
    pixel: the search cannot tell the delays apart). Candidates: ±`search_s` in steps of
    `step_s` (seconds)."""
    taus = np.arange(-search_s, search_s + 1e-12, step_s)
    total = np.zeros(len(taus))
    used = 0
    for f in data:
        col = f.A[:, 9]
        pose = apply_delta(f.prior, f.A @ theta0)
        vis = wireframe.visible(f.index, pose, raycaster, edge_options, fit.max_samples)
        if len(vis.points) < fit.min_samples:
            continue
        # the delay's effect on this frame, pixels per second, at the samples' median depth
        uv, z = pose.project(camera, vis.points)
        ok = np.isfinite(uv).all(axis=1) & (z > 0.5)
        if ok.sum() < fit.min_samples:
            continue
        zmed = float(np.median(z[ok]))
        px_per_s = camera.fx * (np.linalg.norm(col[:3]) + np.linalg.norm(col[3:]) / zmed)
        if px_per_s * step_s < 0.5:
            continue
        nrm = image_normals(camera, pose, vis, uv)[ok]
        # every τ at once
        R, C = delay_poses(f.prior, f.A, theta0, taus)
        xc = np.einsum("tnk,tkj->tnj", vis.points[ok][None] - C[:, None], R)
        grad = downsampled_gradient(images[f.index], 2, 1.0)
        total += oriented_gradient_score(grad, 2, camera.project(xc), nrm, vis.weight[ok])
        used += 1
    if used == 0:
        return None
    return float(taus[int(np.argmax(total))])

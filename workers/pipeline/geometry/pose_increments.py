"""Pose increments of the orientation: rotation vectors, pose corrections, bounded steps and the
projection Jacobian.

In: poses (`Pose`), world points `(N, 3)` (model CRS, metres), a `Camera`. Out: rotation matrices,
corrections `δ = (ω, dC)` (ω rotation vector in the camera frame, radians; dC world metres, with
`R ← R exp([ω]×)`, `C ← C + dC`), Gauss-Newton steps bounded to their linearisation and
`∂uv/∂δ` `(N, 2, 6)`. Every stage of `workers.pipeline.orientation` corrects poses this way (the
frame fit `frame_fit`, the edge observations `edge_observations`, the joint fit
`common_correction`, the bundle adjustment `bundle`, the calibration model `calibration_model`).
"""

from __future__ import annotations

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation vector `(3,)` (radians) -> rotation matrix `(3, 3)` (Rodrigues)."""
    w = np.asarray(w, dtype=np.float64)
    t = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if t < 1e-12:
        return np.eye(3) + K
    K /= t
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation matrix `(3, 3)` -> rotation vector `(3,)` (radians)."""
    c = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    t = np.arccos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if t < 1e-9:
        return 0.5 * v
    return t / (2 * np.sin(t)) * v


def pose_delta(reference: Pose, pose: Pose) -> np.ndarray:
    """`(6,)` correction `(ω, dC)` taking `reference` to `pose` (ω in the reference camera frame)."""
    return np.concatenate([so3_log(reference.R_world_from_cam.T @ pose.R_world_from_cam),
                           pose.center - reference.center])


def apply_delta(reference: Pose, delta: np.ndarray) -> Pose:
    """Inverse of `pose_delta`: `reference` corrected by `delta` `(6,)`."""
    d = np.asarray(delta, dtype=np.float64)
    return Pose(reference.R_world_from_cam @ so3_exp(d[:3]), reference.center + d[3:])


def step_scale(d: np.ndarray, max_deg: float, max_m: float) -> float:
    """The factor (≤ 1) that keeps a correction `(6,)` within `max_deg` of rotation and `max_m` of
    translation (a Gauss-Newton step kept within its linearisation).

    >>> step_scale(np.array([0.0, 0.0, 0.0, 4.0, 0.0, 0.0]), 2.0, 1.0)
    0.25
    """
    d = np.asarray(d, dtype=np.float64)
    r = float(np.linalg.norm(d[:3]))
    t = float(np.linalg.norm(d[3:]))
    return min(1.0, np.radians(max_deg) / max(r, 1e-12), max_m / max(t, 1e-12))


def bounded_step(d: np.ndarray, max_deg: float, max_m: float) -> np.ndarray:
    """A correction `(6,)` with its rotation shortened to `max_deg` and its translation to `max_m`,
    each part on its own."""
    d = np.asarray(d, dtype=np.float64).copy()
    d[:3] *= min(1.0, np.radians(max_deg) / max(float(np.linalg.norm(d[:3])), 1e-12))
    d[3:] *= min(1.0, max_m / max(float(np.linalg.norm(d[3:])), 1e-12))
    return d


def _distortion_jacobian(camera: Camera, ab: np.ndarray) -> np.ndarray:
    """`∂ distort / ∂(a, b)` `(N, 2, 2)` of OpenCV's k1, k2, k3, p1, p2 model at normalised `ab` `(N, 2)`."""
    a, b = ab[:, 0], ab[:, 1]
    k1, k2, k3, p1, p2 = camera.k1, camera.k2, camera.k3, camera.p1, camera.p2
    r2 = a * a + b * b
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_radial = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)  # d radial / d r2
    J = np.empty((len(ab), 2, 2))
    J[:, 0, 0] = radial + 2 * a * a * d_radial + 2 * p1 * b + 6 * p2 * a
    J[:, 0, 1] = 2 * a * b * d_radial + 2 * p1 * a + 2 * p2 * b
    J[:, 1, 0] = J[:, 0, 1]
    J[:, 1, 1] = radial + 2 * b * b * d_radial + 6 * p1 * b + 2 * p2 * a
    return J


def project_jacobian(camera: Camera, pose: Pose, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World points `(N, 3)` -> (pixels `(N, 2)`, depth `(N,)`, `∂uv/∂δ` `(N, 2, 6)`)."""
    R = pose.R_world_from_cam
    return camera_point_jacobian(camera, (np.asarray(X, dtype=np.float64) - pose.center) @ R, R)


def camera_point_jacobian(
    camera: Camera, xc: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`project_jacobian` from the points in the camera frame `xc` `(N, 3)` and the rotation
    world from camera `R`, one `(3, 3)` or one per point `(N, 3, 3)` -> (pixels `(N, 2)`, depth
    `(N,)`, `∂uv/∂δ` `(N, 2, 6)` on `δ = (ω_cam [rad], dC_world [m])`)."""
    x, y, z = xc[:, 0], xc[:, 1], np.maximum(xc[:, 2], 1e-6)
    ab = np.stack([x / z, y / z], axis=1)
    uv = camera.pixel_from_normalized(ab)
    n = len(xc)
    D = _distortion_jacobian(camera, ab)
    D[:, 0, :] *= camera.fx
    D[:, 1, :] *= camera.fy
    dab = np.zeros((n, 2, 3))
    dab[:, 0, 0] = 1 / z
    dab[:, 0, 2] = -x / z**2
    dab[:, 1, 1] = 1 / z
    dab[:, 1, 2] = -y / z**2
    dxc = np.zeros((n, 3, 6))
    dxc[:, 0, 1], dxc[:, 0, 2] = -z, y  # ∂x_c/∂ω = [x_c]× (x_c' = exp(-ω) x_c)
    dxc[:, 1, 0], dxc[:, 1, 2] = z, -x
    dxc[:, 2, 0], dxc[:, 2, 1] = -y, x
    dxc[:, :, 3:] = -np.swapaxes(R, -1, -2)
    return uv, xc[:, 2], D @ dab @ dxc

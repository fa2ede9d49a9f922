"""The sequence calibration's error model: how the ten systematic parameters θ correct one frame.

θ = (ω boresight correction, camera frame, rad; b GNSS offset, world, m; l lever-arm correction,
camera frame, m; τ camera-to-INS delay, s). Frame i's correction `δ_i = (ω_i, dC_i)`
(`geometry.pose_increments.apply_delta`) is linear in θ, `δ_i = A_i θ`:

    ω_i  = ω − τ · Ω_i            (Ω_i: angular rate of the prior, camera frame, rad/s)
    dC_i = b + R_i · l − τ · v_i  (v_i: velocity of the prior centre, world, m/s)

(exposure at `time − τ`, linearised). Used by `calibration` (estimation; `delay_poses`: one
frame's poses for many candidate delays at once, its τ search) and `mounting` (θ in the
manifest's mounting terms).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import so3_log

__all__ = ["N_PARAMS", "delay_poses", "design", "frame_designs", "frame_motion"]

#: number of calibration parameters θ
N_PARAMS = 10


def frame_motion(poses: Sequence[Pose], times: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Velocity `(N, 3)` of the centres (world, m/s) and angular rate `(N, 3)` (camera frame of
    each pose, rad/s) of a pose sequence in recording order, by central differences (one-sided
    at the ends; zero where two stamps coincide or for a single pose)."""
    n = len(poses)
    v = np.zeros((n, 3))
    w = np.zeros((n, 3))
    t = np.asarray(times, dtype=np.float64)
    for i in range(n):
        a, b = max(i - 1, 0), min(i + 1, n - 1)
        dt = t[b] - t[a]
        if b == a or dt <= 0:
            continue
        v[i] = (poses[b].center - poses[a].center) / dt
        Ri = poses[i].R_world_from_cam
        # rate in the camera frame of pose i: R_a^T R_b = exp(Ω dt) expressed at i
        w_a = so3_log(poses[a].R_world_from_cam.T @ poses[b].R_world_from_cam) / dt
        w[i] = Ri.T @ poses[a].R_world_from_cam @ w_a
    return v, w


def design(pose: Pose, velocity: np.ndarray, rate: np.ndarray) -> np.ndarray:
    """`A_i` `(6, 10)`: frame correction `δ_i = A_i θ` (module docstring)."""
    A = np.zeros((6, N_PARAMS))
    A[0:3, 0:3] = np.eye(3)
    A[0:3, 9] = -rate
    A[3:6, 3:6] = np.eye(3)
    A[3:6, 6:9] = pose.R_world_from_cam
    A[3:6, 9] = -velocity
    return A


def frame_designs(frames: Sequence[int], priors: Mapping[int, Pose], times: Mapping[int, float],
                  pick: Sequence[int]) -> dict[int, np.ndarray]:
    """`{frame: A_i (6, 10)}` of the frames of `pick`, their motion from their neighbours in
    `frames` (recording order; `frame_motion`, at a cost that does not grow
    with the sequence length)."""
    where = {f: k for k, f in enumerate(frames)}
    out = {}
    for i in pick:
        k = where[i]
        near = frames[max(k - 1, 0): k + 2]
        v, w = frame_motion([priors[j] for j in near], [times[j] for j in near])
        m = near.index(i)
        out[i] = design(priors[i], v[m], w[m])
    return out


def delay_poses(
    pose: Pose, A: np.ndarray, theta: np.ndarray, taus: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The corrected poses of one frame (prior `pose`, design `A` `(6, 10)`) for every time delay of
    `taus` `(T,)` (seconds), the other parameters at `theta` `(10,)`: `δ(τ) = A θ + (τ − θ_τ) A[:, 9]`
    applied as `geometry.pose_increments.apply_delta` does -> `R_world_from_cam` `(T, 3, 3)` and
    centres `(T, 3)` (world, metres)."""
    deltas = (A @ theta)[None] + (np.asarray(taus, dtype=np.float64) - theta[9])[:, None] * A[:, 9][None]
    return pose.R_world_from_cam @ so3_exp_many(deltas[:, :3]), pose.center + deltas[:, 3:]


def so3_exp_many(w: np.ndarray) -> np.ndarray:
    """Rotation vectors `(T, 3)` (radians) -> rotation matrices `(T, 3, 3)` (Rodrigues, as
    `pose_increments.so3_exp` does one by one).

    >>> R = so3_exp_many(np.array([[0.0, 0.0, np.pi / 2], [0.0, 0.0, 0.0]]))
    >>> bool(np.allclose(R[0] @ [1.0, 0.0, 0.0], [0, 1, 0]) and np.allclose(R[1], np.eye(3)))
    True
    """
    t = np.linalg.norm(w, axis=1)
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    small = t < 1e-12
    s = np.where(small, 1.0, np.sin(t) / np.where(small, 1.0, t))
    c = np.where(small, 0.0, (1 - np.cos(t)) / np.where(small, 1.0, t) ** 2)
    return np.eye(3)[None] + s[:, None, None] * K + c[:, None, None] * (K @ K)

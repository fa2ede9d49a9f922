"""7-parameter similarities `x_target = s R x_source + t` between a reconstruction's world and
the model CRS: Umeyama's closed form, and the placement of a reconstruction on the GNSS/INS.

A straight drive's camera centres lie on a line, which leaves the rotation about it open; the
placement therefore takes its rotation from the attitude priors (the chordal mean of
`R_prior R_recᵀ` over the frames, every frame's attitude an observation of the same rotation)
and only the scale and shift from the centres (Huber-weighted least squares).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import so3_exp


@dataclass(frozen=True, eq=False)
class Similarity:
    """`target_from_source`: `x_target = scale · R (x_source) + t`; `R` `(3, 3)`, `t` `(3,)`."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    @classmethod
    def identity(cls) -> Similarity:
        """The identity."""
        return cls(1.0, np.eye(3), np.zeros(3))

    def points(self, X: np.ndarray) -> np.ndarray:
        """Points `(N, 3)` mapped into the target frame."""
        return self.scale * np.asarray(X, dtype=np.float64) @ self.R.T + self.t

    def pose(self, pose: Pose) -> Pose:
        """A camera pose (source world) as a pose in the target world (the camera frame stays)."""
        return Pose(self.R @ pose.R_world_from_cam, self.scale * self.R @ pose.center + self.t)

    def poses(self, poses: Mapping[int, Pose]) -> dict[int, Pose]:
        """Every pose of `poses` mapped (`pose`)."""
        return {f: self.pose(p) for f, p in poses.items()}

    def then(self, other: Similarity) -> Similarity:
        """`other ∘ self`: first this similarity, then `other`."""
        return Similarity(
            other.scale * self.scale, other.R @ self.R, other.scale * other.R @ self.t + other.t
        )


def similarity_about(q: np.ndarray, c: np.ndarray) -> Similarity:
    """`X' = e^σ R(ω) (X − c) + c + τ` for `q = (ω [rad], τ [m], σ)` `(7,)` about `c` `(3,)`."""
    s, R = float(np.exp(q[6])), so3_exp(q[:3])
    return Similarity(s, R, c + q[3:6] - s * R @ c)


def umeyama(source: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> Similarity:
    """Least-squares similarity `target ≈ s R source + t` of corresponding points `(N, 3)`, N ≥ 3
    not collinear (Umeyama 1991), optionally weighted `(N,)`."""
    w = np.ones(len(source)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    ms, mt = w @ source, w @ target
    S, T = source - ms, target - mt
    U, sv, Vt = np.linalg.svd((T * w[:, None]).T @ S)
    E = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ E @ Vt
    s = float(np.trace(np.diag(sv) @ E) / (w @ np.sum(S**2, axis=1)))
    return Similarity(s, R, mt - s * R @ ms)


def rotation_mean(rotations: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Chordal L2 mean `(3, 3)` of rotations `(N, 3, 3)` (projection of their weighted sum on SO(3))."""
    w = np.ones(len(rotations)) if weights is None else np.asarray(weights, dtype=np.float64)
    U, _, Vt = np.linalg.svd(np.einsum("n,nij->ij", w, rotations))
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def place_on_priors(
    poses: Mapping[int, Pose], prior: Mapping[int, Pose], loss_m: float, iterations: int = 10
) -> tuple[Similarity, float]:
    """`prior_world_from_rec_world` of a reconstruction's `poses` on the GNSS/INS `prior` (same
    frames; module docstring): rotation the robust chordal mean of `R_prior R_recᵀ` (frames
    whose rotation deviates by more than 3 × the median deviation get less weight), scale and
    shift by Huber IRLS (scale `loss_m`, metres) of the rotated centres on the prior centres.
    Returns the similarity and the standard error of its scale (residual RMS over the weighted
    spread of the centres; inf when they do not spread)."""
    fs = sorted(poses)
    Rs = np.array([prior[f].R_world_from_cam @ poses[f].R_world_from_cam.T for f in fs])
    w = np.ones(len(fs))
    for _ in range(3):
        R = rotation_mean(Rs, w)
        ang = np.arccos(np.clip((np.einsum("nij,ij->n", Rs, R) - 1.0) / 2.0, -1.0, 1.0))
        w = 1.0 / np.maximum(1.0, ang / max(3.0 * np.median(ang), 1e-9))
    C = np.array([poses[f].center for f in fs]) @ R.T
    P = np.array([prior[f].center for f in fs])
    w = np.ones(len(fs))
    s, t = 1.0, P.mean(0) - C.mean(0)
    for _ in range(iterations):
        mc, mp = w @ C / w.sum(), w @ P / w.sum()
        dc = C - mc
        denom = float(w @ np.sum(dc**2, axis=1))
        s = float(w @ np.sum(dc * (P - mp), axis=1)) / denom if denom > 1e-12 else 1.0
        t = mp - s * mc
        r = np.linalg.norm(P - (s * C + t), axis=1)
        w = np.minimum(1.0, loss_m / np.maximum(r, 1e-12))
    dof = max(3 * len(fs) - 4, 1)
    sigma_s = float(np.sqrt(w @ r**2 / dof / denom)) if denom > 1e-12 else float("inf")
    return Similarity(s, R, t), sigma_s

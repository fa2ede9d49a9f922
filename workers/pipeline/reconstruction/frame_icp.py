"""Per-frame ICP of a block's dense cloud onto a reference cloud, frames tied by their relative
orientations: every frame's pose corrected, not one rigid transform per block.

In: the source block's per-frame point sets in camera frames (`frame_points[a]` `(N_a, 3)`
metres, camera `a`'s axes: the stereo points of `a`'s pair, triangulated in `a`'s frame, so
free of `a`'s pose error), the frames' initial poses (`Pose`, world = model CRS, metres; e.g.
the GNSS/INS priors after a coarse rigid ICP), the relative orientations of consecutive pairs
measured in the images (`x_b = R x_a + t`, `t` metres) and the reference `target` cloud
`(M, 3)` world metres (the RGB block's dense cloud). Out: `FrameIcpResult`: one corrected pose
per frame and per-frame figures.

One robust least-squares problem over all frames' 6-dof corrections (`ω_a` rotation about the
camera centre, world axes, radians; `dC_a` metres), solved by Gauss-Newton with the
correspondences found again at every iteration, coarse to fine in correspondence distance:
- point-to-plane residuals `n · (R_a x + C_a − p)` of each frame's points against the target
  (nearest target point `p`, PCA normal `n`), Tukey-weighted, `point_sigma_m` each, at most
  `max_points_per_frame` points per frame (so a frame's cloud, whose errors are correlated,
  does not outweigh everything else);
- relative-orientation residuals of each image-measured pair (`a`, `b`): rotation
  `log(R_bᵀ R_a R_abᵀ)` (`relative_rotation_sigma_deg`) and baseline `C_a − C_b − R_b t`
  (`relative_position_sigma_m`): the frames form a flexible chain, so a frame that sees one
  plane only (sliding along it is unobserved) is held by its neighbours that see a corner;
- priors on each frame's initial pose moved by an unknown common offset (rotation and shift
  shared by all frames, weakly held: `common_*_sigma`): per-frame noise `prior_position_sigma_m`,
  `prior_rotation_sigma_deg` (the GNSS/INS white noise and vibration); the common part (bias,
  boresight left over) is not pulled back to the priors.
Linearisation: `R_a = exp([ω_a]×) R_a0`, `C_a = C_a0 + dC_a`; the point residual's Jacobian
is `[(v × n)ᵀ, nᵀ]` with `v = R_a0 x`. Coordinates are taken about the target's centroid.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.pose import Pose


@dataclass(frozen=True)
class FrameIcpOptions:
    """Parameters of `register_frames` (metres, degrees)."""

    distances_m: tuple[float, ...] = (1.5, 1.0, 0.6, 0.4, 0.25)  # correspondence distance per level
    iterations: int = 4  # Gauss-Newton iterations per level
    voxel_m: float = 0.1  # per-frame source downsampling
    target_voxel_m: float = 0.05
    normal_radius_m: float = 0.25
    max_points_per_frame: int = 800
    point_sigma_m: float = 0.15
    relative_rotation_sigma_deg: float = 0.3  # measured on the bench's TIR pairs: 0.24-0.52° median
    relative_position_sigma_m: float = 0.06  # (0.05-0.07 m)
    prior_position_sigma_m: float = 0.3
    prior_rotation_sigma_deg: float = 0.2
    common_position_sigma_m: float = 3.0  # the priors' common error (GNSS bias left over)
    common_rotation_sigma_deg: float = 1.0  # (boresight left over)
    min_points: int = 50  # a frame with fewer correspondences gets no point residuals
    seed: int = 0


@dataclass(frozen=True, eq=False)
class FrameIcpResult:
    """Outcome of `register_frames`.

    Attributes:
        poses: corrected poses, one per frame (world).
        points_used: `(F,)` int, correspondences of each frame at the last iteration.
        rms_m: `(F,)` RMS point-to-plane residual of each frame's inliers at the end (NaN: none).
        step_m: norm of the last iteration's largest position update, metres (convergence).
    """

    poses: tuple[Pose, ...]
    points_used: np.ndarray
    rms_m: np.ndarray
    step_m: float


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector `w` (radians)."""
    th = float(np.linalg.norm(w))
    K = _skew(w / th) if th > 1e-15 else np.zeros((3, 3))
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


def _log(R: np.ndarray) -> np.ndarray:
    """Rotation vector (radians) of `R` (small or moderate angles)."""
    c = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    th = float(np.arccos(c))
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return v * (0.5 if th < 1e-9 else th / (2 * np.sin(th)))


def _subsample(x: np.ndarray, voxel: float, cap: int, rng: np.random.Generator) -> np.ndarray:
    """First point per `voxel` cell of `x` `(N, 3)`, at most `cap` of them (random, seeded)."""
    if len(x) == 0:
        return x
    _, first = np.unique(np.floor(x / voxel).astype(np.int64), axis=0, return_index=True)
    y = x[np.sort(first)]
    if len(y) > cap:
        y = y[np.sort(rng.choice(len(y), cap, replace=False))]
    return y


def _target(target: np.ndarray, options: FrameIcpOptions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origin `(3,)`, target points about it `(M', 3)` downsampled, unit normals `(M', 3)`)."""
    import open3d as o3d

    o = target.mean(axis=0)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target - o)).voxel_down_sample(
        options.target_voxel_m
    )
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=options.normal_radius_m, max_nn=30))
    return o, np.asarray(pc.points), np.asarray(pc.normals)


def register_frames(
    frame_points: Sequence[np.ndarray],
    poses: Sequence[Pose],
    relative: Sequence[tuple[int, int, np.ndarray, np.ndarray]],
    target: np.ndarray,
    options: FrameIcpOptions = FrameIcpOptions(),
) -> FrameIcpResult:
    """Correct every frame's pose (see the module docstring). `frame_points[a]` `(N_a, 3)` in
    camera `a`'s frame (may be empty), `poses[a]` its initial pose, `relative` items `(a, b,
    R_b_from_a, t_b_from_a)` measured in the images, `target` `(M, 3)` world points."""
    from scipy.spatial import cKDTree

    F = len(poses)
    if len(frame_points) != F:
        raise ValueError(f"frame_points: {len(frame_points)} sets for {F} poses")
    o, tp, tn = _target(np.asarray(target, dtype=np.float64), options)
    tree = cKDTree(tp)
    rng = np.random.default_rng(options.seed)
    src = [
        _subsample(np.asarray(x, float), options.voxel_m, options.max_points_per_frame, rng)
        for x in frame_points
    ]
    R0 = [p.R_world_from_cam.copy() for p in poses]
    C0 = [p.center - o for p in poses]
    R, C = [r.copy() for r in R0], [c.copy() for c in C0]
    w_pt = 1.0 / options.point_sigma_m**2
    w_rr = 1.0 / np.radians(options.relative_rotation_sigma_deg) ** 2
    w_rt = 1.0 / options.relative_position_sigma_m**2
    w_pp = 1.0 / options.prior_position_sigma_m**2
    w_pr = 1.0 / np.radians(options.prior_rotation_sigma_deg) ** 2
    wp = np.diag([w_pr] * 3 + [w_pp] * 3)
    wc = np.diag(
        [1.0 / np.radians(options.common_rotation_sigma_deg) ** 2] * 3
        + [1.0 / options.common_position_sigma_m**2] * 3
    )
    common = np.zeros(6)  # common rotation (rad, world axes) and shift (m) of all frames vs their priors
    used, rms, step = np.zeros(F, np.int64), np.full(F, np.nan), 0.0
    for dist in options.distances_m:
        for _ in range(options.iterations):
            H = np.zeros((6 * F + 6, 6 * F + 6))
            g = np.zeros(6 * F + 6)
            H[6 * F :, 6 * F :] += wc  # the common offset's own weak prior (about zero)
            g[6 * F :] += wc @ common
            for a in range(F):
                s = slice(6 * a, 6 * a + 6)
                # prior: initial pose moved by the common offset (world axes), per-frame noise
                e = np.concatenate([_log(R[a] @ R0[a].T), C[a] - C0[a]]) - common
                idx = np.r_[6 * a : 6 * a + 6, 6 * F : 6 * F + 6]
                H[np.ix_(idx, idx)] += np.block([[wp, -wp], [-wp, wp]])
                g[idx] += np.concatenate([wp @ e, -wp @ e])
                used[a], rms[a] = 0, np.nan
                if len(src[a]) == 0:
                    continue
                v = src[a] @ R[a].T
                d, j = tree.query(v + C[a], distance_upper_bound=dist)
                ok = np.isfinite(d)
                if np.count_nonzero(ok) < options.min_points:
                    continue
                n, vv = tn[j[ok]], v[ok]
                r = np.einsum("ij,ij->i", n, vv + C[a] - tp[j[ok]])
                wt = np.where(np.abs(r) < dist, (1 - (r / dist) ** 2) ** 2, 0.0) * w_pt
                J = np.hstack([np.cross(vv, n), n])
                H[s, s] += (J * wt[:, None]).T @ J
                g[s] += J.T @ (wt * r)
                used[a] = int(np.count_nonzero(wt))
                rms[a] = float(np.sqrt(np.sum(wt * r * r) / max(np.sum(wt), 1e-12))) if used[a] else np.nan
            for a, b, R_ba, t_ba in relative:
                er = R[b] @ _log(R[b].T @ R[a] @ R_ba.T)  # world axes
                u = R[b] @ t_ba
                et = C[a] - C[b] - u
                Jr = np.zeros((3, 12))
                Jr[:, 0:3], Jr[:, 6:9] = np.eye(3), -np.eye(3)
                Jt = np.zeros((3, 12))
                Jt[:, 3:6], Jt[:, 9:12], Jt[:, 6:9] = np.eye(3), -np.eye(3), _skew(u)
                idx = np.r_[6 * a : 6 * a + 6, 6 * b : 6 * b + 6]
                H[np.ix_(idx, idx)] += w_rr * Jr.T @ Jr + w_rt * Jt.T @ Jt
                g[idx] += w_rr * Jr.T @ er + w_rt * Jt.T @ et
            dx = -np.linalg.solve(H + 1e-9 * np.eye(len(g)), g)
            common = common + dx[6 * F :]
            for a in range(F):
                R[a] = _exp(dx[6 * a : 6 * a + 3]) @ R[a]
                C[a] = C[a] + dx[6 * a + 3 : 6 * a + 6]
            step = float(np.max(np.linalg.norm(dx[: 6 * F].reshape(F, 6)[:, 3:], axis=1)))
            if step < 1e-4:
                break
    out = tuple(Pose(R[a], C[a] + o) for a in range(F))
    return FrameIcpResult(out, used, rms, step)

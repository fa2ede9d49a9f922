"""Rigid registration of one point cloud onto another: Open3D point-to-plane ICP, robust kernel.

In: `source` `(N, 3)` and `target` `(M, 3)` float64 world points (model CRS, metres), both already
in the same world frame to within the coarse alignment of their priors (metres), and an initial
`target_from_source` `(4, 4)` (identity: the priors are the coarse alignment). Out: `IcpResult`
with `target_from_source` `(4, 4)` in world coordinates (`x_t = R x_s + t`), Open3D's fitness
(share of source points with a correspondence) and inlier RMSE at the finest level, and the
source-to-target nearest-neighbour distances before and after.

Coarse to fine: levels of (voxel size, correspondence distance), each a point-to-plane ICP with a
Tukey kernel of scale `kernel_scale` × that level's distance, started from the previous level's
transform; target normals by PCA over a radius. By default the translation only (the GNSS/INS
error of a drive is mostly a position error; on street scenes of planar facades the rotation is
weakly observed and a 6-dof ICP was measured turning by 9° on the bench drive), with a weak prior
holding directions no plane observes (e.g. height without ground or roofs in view; a direction
counts as observed with at least `degeneracy_ratio` = 1 % of the largest eigenvalue of the
normals' scatter: on the bench drive 94 % of the normals face the street and the along-street
and vertical directions carry 6–8 %, observed by thousands of points; the former 10 % held them
at the prior and left 1.2 m / 1.6 m of the GNSS bias in the poses);
`rotation=True` runs Open3D's 6-dof point-to-plane ICP (`TransformationEstimationPointToPlane`
with `TukeyLoss`). Fitness and inlier RMSE come from `evaluate_registration` at the finest level.
Computed about the target's centroid (large UTM coordinates would lose precision in float32
kernels and in the rotation lever).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class IcpOptions:
    """Parameters of `register_clouds` (metres)."""

    # (voxel, correspondence distance) per level: the coarsest voxel keeps the window reveals,
    # which alone observe the height on facades seen from the street (0.4 m voxels and 1.6 m
    # normal radii smoothed them away: the bench's multi-view TIR cloud stayed 1.2 m low)
    levels: tuple[tuple[float, float], ...] = ((0.2, 3.0), (0.1, 1.2), (0.05, 0.5), (0.05, 0.25))
    kernel_scale: float = 1.0  # Tukey scale as a share of the level's correspondence distance
    normal_radius_factor: float = 4.0  # normal estimation radius = factor × the level's voxel
    max_iterations: int = 40
    relative_rmse: float = 1e-7
    report_max_distance_m: float = 1.0  # `trimmed` distances: nearest neighbours within this
    rotation: bool = False  # 6 dof (Open3D point-to-plane, Tukey) instead of the translation only
    prior_sigma_m: float = 5.0  # translation prior: holds directions no plane observes
    degeneracy_ratio: float = 0.01  # directions with less information than this share keep the prior


@dataclass(frozen=True, eq=False)
class IcpResult:
    """Outcome of `register_clouds`.

    Attributes:
        target_from_source: `(4, 4)` world transform found (`x_t = R x_s + t`).
        fitness: share of source points with a target point within the finest distance.
        inlier_rmse: RMS point-to-point distance of those correspondences, metres (bounded
            below by the point spacing of the finest level's voxel grid).
        mean_before_m / median_before_m / mean_after_m / median_after_m: source-to-target
            distances (`nn_distances`: to the target's local plane, all source points), metres.
        trimmed_mean_before_m / trimmed_mean_after_m: the same mean over the distances below
            `report_max_distance_m` (the overlap, without points the other cloud lacks).
        observed_directions: translation directions (0–3) the target's surfaces observe at the
            solution (translation mode; 3 with `rotation`): the others kept the prior.
    """

    target_from_source: np.ndarray
    fitness: float
    inlier_rmse: float
    mean_before_m: float
    median_before_m: float
    mean_after_m: float
    median_after_m: float
    trimmed_mean_before_m: float
    trimmed_mean_after_m: float
    observed_directions: int = 3


def _cloud(points: np.ndarray) -> object:
    import open3d as o3d

    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64)))


def nn_distances(
    source: np.ndarray, target: np.ndarray, cap_m: float = 1.0, normal_radius_m: float = 0.3
) -> np.ndarray:
    """Cloud-to-cloud distance `(N,)` of every source point `(N, 3)` to the target `(M, 3)`, metres:
    to the local plane of its nearest target point (normal by PCA over `normal_radius_m`) when
    that point is within `cap_m`, else to the point itself; so the figure measures the surfaces'
    separation, not the sampling density of the target."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    if len(source) == 0 or len(target) < 3:
        return np.full(len(source), np.inf)
    o = target.mean(axis=0)
    t = _cloud(target - o)
    t.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_m, max_nn=30))
    tp, tn = np.asarray(t.points), np.asarray(t.normals)
    x = source - o
    d, j = cKDTree(tp).query(x)
    plane = np.abs(np.einsum("ij,ij->i", tn[j], x - tp[j]))
    return np.where(d < cap_m, plane, d)


def _figures(d: np.ndarray, cap: float) -> tuple[float, float, float]:
    """(mean, median, mean of those below `cap`) of distances `d`; NaN when empty."""
    if len(d) == 0:
        return float("nan"), float("nan"), float("nan")
    near = d[d < cap]
    return float(d.mean()), float(np.median(d)), float(near.mean()) if len(near) else float("nan")


def apply_transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """`(4, 4)` transform applied to points `(N, 3)`."""
    return np.asarray(points, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]


def _translation_step(
    s: np.ndarray, t: np.ndarray, normals: np.ndarray, tree: object, T: np.ndarray, t0: np.ndarray,
    dist: float, options: IcpOptions,
) -> np.ndarray:  # fmt: skip
    """One robust point-to-plane step for the translation only: `(3,)` increment. Source `s`
    `(N, 3)`, target `t` `(M, 3)` with `normals` `(M, 3)`, `tree` a KD-tree of `t`, current `T`.
    Directions the planes do not observe are held at the prior translation `t0` `(3,)` (weight
    `1 / prior_sigma_m²` against the residuals' robust variance)."""
    x = apply_transform(T, s)
    d, j = tree.query(x, distance_upper_bound=dist)
    ok = np.isfinite(d)
    if np.count_nonzero(ok) < 10:
        return np.zeros(3)
    n = normals[j[ok]]
    r = np.einsum("ij,ij->i", n, x[ok] - t[j[ok]])
    c = options.kernel_scale * dist
    w = np.where(np.abs(r) < c, (1 - (r / c) ** 2) ** 2, 0.0)  # Tukey
    sigma2 = max(float(np.sum(w * r * r) / max(np.sum(w), 1e-9)), (0.1 * c) ** 2)
    A = (n * w[:, None]).T @ n / sigma2 + np.eye(3) / options.prior_sigma_m**2
    b = -(n * (w * r)[:, None]).sum(axis=0) / sigma2 - (T[:3, 3] - t0) / options.prior_sigma_m**2
    return observed(n, np.ones(len(n)), options.degeneracy_ratio) @ np.linalg.solve(A, b)


def observed(n: np.ndarray, w: np.ndarray, ratio: float = 0.1) -> np.ndarray:
    """Projector `(3, 3)` onto the translation directions the correspondences observe: the
    eigenvectors of the normals' weighted scatter `Σ w n nᵀ` (`n` `(N, 3)`, `w` `(N,)`) with at
    least `ratio` of the largest eigenvalue. A street of parallel facades observes only their
    normal: sliding along them or up is noise-driven and stays with the prior (degeneracy-aware
    solution remapping, Zhang, Kaess & Singh, ICRA 2016)."""
    lam, V = np.linalg.eigh((n * w[:, None]).T @ n)
    keep = V[:, lam >= ratio * max(float(lam[-1]), 1e-12)]
    return keep @ keep.T


def observed_directions(source: np.ndarray, target: np.ndarray, T: np.ndarray, options: IcpOptions) -> int:
    """How many translation directions (0–3) the finest level observes at `T` (see `observed`)."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    voxel, dist = options.levels[-1]
    s, t = _cloud(source).voxel_down_sample(voxel), _cloud(target).voxel_down_sample(voxel)
    radius = options.normal_radius_factor * voxel
    t.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
    tp, tn = np.asarray(t.points), np.asarray(t.normals)
    d, j = cKDTree(tp).query(apply_transform(T, np.asarray(s.points)), distance_upper_bound=dist)
    ok = np.isfinite(d)
    if np.count_nonzero(ok) < 3:
        return 0
    P = observed(tn[j[ok]], np.ones(np.count_nonzero(ok)), options.degeneracy_ratio)
    return round(float(np.trace(P)))


def _translation_icp(
    src: object, tgt: object, T: np.ndarray, t0: np.ndarray, voxel: float, dist: float, options: IcpOptions
) -> np.ndarray:
    """Translation-only robust point-to-plane ICP at one level (local coordinates) -> `(4, 4)`."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    s, t = src.voxel_down_sample(voxel), tgt.voxel_down_sample(voxel)
    radius = options.normal_radius_factor * voxel
    t.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
    sp, tp, tn = np.asarray(s.points), np.asarray(t.points), np.asarray(t.normals)
    tree = cKDTree(tp)
    T = T.copy()
    for _ in range(options.max_iterations):
        dt = _translation_step(sp, tp, tn, tree, T, t0, dist, options)
        T[:3, 3] += dt
        if np.linalg.norm(dt) < 1e-4:
            break
    return T


def register_clouds(
    source: np.ndarray, target: np.ndarray, options: IcpOptions = IcpOptions(), init: np.ndarray | None = None
) -> IcpResult:
    """Register `source` onto `target` (see the module docstring). Raises `ValueError` when a
    cloud has fewer than 10 points."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    if len(source) < 10 or len(target) < 10:
        raise ValueError(f"icp: too few points (source {len(source)}, target {len(target)})")
    o = target.mean(axis=0)
    shift, unshift = np.eye(4), np.eye(4)
    shift[:3, 3], unshift[:3, 3] = -o, o
    T_local = shift @ (np.eye(4) if init is None else np.asarray(init, float)) @ unshift  # about o
    src, tgt = _cloud(source - o), _cloud(target - o)
    t0 = T_local[:3, 3].copy()
    for voxel, dist in options.levels:
        if not options.rotation:
            T_local = _translation_icp(src, tgt, T_local, t0, voxel, dist, options)
            continue
        s, t = src.voxel_down_sample(voxel), tgt.voxel_down_sample(voxel)
        radius = options.normal_radius_factor * voxel
        t.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=30))
        loss = reg.TukeyLoss(k=options.kernel_scale * dist)
        crit = reg.ICPConvergenceCriteria(
            relative_rmse=options.relative_rmse, max_iteration=options.max_iterations
        )
        res = reg.registration_icp(s, t, dist, T_local, reg.TransformationEstimationPointToPlane(loss), crit)
        T_local = np.asarray(res.transformation)
    voxel, dist = options.levels[-1]
    s_fine, t_fine = src.voxel_down_sample(voxel), tgt.voxel_down_sample(voxel)
    res = reg.evaluate_registration(s_fine, t_fine, dist, T_local)
    T = unshift @ T_local @ shift
    dims = 3 if options.rotation else observed_directions(source - o, target - o, T_local, options)
    cap = options.report_max_distance_m
    before = _figures(nn_distances(source, target, cap), cap)
    after = _figures(nn_distances(apply_transform(T, source), target, cap), cap)
    return IcpResult(
        target_from_source=T,
        fitness=float(res.fitness),
        inlier_rmse=float(res.inlier_rmse),
        mean_before_m=before[0],
        median_before_m=before[1],
        mean_after_m=after[0],
        median_after_m=after[1],
        trimmed_mean_before_m=before[2],
        trimmed_mean_after_m=after[2],
        observed_directions=dims,
    )

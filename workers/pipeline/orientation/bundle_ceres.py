"""The bundle adjustment's problem (`bundle`) solved by Ceres (`pyceres`): a second solver, the
numpy one's oracle.

In and out: as `bundle.bundle_adjust` (the same arguments, a `BundleResult`).

The same problem: per frame a correction `δ_f` of its pose (`geometry.pose_increments`), per
track its world point, one common correction `c` of the block's priors; residuals

- tie points: `(uv(δ_f, X_t) − uv_obs) / tie_sigma_px`, Ceres' `HuberLoss` at
  `tie_huber_px / tie_sigma_px` (the numpy solver's Huber weights are its iteratively
  re-weighted form); observations nearer than `min_depth_m` give no residual;
- planes: `(n_t · X_t − d_t) / plane_sigma_m`, weighted by the Tukey weight of the distance at
  the start of each outer iteration (Ceres ships no Tukey loss; the numpy solver re-weights the
  same way every iteration);
- priors: `L_fᵀ (pose_delta(prior_f, pose_f) − c)` with `frame_info = L_f L_fᵀ`, and `L_cᵀ c`; a
  weak prior (σ 1 km) on each point's move, as in the numpy solver;
- model edges: per frame the quadratic form of its edge normal equations at the outer
  iteration's poses (`bundle._add_edge_equations`: an edge search along the projected edges'
  normals, not a differentiable residual), as `Λ^½ Qᵀ δ_f − Λ^-½ Qᵀ g_f` with `H_f = Q Λ Qᵀ`.

The outer iterations follow the numpy solver (edge search radius shrinking from
`edge_radius_start_px`, visibility every `revisibility_every` iterations, tie outliers beyond
`outlier_px` dropped after the first phase); each solves the problem linearised that way with
Ceres' Levenberg-Marquardt (Schur elimination of the points) instead of one Gauss-Newton step,
each frame's move bounded to `max_step_deg` / `max_step_m` per component (the numpy solver scales
its whole step to those bounds).
The residuals are Python cost functions (one call per observation and evaluation): slow, kept as
the test oracle (`bench/bundle.py` measures both: 40–60 × the numpy solver's CPU seconds on
30-frame parts of a real drive's blocks). It agrees with the numpy solver to millimetres on
blocks that converge (`tests/unit/test_bundle_ceres.py`); on blocks whose ties fit badly
(σ0 2.5–3, the frames still moving by tens of pixels when the numpy solver's iterations end)
the two end metres apart. Covariances: `pyceres.Covariance` of the
frames' corrections at the solution, scaled like the numpy solver's by max(1, σ0²).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pyceres

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import apply_delta, pose_delta, project_jacobian
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.bundle import (
    BundleOptions,
    BundleResult,
    _add_edge_equations,
    _block_edges,
    _block_observations,
    _edge_figures,
    _residuals,
    _tie_figures,
)
from workers.pipeline.orientation.features import FeatureOptions
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.priors import PriorOptions
from workers.pipeline.orientation.tracks import Tracks
from workers.pipeline.orientation.wireframe import EdgeOptions, Wireframe

__all__ = ["CeresOptions", "bundle_adjust_ceres"]


@dataclass(frozen=True)
class CeresOptions:
    """Ceres' solver per outer iteration."""

    max_num_iterations: int = 20
    function_tolerance: float = 1e-10
    parameter_tolerance: float = 1e-10
    gradient_tolerance: float = 1e-12


class _Tie(pyceres.CostFunction):
    """One tie observation: residual `(2,)` px / σ of the frame's correction `(6,)` and the point
    `(3,)`."""

    def __init__(self, camera: Camera, ref: Pose, uv: np.ndarray, scale: float, min_depth: float) -> None:
        super().__init__()
        self.camera, self.ref, self.uv, self.scale, self.min_depth = camera, ref, uv, scale, min_depth
        self.set_num_residuals(2)
        self.set_parameter_block_sizes([6, 3])

    def Evaluate(self, parameters: list[np.ndarray], residuals: np.ndarray,
                 jacobians: list[np.ndarray] | None) -> bool:
        pose = apply_delta(self.ref, parameters[0])
        uv, z, J = project_jacobian(self.camera, pose, parameters[1][None])
        ok = bool(z[0] >= self.min_depth and np.all(np.isfinite(uv)))
        residuals[:] = (uv[0] - self.uv) * self.scale if ok else 0.0
        if jacobians is not None:
            Jd = J[0] * self.scale if ok else np.zeros((2, 6))
            if jacobians[0] is not None:
                jacobians[0][:] = Jd.ravel()
            if jacobians[1] is not None:
                jacobians[1][:] = (-Jd[:, 3:]).ravel()
        return True


class _Linear(pyceres.CostFunction):
    """A linear residual `A x − y` `(k,)` of one or more parameter blocks (`A` split by block)."""

    def __init__(self, blocks: list[np.ndarray], y: np.ndarray) -> None:
        super().__init__()
        self.blocks, self.y = blocks, y
        self.set_num_residuals(len(y))
        self.set_parameter_block_sizes([a.shape[1] for a in blocks])

    def Evaluate(self, parameters: list[np.ndarray], residuals: np.ndarray,
                 jacobians: list[np.ndarray] | None) -> bool:
        residuals[:] = sum(a @ p for a, p in zip(self.blocks, parameters, strict=True)) - self.y
        if jacobians is not None:
            for k, a in enumerate(self.blocks):
                if jacobians[k] is not None:
                    jacobians[k][:] = a.ravel()
        return True


class _Prior(pyceres.CostFunction):
    """A frame's prior: `Lᵀ (pose_delta(prior, ref ⊕ δ) − c)` `(6,)` of `δ` and `c`."""

    def __init__(self, ref: Pose, prior: Pose, sqrt_info_t: np.ndarray) -> None:
        super().__init__()
        self.ref, self.prior, self.Lt = ref, prior, sqrt_info_t
        self.set_num_residuals(6)
        self.set_parameter_block_sizes([6, 6])

    def Evaluate(self, parameters: list[np.ndarray], residuals: np.ndarray,
                 jacobians: list[np.ndarray] | None) -> bool:
        rho = pose_delta(self.prior, apply_delta(self.ref, parameters[0]))
        residuals[:] = self.Lt @ (rho - parameters[1])
        if jacobians is not None:
            D = np.eye(6)
            D[:3, :3] = _inverse_right_jacobian(rho[:3])
            if jacobians[0] is not None:
                jacobians[0][:] = (self.Lt @ D).ravel()
            if jacobians[1] is not None:
                jacobians[1][:] = (-self.Lt).ravel()
        return True


def _inverse_right_jacobian(w: np.ndarray) -> np.ndarray:
    """`J_r⁻¹(ω)` `(3, 3)` of SO(3): `∂ log(R₀ exp(ω) exp(δ)) / ∂δ` at δ = 0."""
    t = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if t < 1e-6:
        return np.eye(3) + 0.5 * K
    return np.eye(3) + 0.5 * K + (1 / t**2 - (1 + np.cos(t)) / (2 * t * np.sin(t))) * (K @ K)


def _sqrt_t(info: np.ndarray) -> np.ndarray:
    """`Lᵀ` with `info = L Lᵀ` (symmetric PSD; eigen-decomposition, so semidefinite is fine)."""
    lam, Q = np.linalg.eigh(0.5 * (info + info.T))
    return np.sqrt(np.clip(lam, 0.0, None))[:, None] * Q.T


def bundle_adjust_ceres(
    camera: Camera, frames: Sequence[int], images: Mapping[int, np.ndarray], start: Mapping[int, Pose],
    prior: Mapping[int, Pose], frame_info: Mapping[int, np.ndarray], common_info: np.ndarray | None,
    tracks: Tracks, wireframe: Wireframe | None, raycaster: RayCaster,
    options: BundleOptions = BundleOptions(),
    fit_options: FrameFitOptions = FrameFitOptions(), edge_options: EdgeOptions = EdgeOptions(),
    feature_options: FeatureOptions = FeatureOptions(), prior_options: PriorOptions = PriorOptions(),
    ceres_options: CeresOptions = CeresOptions(),
) -> BundleResult:
    """`bundle.bundle_adjust`'s problem solved with Ceres (module docstring; same arguments)."""
    frames = list(frames)
    n = len(frames)
    poses = {f: start[f] for f in frames}
    slot, t_obs, f_obs, uv_obs = _block_observations(tracks, frames)
    X = tracks.point.copy()
    inl = np.ones(len(t_obs), bool)
    wf, edges = _block_edges(camera, wireframe, raycaster, frames, images, poses, options, fit_options,
                             edge_options, feature_options)
    common = np.zeros(6)
    polish, k_phase = False, 0
    for it in range(options.iterations + options.polish_iterations):
        R_e = max(fit_options.edge_radius_min_px, options.edge_radius_start_px * options.radius_decay ** it)
        He = np.zeros((6 * n, 6 * n))
        ge = np.zeros(6 * n)
        if edges:
            _add_edge_equations(He, ge, camera, wf, raycaster, edges, poses, slot, it, R_e,  # type: ignore[arg-type]
                                options, fit_options, edge_options)
        delta, X, common, _ = _solve(camera, frames, poses, prior, frame_info, common_info, common, He, ge,
                                     f_obs[inl], t_obs[inl], uv_obs[inl], X, tracks, options, ceres_options)
        for f in frames:
            poses[f] = apply_delta(poses[f], delta[slot[f]])
        k_phase += 1
        move = max(float(np.max(np.linalg.norm(delta[:, 3:], axis=1))),
                   10.0 * float(np.max(np.linalg.norm(delta[:, :3], axis=1))))
        # (without edges there is no search radius to wait for)
        done = move < options.converged_m and (not edges or R_e <= fit_options.edge_radius_min_px + 1e-9)
        if polish and (done or k_phase >= options.polish_iterations):
            break
        if not polish and (done or k_phase >= options.iterations):
            polish, k_phase = True, 0
            r = _residuals(camera, poses, frames, f_obs, t_obs, uv_obs, X)
            inl = np.linalg.norm(r, axis=1) <= options.outlier_px
    inl, ties, tie_rms, sigma0 = _tie_figures(camera, poses, frames, slot, f_obs, t_obs, uv_obs, X, options)
    # covariances: the last outer iteration's problem again at the solution (zero corrections)
    He = np.zeros((6 * n, 6 * n))
    ge = np.zeros(6 * n)
    if edges:
        _add_edge_equations(He, ge, camera, wf, raycaster, edges, poses, slot, 1,  # type: ignore[arg-type]
                            fit_options.edge_radius_min_px, options, fit_options, edge_options)
    *_, cov = _solve(camera, frames, poses, prior, frame_info, common_info, common, He, ge, f_obs[inl],
                     t_obs[inl], uv_obs[inl], X, tracks, options, ceres_options, covariance=True)
    s2 = max(1.0, sigma0**2)
    edge_rms, support, null, matched = _edge_figures(camera, wf, raycaster, edges, poses,  # type: ignore[arg-type]
                                                     edge_options, fit_options, prior_options.null_shift_px,
                                                     options.visibility_reuse_px)
    ok = cov is not None
    covariance = {f: cov[slot[f]] * s2 if cov is not None else np.full((6, 6), np.nan) for f in frames}
    return BundleResult(poses=poses, covariance=covariance, ties=ties, tie_rms_px=tie_rms,
                        edge_rms_px=edge_rms, edge_support=support, null_support=null, matched_edges=matched,
                        points=X, inlier=inl, sigma0=sigma0, converged=ok)


def _solve(
    camera: Camera, frames: Sequence[int], poses: Mapping[int, Pose], prior: Mapping[int, Pose],
    frame_info: Mapping[int, np.ndarray], common_info: np.ndarray | None, common: np.ndarray, He: np.ndarray,
    ge: np.ndarray, f_obs: np.ndarray, t_obs: np.ndarray, uv_obs: np.ndarray, X: np.ndarray, tracks: Tracks,
    options: BundleOptions, ceres_options: CeresOptions, covariance: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """One outer iteration: the problem around `poses` (corrections from zero), solved (or, with
    `covariance`, only its covariance taken at the start). Returns (corrections `(n, 6)`, points
    `(T, 3)`, common correction `(6,)`, frame covariances `(n, 6, 6)` or None)."""
    n = len(frames)
    problem = pyceres.Problem()
    delta = [np.zeros(6) for _ in frames]
    pts = [np.array(x, dtype=np.float64) for x in X]
    c = np.array(common, dtype=np.float64)
    for d in delta:
        problem.add_parameter_block(d, 6)
        # one outer iteration's move is bounded like a numpy step (the edge equations are a local
        # model around the outer iteration's poses)
        for i in range(6):
            lim = np.radians(options.max_step_deg) if i < 3 else options.max_step_m
            problem.set_parameter_lower_bound(d, i, -lim)
            problem.set_parameter_upper_bound(d, i, lim)
    problem.add_parameter_block(c, 6)
    if common_info is None:
        problem.set_parameter_block_constant(c)
    else:
        problem.add_residual_block(_Linear([_sqrt_t(common_info)], np.zeros(6)), None, [c])
    huber = pyceres.HuberLoss(options.tie_huber_px / options.tie_sigma_px)
    for k, f in enumerate(frames):
        problem.add_residual_block(_Prior(poses[f], prior[f], _sqrt_t(frame_info[f])), None, [delta[k], c])
        Hk = He[6 * k:6 * k + 6, 6 * k:6 * k + 6]
        if np.any(Hk):
            lam, Q = np.linalg.eigh(0.5 * (Hk + Hk.T))
            keep = lam > 1e-12 * max(float(lam.max()), 1e-300)
            s = np.sqrt(lam[keep])
            A = s[:, None] * Q[:, keep].T
            y = (Q[:, keep].T @ ge[6 * k:6 * k + 6]) / s
            problem.add_residual_block(_Linear([A], y), None, [delta[k]])
    scale = 1.0 / options.tie_sigma_px
    for o in range(len(f_obs)):
        tie = _Tie(camera, poses[frames[f_obs[o]]], uv_obs[o], scale, options.min_depth_m)
        problem.add_residual_block(tie, huber, [delta[f_obs[o]], pts[t_obs[o]]])
    rp = np.asarray(tracks.offset) - np.sum(tracks.normal * X, axis=1)
    x = np.abs(rp) / options.plane_tukey_m
    wp = np.where(x < 1, (1 - x * x) ** 2, 0.0) / options.plane_sigma_m**2
    for t in np.unique(t_obs):
        # the numpy solver's weak prior on each point's step (points seen from nearly one direction)
        problem.add_residual_block(_Linear([1e-3 * np.eye(3)], 1e-3 * X[t]), None, [pts[t]])
        if wp[t] > 0:
            s = np.sqrt(wp[t])
            plane = _Linear([s * tracks.normal[t][None]], np.array([s * tracks.offset[t]]))
            problem.add_residual_block(plane, None, [pts[t]])
    if not covariance:
        so = pyceres.SolverOptions()
        so.linear_solver_type = pyceres.LinearSolverType.SPARSE_SCHUR
        so.max_num_iterations = ceres_options.max_num_iterations
        so.function_tolerance = ceres_options.function_tolerance
        so.parameter_tolerance = ceres_options.parameter_tolerance
        so.gradient_tolerance = ceres_options.gradient_tolerance
        so.num_threads = 1
        summary = pyceres.SolverSummary()
        pyceres.solve(so, problem, summary)
        return np.array(delta), np.array(pts).reshape(-1, 3), c, None
    cov_options = pyceres.CovarianceOptions()
    cov = pyceres.Covariance(cov_options)
    if not cov.compute([(d, d) for d in delta], problem):
        return np.array(delta), np.array(pts).reshape(-1, 3), c, None
    blocks = np.array([cov.get_covariance_block(d, d) for d in delta])
    return np.array(delta), np.array(pts).reshape(-1, 3), c, blocks.reshape(n, 6, 6)

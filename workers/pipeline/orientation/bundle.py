"""Bundle adjustment of a block of frames against the building model (tie points, planes, edges).

In: a `Camera`, frames with their images `(H, W)` float32, start poses and GNSS/INS priors
(world = model CRS) with their information matrices, feature `Tracks` on the model's surfaces
(`tracks`), a wireframe and the `RayCaster` of the scene. Out: `BundleResult`: a refined pose per
frame with its covariance, residual figures and tie counts, the adjusted track points.

Why (Hoegner & Stilla, method 2, with the model edges of Avbelj et al. 2012): at close range a
single TIR frame of a drive rarely shows enough model edges to fix its pose (a vertical corner,
no eave, no ground line), and its GNSS/INS pose is decimetres off from frame to frame. Facade
points tracked through the sequence tie the frames together to a fraction of a pixel; the points
lying on the model's planes, the model's edges wherever a frame sees them, and the priors place
the tied block in the model.

Unknowns: per frame a correction `δ_f = (ω_cam, dC_world)` of its pose
(`geometry.pose_increments.apply_delta`), per track its world point `X_t` (3). Observations:

- tie points: image positions of every track observation, σ `tie_sigma_px`, Huber weights;
- planes: the distance of `X_t` from the plane of the model polygon its track lies on, σ
  `plane_sigma_m`, re-weighted by that distance each iteration (Tukey: points off the model, on
  trees, cars or recessed windows, lose their weight);
- model edges: the edge-normal distances of every visible wireframe sample to the strongest
  image edge along the normal (`edge_observations.normal_equations`, Tukey weights, search
  radius shrinking from `edge_radius_start_px`), weighted by `edge_weight`;
- priors: the GNSS/INS errors of a block's frames are not independent (Kolecki et al.; the
  calibration leaves a common error of decimetres, the white noise and vibration vary from frame
  to frame). Hence one common correction `c` (6) of the block with a prior of zero
  (`common_info`, the calibrated accuracy), and per frame `δ_total,f − c = 0` with the
  per-frame information (`frame_info`, the white part). Independent priors of a few decimetres
  each would pin a block of forty frames to its common error as if it were known to centimetres.

Each Gauss-Newton step eliminates the points (3 × 3 blocks, Schur complement) and solves the
reduced `6 (n + 1) × 6 (n + 1)` system of the frames and the common correction: banded (a track
ties a few consecutive frames) with the common correction as a dense border (`bundle_system`).
The visible model edges of a frame are computed on the part of the wireframe its camera may see
(`edge_observations.FrameWireframes`: the same samples as on the whole scene). The same problem
solved by Ceres is the test oracle (`bundle_ceres`; `bench/bundle.py` compares both). After
convergence, tie observations beyond `outlier_px` are dropped and the adjustment continues. The
frame covariances are the diagonal blocks of the reduced system's inverse, scaled by the
a-posteriori variance factor (≥ 1).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import apply_delta, pose_delta, step_scale
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.bundle_edges import (
    stacked_edge_equations,
    stacked_project,
    stacked_project_jacobian,
)
from workers.pipeline.orientation.bundle_system import (
    banded_width,
    block_sums,
    diagonal_inverse_blocks,
    single_threaded_blas,
    solve_reduced,
)
from workers.pipeline.orientation.bundle_types import BundleOptions, BundleResult
from workers.pipeline.orientation.edge_observations import (
    FrameEdges,
    FrameWireframes,
    edge_support,
    frame_edges,
)
from workers.pipeline.orientation.features import FeatureOptions
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.priors import PriorOptions
from workers.pipeline.orientation.tracks import Tracks
from workers.pipeline.orientation.wireframe import EdgeOptions, Wireframe

__all__ = ["BundleOptions", "BundleResult", "bundle_adjust", "track_pairs"]


def track_pairs(track: np.ndarray, n_tracks: int) -> tuple[np.ndarray, np.ndarray]:
    """All ordered pairs `(i, j)` of observations of the same track, `i` and `j` `(P,)` indices
    into `track` `(M,)` (pairs with i == j included).

    >>> i, j = track_pairs(np.array([0, 1, 0]), 2)
    >>> sorted(zip(i.tolist(), j.tolist()))
    [(0, 0), (0, 2), (1, 1), (2, 0), (2, 2)]
    """
    order = np.argsort(track, kind="stable")
    ts = track[order]
    counts = np.bincount(ts, minlength=n_tracks)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rep = counts[ts]
    first = np.repeat(np.arange(len(ts)), rep)
    offs = np.arange(int(rep.sum())) - np.repeat(np.cumsum(rep) - rep, rep)
    second = starts[ts[first]] + offs
    return order[first], order[second]


def bundle_adjust(
    camera: Camera,
    frames: Sequence[int],
    images: Mapping[int, np.ndarray],
    start: Mapping[int, Pose],
    prior: Mapping[int, Pose],
    frame_info: Mapping[int, np.ndarray],
    common_info: np.ndarray | None,
    tracks: Tracks,
    wireframe: Wireframe | FrameWireframes | None,
    raycaster: RayCaster,
    options: BundleOptions = BundleOptions(),
    fit_options: FrameFitOptions = FrameFitOptions(),
    edge_options: EdgeOptions = EdgeOptions(),
    feature_options: FeatureOptions = FeatureOptions(),
    prior_options: PriorOptions = PriorOptions(),
    figures_below_sigma0: float = float("inf"),
) -> BundleResult:
    """Adjust the poses of `frames` from `start` (see the module docstring).

    Args:
        camera: interior orientation.
        frames: frame indices of the block.
        images: `(H, W)` float32 physical values per frame (model edges).
        start: start pose per frame.
        prior: GNSS/INS (calibrated) prior pose per frame.
        frame_info: `(6, 6)` information of each frame's own deviation from the block's common
            prior error (rad⁻², m⁻²).
        common_info: `(6, 6)` information of the zero prior of the common error; None: no
            common error (each frame's prior is independent).
        tracks: tie-point tracks on the model's surfaces (observations of other frames ignored).
        wireframe: model edges to observe (None: no edge observations), or its parts per frame
            (`FrameWireframes`, kept by the caller for another adjustment of the same frames).
        raycaster: the scene (hidden-edge removal).
        options, fit_options, edge_options, feature_options: parameters.
        prior_options: the null shift of the final edge support (`null_support`).
        figures_below_sigma0: the final edge figures (`edge_rms_px`, `edge_support`,
            `null_support`, `matched_edges`) are left empty when the ties' σ0 exceeds this
            (`block.adjust_block`: that block is tracked and adjusted again, this result is not kept).
    """
    with single_threaded_blas():  # small dense algebra: OpenBLAS threads only spin (bundle_system)
        return _adjust(camera, frames, images, start, prior, frame_info, common_info, tracks, wireframe,
                       raycaster, options, fit_options, edge_options, feature_options, prior_options,
                       figures_below_sigma0)


def _adjust(
    camera: Camera, frames: Sequence[int], images: Mapping[int, np.ndarray], start: Mapping[int, Pose],
    prior: Mapping[int, Pose], frame_info: Mapping[int, np.ndarray], common_info: np.ndarray | None,
    tracks: Tracks, wireframe: Wireframe | FrameWireframes | None, raycaster: RayCaster,
    options: BundleOptions, fit_options: FrameFitOptions, edge_options: EdgeOptions,
    feature_options: FeatureOptions, prior_options: PriorOptions, figures_below_sigma0: float,
) -> BundleResult:
    """`bundle_adjust`."""
    frames = list(frames)
    n = len(frames)
    poses = {f: start[f] for f in frames}
    slot, t_obs, f_obs, uv_obs = _block_observations(tracks, frames)
    X = tracks.point.copy()
    nrm = tracks.normal
    d_plane = np.asarray(tracks.offset)
    inl = np.ones(len(t_obs), bool)
    wf, edges = _block_edges(camera, wireframe, raycaster, frames, images, poses, options, fit_options,
                             edge_options, feature_options)
    w_tie = options.tie_sigma_px ** -2
    w_plane = options.plane_sigma_m ** -2
    nc = 0 if common_info is None else 1  # the common correction's block
    S = np.zeros((6 * (n + nc), 6 * (n + nc)))
    band = banded_width(t_obs, f_obs, len(X))
    common = np.zeros(6)
    polish, k_phase = False, 0
    converged = True
    for it in range(options.iterations + options.polish_iterations):
        R_e = max(fit_options.edge_radius_min_px, options.edge_radius_start_px * options.radius_decay ** it)
        use = _tied(inl, t_obs, len(X), options.min_track_observations)
        S, b, V_inv, Wt, bt = _normal_system(camera, frames, poses, prior, frame_info, common_info, common,
                                             f_obs[use], t_obs[use], uv_obs[use], X, nrm, d_plane, w_tie,
                                             w_plane, options)
        if edges:
            _add_edge_equations(S, b, camera, wf, raycaster, edges, poses, slot, it, R_e,  # type: ignore[arg-type]
                                options, fit_options, edge_options)
        x = solve_reduced(S, b, n, band)
        if x is None:
            converged = False
            break
        dx = _bounded(x, options)
        steps = dx.reshape(-1, 6)[:n]
        for f in frames:
            poses[f] = apply_delta(poses[f], steps[slot[f]])
        if nc:
            common = common + dx[6 * n:]
        if len(Wt):
            X = X + _point_steps(V_inv, Wt, bt, steps[f_obs[use]], t_obs[use])
        # converged: steps below `converged_m` (rotations as metres at 10 m) or below
        # `converged_sigma` of every frame's own σ, the edge search at its final radius; then the
        # outliers go and the polish runs to convergence
        k_phase += 1
        done = R_e <= fit_options.edge_radius_min_px + 1e-9 and (
            _largest_move(dx) < options.converged_m or _largest_sigma_step(S, steps) < options.converged_sigma
        )
        if polish and (done or k_phase >= options.polish_iterations):
            break
        if not polish and (done or k_phase >= options.iterations):
            polish, k_phase = True, 0
            r = _residuals(camera, poses, frames, f_obs, t_obs, uv_obs, X)
            inl = np.linalg.norm(r, axis=1) <= options.outlier_px
    # figures at the final poses
    inl, ties, tie_rms, sigma0 = _tie_figures(camera, poses, frames, slot, f_obs, t_obs, uv_obs, X, options)
    seen = edges if sigma0 <= figures_below_sigma0 else {}
    edge_rms, support, null, matched = _edge_figures(camera, wf, raycaster, seen, poses,  # type: ignore[arg-type]
                                                     edge_options, fit_options, prior_options.null_shift_px,
                                                     options.visibility_reuse_px)
    cov, factored = _covariances(S, frames, slot, sigma0)
    return BundleResult(poses=poses, covariance=cov, ties=ties, tie_rms_px=tie_rms, edge_rms_px=edge_rms,
                        edge_support=support, null_support=null, matched_edges=matched, points=X, inlier=inl,
                        sigma0=sigma0, converged=converged and factored)


def _tied(inl: np.ndarray, t_obs: np.ndarray, n_tracks: int, k: int) -> np.ndarray:
    """`(M,)` bool: the inlier observations `inl` of tracks (`t_obs` `(M,)`) with at least `k`
    of them: a point seen once ties nothing (its elimination only cancels its own observation)."""
    counts = np.bincount(t_obs[inl], minlength=n_tracks)
    return inl & (counts[t_obs] >= k)


def _block_observations(
    tracks: Tracks, frames: Sequence[int]
) -> tuple[dict[int, int], np.ndarray, np.ndarray, np.ndarray]:
    """The slot of each frame in the block and the track observations in `frames`: track ids
    `(K,)`, frame slots `(K,)`, image positions `(K, 2)` px."""
    slot = {f: k for k, f in enumerate(frames)}
    m_obs = np.isin(tracks.frame, frames)
    f_obs = np.array([slot[f] for f in tracks.frame[m_obs]], dtype=int)
    return slot, tracks.track[m_obs], f_obs, tracks.uv[m_obs]


def _block_edges(
    camera: Camera, wireframe: Wireframe | FrameWireframes | None, raycaster: RayCaster,
    frames: Sequence[int], images: Mapping[int, np.ndarray], poses: Mapping[int, Pose],
    options: BundleOptions, fit_options: FrameFitOptions, edge_options: EdgeOptions,
    feature_options: FeatureOptions,
) -> tuple[FrameWireframes | None, dict[int, FrameEdges]]:
    """Per frame the part of the scene wireframe it may see (the same visible samples) and the
    image edges around it (`frame_edges`); `(None, {})` without edge observations."""
    if not options.edges or wireframe is None:
        return None, {}
    wf = wireframe if isinstance(wireframe, FrameWireframes) else FrameWireframes(wireframe, camera)
    margin = options.edge_radius_start_px + fit_options.roi_margin_px
    return wf, frame_edges(camera, wf, raycaster, frames, images, poses, margin, fit_options, edge_options,
                           feature_options)


def _bounded(dx: np.ndarray, options: BundleOptions) -> np.ndarray:
    """The Gauss-Newton step `(6 (n + c),)` scaled so that no block moves more than `max_step_deg`
    and `max_step_m`: one scale for the whole step (frames and common correction are coupled:
    bounding them one by one would change the step's direction)."""
    return dx * min(step_scale(d, options.max_step_deg, options.max_step_m) for d in dx.reshape(-1, 6))


def _largest_move(dx: np.ndarray) -> float:
    """The largest motion of a block of the step (metres; rotations as the motion they cause at
    10 m)."""
    blocks = dx.reshape(-1, 6)
    return max(float(np.max(np.linalg.norm(blocks[:, 3:], axis=1))),
               10.0 * float(np.max(np.linalg.norm(blocks[:, :3], axis=1))))


def _largest_sigma_step(S: np.ndarray, steps: np.ndarray) -> float:
    """The largest step of a frame, `steps` `(n, 6)`, in units of its own σ: `sqrt(δᵀ S_ff δ)`
    with `S_ff` the frame's `(6, 6)` diagonal block of the reduced normal matrix `S` (its
    information with the other frames and the common correction held)."""
    n = len(steps)
    if n == 0:
        return 0.0
    idx = np.arange(n)[:, None] * 6 + np.arange(6)[None, :]
    D = S[idx[:, :, None], idx[:, None, :]]
    return float(np.sqrt(max(float(np.max(np.einsum("ni,nij,nj->n", steps, D, steps))), 0.0)))


def _add_edge_equations(
    S: np.ndarray, b: np.ndarray, camera: Camera, wireframe: FrameWireframes, raycaster: RayCaster,
    edges: Mapping[int, FrameEdges], poses: Mapping[int, Pose], slot: Mapping[int, int], it: int, R_e: float,
    options: BundleOptions, fit_options: FrameFitOptions, edge_options: EdgeOptions,
) -> None:
    """Add the model-edge normal equations of every frame (search radius `R_e`, iteration `it`;
    visibility recomputed every `revisibility_every` iterations) to the frames' blocks of the
    reduced system `S`, `b` in place, weighted by `edge_weight` (all frames at once,
    `bundle_edges.stacked_edge_equations`)."""
    fo_it = replace(fit_options, tukey_min_px=max(fit_options.tukey_min_px, R_e / 3))
    used = []
    for f, ed in edges.items():
        if it % options.revisibility_every == 0 and it > 0:
            ed.vis = wireframe.visible(f, poses[f], raycaster, edge_options, fit_options.max_samples,
                                       options.visibility_reuse_px)
        if ed.vis is not None and len(ed.vis.points) >= fit_options.min_samples:
            used.append(f)
    H, g = stacked_edge_equations(camera, [poses[f] for f in used], [edges[f].vis for f in used],
                                  [edges[f].feats for f in used], R_e, fo_it)
    for f, Hf, gf in zip(used, H, g, strict=True):
        k = 6 * slot[f]
        S[k:k + 6, k:k + 6] += options.edge_weight * Hf
        b[k:k + 6] += options.edge_weight * gf


def _point_steps(V_inv: np.ndarray, Wt: np.ndarray, bt: np.ndarray, dpose: np.ndarray,
                 t_obs: np.ndarray) -> np.ndarray:
    """Back-substitution of the points `(T, 3)`: ΔX_t = V_t⁻¹ (b_t − Σ W_oᵀ Δ_f(o)), with the
    frames' steps `dpose` `(M, 6)` of the observations `t_obs` `(M,)` taken (`_normal_system`)."""
    rhs = bt.copy()
    np.add.at(rhs, t_obs, -np.einsum("oij,oi->oj", Wt, dpose))
    return np.einsum("tij,tj->ti", V_inv, rhs)


def _tie_figures(
    camera: Camera, poses: Mapping[int, Pose], frames: Sequence[int], slot: Mapping[int, int],
    f_obs: np.ndarray, t_obs: np.ndarray, uv_obs: np.ndarray, X: np.ndarray, options: BundleOptions,
) -> tuple[np.ndarray, dict[int, int], dict[int, float], float]:
    """The ties at the final poses: (inlier `(M,)` within `outlier_px`, inliers per frame, their
    RMS per frame (px), σ0 of unit weight)."""
    r = _residuals(camera, poses, frames, f_obs, t_obs, uv_obs, X)
    e = np.linalg.norm(r, axis=1)
    inl = e <= options.outlier_px
    ties = {f: int(np.sum(inl & (f_obs == slot[f]))) for f in frames}
    tie_rms = {f: float(np.sqrt(np.mean(e[inl & (f_obs == slot[f])] ** 2))) if ties[f] else float("nan")
               for f in frames}
    chi2 = float(np.sum((e[inl] / options.tie_sigma_px) ** 2))
    # redundancy of the ties: 2 per observation, minus 2 per point (3 coordinates, 1 plane)
    dof = 2 * int(inl.sum()) - 2 * int(np.unique(t_obs[inl]).size)
    sigma0 = float(np.sqrt(chi2 / dof)) if dof > 0 else 1.0
    return inl, ties, tie_rms, sigma0


def _edge_figures(
    camera: Camera, wireframe: FrameWireframes, raycaster: RayCaster, edges: Mapping[int, FrameEdges],
    poses: Mapping[int, Pose], edge_options: EdgeOptions, fit_options: FrameFitOptions, null_shift_px: float,
    reuse_px: float,
) -> tuple[dict[int, float], dict[int, float], dict[int, float], dict[int, int]]:
    """Per frame that sees model edges, at its final pose (`edge_observations.edge_support`): RMS
    of the inlier edge offsets (px), edge support, null support (samples `null_shift_px` off
    their edges), matched model edges."""
    edge_rms: dict[int, float] = {}
    support: dict[int, float] = {}
    null: dict[int, float] = {}
    matched: dict[int, int] = {}
    for f, ed in edges.items():
        vis = wireframe.visible(f, poses[f], raycaster, edge_options, fit_options.max_samples, reuse_px)
        got = edge_support(camera, wireframe.wireframe, raycaster, poses[f], ed.feats, edge_options,
                           fit_options, null_shift_px, visible=vis)
        if got is None:
            continue
        support[f], null[f], off, matched[f] = got
        edge_rms[f] = float(np.sqrt(np.mean(off**2))) if len(off) else float("nan")
    return edge_rms, support, null, matched


def _covariances(S: np.ndarray, frames: Sequence[int], slot: Mapping[int, int],
                 sigma0: float) -> tuple[dict[int, np.ndarray], bool]:
    """The frames' covariances `(6, 6)` from the Cholesky factor of the last reduced system `S`,
    scaled by max(1, σ0²), and whether `S` was positive definite (else NaN: the frames' poses
    are not determined)."""
    n = len(frames)
    blocks = diagonal_inverse_blocks(S, n)
    ok = blocks is not None
    if blocks is None:
        blocks = np.full((n, 6, 6), np.nan)
    s2 = max(1.0, sigma0**2)
    return {f: blocks[slot[f]] * s2 for f in frames}, ok


def _pose_arrays(poses: Mapping[int, Pose], frames: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Rotations `(n, 3, 3)` (world from camera) and centres `(n, 3)` of `frames`, in block order."""
    return np.stack([poses[f].R_world_from_cam for f in frames]), np.stack([poses[f].center for f in frames])


def _residuals(camera: Camera, poses: Mapping[int, Pose], frames: Sequence[int], f_obs: np.ndarray,
               t_obs: np.ndarray, uv_obs: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Tie residuals `(M, 2)` px (observed − projected); NaN-free (behind: large)."""
    if len(f_obs) == 0:
        return np.full((0, 2), 1e6)
    Rs, Cs = _pose_arrays(poses, frames)
    uv, z = stacked_project(camera, Rs[f_obs], Cs[f_obs], X[t_obs])
    r = uv_obs - uv
    r[~(np.isfinite(r).all(axis=1) & (z > 0))] = 1e6
    return r


def _normal_system(
    camera: Camera, frames: Sequence[int], poses: Mapping[int, Pose], prior: Mapping[int, Pose],
    frame_info: Mapping[int, np.ndarray], common_info: np.ndarray | None, common: np.ndarray,
    f_obs: np.ndarray, t_obs: np.ndarray, uv_obs: np.ndarray, X: np.ndarray, nrm: np.ndarray,
    d_plane: np.ndarray, w_tie: float, w_plane: float, options: BundleOptions,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reduced normal equations of the frames and the common correction (last block, when
    `common_info` is given; points eliminated).

    Returns (S `(6(n+c), 6(n+c))`, b `(6(n+c),)` (c = 1 with a common correction, else 0),
    V⁻¹ `(T, 3, 3)`, W `(M, 6, 3)` per observation, b_t `(T, 3)`)."""
    n = len(frames)
    T = len(X)
    M = len(f_obs)
    U = np.zeros((n, 6, 6))
    bu = np.zeros((n, 6))
    Scc = np.zeros((6, 6)) if common_info is None else common_info.copy()
    bc = -Scc @ common
    Sfc = np.zeros((n, 6, 6))
    for k, f in enumerate(frames):
        # ρ_f = δ_total,f − c, ∂ρ/∂δ_f = I, ∂ρ/∂c = −I
        info = frame_info[f]
        rho = pose_delta(prior[f], poses[f]) - common
        U[k] += info
        bu[k] -= info @ rho
        Sfc[k] -= info
        Scc += info
        bc += info @ rho
    V = np.zeros((T, 3, 3))
    bt = np.zeros((T, 3))
    # planes: r = d − n·X, weight re-weighted by the distance (Tukey)
    rp = d_plane - np.sum(nrm * X, axis=1)
    x = np.abs(rp) / options.plane_tukey_m
    wp = w_plane * np.where(x < 1, (1 - x * x) ** 2, 0.0)
    V += wp[:, None, None] * nrm[:, :, None] * nrm[:, None, :]
    bt += (wp * rp)[:, None] * nrm
    # damping of every point's step (a point seen from nearly one direction without plane weight:
    # with 1e-6 m⁻² its V had a condition of 1e12, and the inverse's rounding made a frame's block
    # of S indefinite on a 300-frame NRW drive, -7e3 against 3e7, ending the adjustment); 1e-4
    # suffices there, 1e-2 held points kilometres away (tests/unit/test_bundle.py)
    V += np.eye(3)[None] * options.point_step_sigma_m ** -2
    Wt = np.zeros((M, 6, 3))
    if M:
        Rs, Cs = _pose_arrays(poses, frames)  # every observation at once
        uv, depth, Jf = stacked_project_jacobian(camera, Rs[f_obs], Cs[f_obs], X[t_obs])
        e = uv_obs - uv
        front = (depth >= options.min_depth_m) & np.isfinite(e).all(axis=1)
        e = np.where(front[:, None], np.nan_to_num(e, nan=0.0), 0.0)
        Jx = -Jf[:, :, 3:]
        a = np.linalg.norm(e, axis=1)
        w = w_tie * np.where(a <= options.tie_huber_px, 1.0, options.tie_huber_px / np.maximum(a, 1e-12))
        w = np.where(front, w, 0.0)
        JfW = Jf * w[:, None, None]
        U += block_sums(f_obs, np.einsum("oki,okj->oij", JfW, Jf), n)
        bu += block_sums(f_obs, np.einsum("oki,ok->oi", JfW, e), n)
        V += block_sums(t_obs, np.einsum("oki,okj->oij", Jx * w[:, None, None], Jx), T)
        bt += block_sums(t_obs, np.einsum("oki,ok->oi", Jx * w[:, None, None], e), T)
        Wt = np.einsum("oki,okj->oij", JfW, Jx)
    V_inv = np.linalg.inv(V)
    S4 = np.zeros((n, n, 6, 6))
    S4[np.arange(n), np.arange(n)] = U
    b = bu.copy()
    if M:
        Y = np.einsum("oij,ojk->oik", Wt, V_inv[t_obs])  # W V⁻¹  (M, 6, 3)
        i, j = track_pairs(t_obs, T)
        pair = np.einsum("pik,pjk->pij", Y[i], Wt[j])
        S4 -= block_sums(f_obs[i] * n + f_obs[j], pair, n * n).reshape(S4.shape)
        b -= block_sums(f_obs, np.einsum("oik,ok->oi", Y, bt[t_obs]), n)
    if common_info is None:
        return S4.transpose(0, 2, 1, 3).reshape(6 * n, 6 * n), b.reshape(-1), V_inv, Wt, bt
    S = np.zeros((6 * (n + 1), 6 * (n + 1)))
    S[:6 * n, :6 * n] = S4.transpose(0, 2, 1, 3).reshape(6 * n, 6 * n)
    S[:6 * n, 6 * n:] = Sfc.reshape(6 * n, 6)
    S[6 * n:, :6 * n] = Sfc.reshape(6 * n, 6).T
    S[6 * n:, 6 * n:] = Scc
    return S, np.concatenate([b.reshape(-1), bc]), V_inv, Wt, bt

"""Joint orientation of all frames of a building: ONE common correction of the GNSS/INS priors.

In: `Camera`, a wireframe (the whole scene of the ray caster: building and neighbours), the
`RayCaster`, frames with their images and prior poses, the prior's information matrix and
`JointOptions`, `FrameFitOptions` and `PriorOptions`. Out: `JointFit` (the common correction
`δ = (ω_cam, dC_world)`, applied to every prior with `geometry.pose_increments.apply_delta`, its
covariance, the mean edge support, acceptance).

Why: the GNSS bias and the boresight misalignment are constant over a building's frames and the
INS relative trajectory is precise, while a single close-range frame of a drive (vertical
building corners only, roof and ground lines out of the frame) does not determine its pose.
Stacking the edge observations of all frames in one adjustment of six parameters determines the
common correction (vertical corners seen from many positions fix the along/across-track position
and the heading; frames that see an eave, a roof line or a ground line fix height and pitch).

Two stages:

1. **coarse**: an oriented-gradient score of the projected wireframe samples, summed over frames,
   for common image shifts on a grid (`oriented_gradient`: frames downsampled and smoothed; the
   score of a sample is the image gradient component along the projected edge's normal minus the
   one across it, normalised per frame): correspondence-free and insensitive to the window rows the model does
   not contain (a plain distance transform is not), optionally with the cameras also rolled about
   their optical axes (`coarse_rolls_deg`: a flight's boresight error turns the image). The best
   local maxima are candidates; so
   are the best common world translations (searched coarse to fine: the whole range on a grid
   of at most 7 × 7 × 7 nodes on strongly smoothed frames, then finer grids around the best
   only, `_translation_levels`): at close range a position bias shifts near and far facades
   differently, which no common image shift explains;
2. **fine**: Gauss-Newton of the six common parameters (plus per-frame deviations `ε_i` with
   a-priori σ `PriorOptions.frame_sigma_*`, `priors`, eliminated by a Schur complement) from every
   frame's edge-normal distances (1-D gradient search along each projected edge sample,
   `edge_observations.normal_equations`, Tukey weights) with a shrinking search radius, the prior
   a weighted observation. Each candidate is run on a few frames; the one with the highest edge
   support is refined on all.

The visible edge samples of a frame come from its part of the scene wireframe
(`edge_observations.FrameWireframes`: the same samples at a cost that follows what the frame
sees), computed again only when its pose moved them more than `visibility_reuse_px`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import apply_delta, bounded_step, pose_delta
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.bundle_edges import edge_equations
from workers.pipeline.orientation.coarse import candidate_pose, shift_pose
from workers.pipeline.orientation.edge_observations import (
    FrameWireframes,
    edge_support,
    frame_edges,
    image_normals,
)
from workers.pipeline.orientation.features import FeatureOptions, ImageFeatures
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.oriented_gradient import downsampled_gradient, oriented_gradient_score
from workers.pipeline.orientation.priors import PriorOptions, frame_noise_information
from workers.pipeline.orientation.wireframe import EdgeOptions, VisibleWireframe, Wireframe

__all__ = ["JointFit", "JointOptions", "joint_fit"]


@dataclass(frozen=True)
class JointOptions:
    """Parameters of the joint orientation (pixels, full resolution)."""

    # at most this many frames (evenly spread) take part
    max_frames: int = 40
    # run the coarse search (common image shifts, common world translations); off when the priors
    # are already calibrated for the sequence (`calibration`): the fine stage starts at zero
    search: bool = True
    # coarse: frames downsampled by this factor, smoothed with this σ (downsampled pixels) ...
    coarse_downsample: int = 2
    coarse_sigma_px: float = 3.0
    # ... common image shifts up to this radius, on a grid of this step (full-resolution pixels)
    coarse_radius_px: float = 200.0
    coarse_step_px: float = 8.0
    # ... at most this many samples per frame and frames (evenly spread), this many
    # candidates (local maxima at least `candidate_separation_px` apart)
    coarse_samples: int = 150
    coarse_frames: int = 16
    candidates: int = 3
    candidate_separation_px: float = 40.0
    # ... also with the cameras rolled about their optical axes by these angles (degrees; each
    # non-zero roll on a grid of twice the step): a boresight error about the optical axis (a
    # flight's) turns the image, which no common shift explains
    coarse_rolls_deg: tuple[float, ...] = (0.0,)
    # ... and common world translations up to this many metres per axis on a grid of this step
    # (frames downsampled and smoothed by these), the best `translation_candidates` refined on a
    # grid of a quarter step
    translation_max_m: float = 6.0
    translation_step_m: float = 1.0
    translation_downsample: int = 8
    translation_sigma_px: float = 4.0
    translation_candidates: int = 3
    # fine: edge search radius at the start (shrinks by `radius_decay` per iteration to the
    # frame fit's minimum), iterations; candidates are compared on `verify_frames` frames with
    # `verify_iterations` iterations
    radius_start_px: float = 48.0
    radius_decay: float = 0.8
    iterations: int = 14
    verify_frames: int = 8
    verify_iterations: int = 10
    # a frame's visible samples are computed again (every 4 iterations) only when its pose moved
    # some of them more than this many pixels since they were (0: always; the sequence
    # calibration, which verifies many candidates over many frames, takes 3)
    visibility_reuse_px: float = 0.0
    # acceptance: mean edge support over the frames (share of samples with an image edge within
    # the frame fit's `support_px`), frames that must reach the frame fit's `min_support`, and
    # the largest plausible correction
    min_mean_support: float = 0.45
    min_supported_frames: int = 3
    max_correction_m: float = 9.0
    max_correction_deg: float = 8.0


@dataclass(frozen=True, eq=False)
class JointFit:
    """Result of the joint orientation.

    Attributes:
        delta: `(6,)` common correction `(ω_cam [rad], dC_world [m])` of every prior.
        covariance: `(6, 6)` of a correction common to all frames from the stacked observations
            (no per-frame deviations; a-posteriori variance factor applied, ≥ 1): how well the
            frames together determine the constant part of the error.
        support: `{frame: share of visible edge samples with an image edge within support_px}`
            at the corrected pose (frames that took part).
        mean_support: mean of `support`.
        accepted: the acceptance tests passed.
        reason: why not ("" when accepted).
        frame_delta: `{frame: (6,)}` correction `δ + ε_i` of each frame that took part.
    """

    delta: np.ndarray
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    support: dict[int, float] = field(default_factory=dict)
    mean_support: float = 0.0
    accepted: bool = False
    reason: str = ""
    frame_delta: dict[int, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class _Frame:
    index: int
    prior: Pose
    feats: ImageFeatures


def joint_fit(
    camera: Camera,
    wireframe: Wireframe | FrameWireframes,
    raycaster: RayCaster,
    frames: Sequence[int],
    images: Mapping[int, np.ndarray],
    prior: Mapping[int, Pose],
    prior_info: np.ndarray,
    options: JointOptions = JointOptions(),
    fit_options: FrameFitOptions = FrameFitOptions(),
    edge_options: EdgeOptions = EdgeOptions(),
    feature_options: FeatureOptions = FeatureOptions(),
    prior_options: PriorOptions = PriorOptions(),
) -> JointFit:
    """One common correction of the priors of `frames` (see the module docstring).

    `prior_info` `(6, 6)`: information of the prior on the common `δ` (rad⁻², m⁻²);
    `prior_options`: the a-priori σ of the per-frame deviations `ε_i`; `wireframe`: the scene's,
    or its parts per frame (`FrameWireframes`, which also keep each frame's last visibility).
    """
    if not isinstance(wireframe, FrameWireframes):
        wireframe = FrameWireframes(wireframe, camera)
    frames = list(frames)
    pick = [frames[k] for k in np.unique(np.linspace(0, len(frames) - 1, min(len(frames), options.max_frames))
                                         .round().astype(int))] if frames else []
    margin = options.coarse_radius_px + options.radius_start_px + fit_options.roi_margin_px
    found = frame_edges(camera, wireframe, raycaster, pick, images, prior, margin, fit_options, edge_options,
                        feature_options)
    data = [_Frame(i, prior[i], found[i].feats) for i in pick if i in found]
    if len(data) < options.min_supported_frames:
        return JointFit(delta=np.zeros(6), reason="too few frames see model edges")
    starts = [np.zeros(6)]
    if options.search:
        starts = _coarse_candidates(camera, wireframe, raycaster, data, images, options, fit_options,
                                    edge_options)
    verify = [data[k] for k in np.unique(np.linspace(0, len(data) - 1, min(len(data), options.verify_frames))
                                         .round().astype(int))]
    best = JointFit(delta=starts[0])
    if len(starts) > 1:
        fits = [_fine(camera, wireframe, raycaster, verify, d0, prior_info, options.verify_iterations,
                      options, fit_options, edge_options, prior_options) for d0 in starts]
        best = max(fits, key=lambda f: f.mean_support)
    fit = _fine(camera, wireframe, raycaster, data, best.delta, prior_info, options.iterations, options,
                fit_options, edge_options, prior_options, radius_start=fit_options.edge_radius_start_px / 2)
    supported = sum(s >= fit_options.min_support for s in fit.support.values())
    reason = ""
    if fit.mean_support < options.min_mean_support:
        reason = f"mean edge support {fit.mean_support:.2f} < {options.min_mean_support}"
    elif supported < options.min_supported_frames:
        reason = f"only {supported} frames with edge support"
    elif np.linalg.norm(fit.delta[3:]) > options.max_correction_m or \
            np.degrees(np.linalg.norm(fit.delta[:3])) > options.max_correction_deg:
        reason = "correction beyond the plausible range"
    return replace(fit, accepted=not reason, reason=reason)


def _peaks(score: np.ndarray, n: int, sep: int) -> list[tuple[int, ...]]:
    """Indices of the `n` best local maxima of `score` (any dimension), `sep` cells apart."""
    work = score.copy()
    out = []
    for _ in range(n):
        k = np.unravel_index(int(np.argmax(work)), work.shape)
        if not np.isfinite(work[k]):
            break
        out.append(tuple(int(x) for x in k))
        work[tuple(slice(max(x - sep, 0), x + sep + 1) for x in k)] = -np.inf
    return out


def _coarse_candidates(
    camera: Camera, wireframe: FrameWireframes, raycaster: RayCaster, data: list[_Frame],
    images: Mapping[int, np.ndarray], options: JointOptions, fo: FrameFitOptions, eo: EdgeOptions,
) -> list[np.ndarray]:
    """Common corrections `(6,)`, zero first: the best common image shifts (a rotation and a
    translation across the optical axis, `shift_pose`), then the best common world translations
    (a grid, refined on a finer one): at close range a position bias shifts near and far facades
    differently, which no common image shift explains."""
    ds = max(int(options.coarse_downsample), 1)
    wide = replace(eo, image_margin_px=-options.coarse_radius_px)
    samples = []
    pick = np.unique(np.linspace(0, len(data) - 1, min(len(data), options.coarse_frames)).round().astype(int))
    for fr in (data[k] for k in pick):
        vis = wireframe.visible(fr.index, fr.prior, raycaster, wide, options.coarse_samples)
        if len(vis.points) < fo.min_samples:
            continue
        uv, z = fr.prior.project(camera, vis.points)
        ok = np.isfinite(uv).all(axis=1) & (z > 0.5)
        if ok.sum() < fo.min_samples:
            continue
        nrm = image_normals(camera, fr.prior, vis, uv)[ok]
        samples.append((fr, vis.points[ok], uv[ok], nrm, vis.weight[ok], float(np.median(z[ok]))))
    out = [np.zeros(6)]
    if not samples:
        return out
    # common image shifts (and rolls about the optical axis)
    step = options.coarse_step_px
    r = int(np.ceil(options.coarse_radius_px / step))
    grid = np.arange(-r, r + 1) * step
    sx, sy = np.meshgrid(grid, grid)
    shifts = np.stack([sx.ravel(), sy.ravel()], axis=1)
    half = ((np.arange(len(grid)) % 2 == 0)[None, :] & (np.arange(len(grid)) % 2 == 0)[:, None]).ravel()
    rolls = np.radians(np.asarray(options.coarse_rolls_deg, dtype=np.float64).reshape(-1))
    total = np.full((len(rolls), len(shifts)), -np.inf)
    grads = {}
    for fr, X, uv, nrm, w, _ in samples:
        grads[fr.index] = downsampled_gradient(images[fr.index], ds, options.coarse_sigma_px)
        for q, roll in enumerate(rolls):
            at = np.ones(len(shifts), bool) if roll == 0 else half
            uq, nq = (uv, nrm) if roll == 0 else _rolled(camera, fr.prior, X, uv, nrm, roll)
            score = oriented_gradient_score(grads[fr.index], ds, uq[None] + shifts[at][:, None], nq, w)
            total[q, at] = np.where(np.isfinite(total[q, at]), total[q, at], 0.0) + score
    dmed = float(np.median([smp[5] for smp in samples]))
    centre = np.array([camera.cx, camera.cy])
    ref_pose = data[len(data) // 2].prior
    sep = int(np.ceil(options.candidate_separation_px / step))
    for q, iy, ix in _peaks(total.reshape(len(rolls), *sx.shape), options.candidates, sep):
        shift = np.array([grid[ix], grid[iy]])
        if shift.any() or rolls[q] != 0:
            rolled = candidate_pose(ref_pose, 0.0, float(rolls[q]))
            out.append(pose_delta(ref_pose, shift_pose(camera, rolled, centre, shift, dmed, fo)))
    # common world translations, coarse to fine (`_translation_levels`)
    centres = _translation_search(camera, samples, images, grads, options)
    out += [np.concatenate([np.zeros(3), c]) for c in centres if np.any(c)]
    return out


def _rolled(camera: Camera, pose: Pose, X: np.ndarray, uv: np.ndarray, nrm: np.ndarray,
            roll: float) -> tuple[np.ndarray, np.ndarray]:
    """Image points `(N, 2)` of the samples `X` `(N, 3)` (world) seen from `pose` rolled by `roll`
    (rad) about its optical axis, and their normals `nrm` `(N, 2)` (at `uv`, unrolled) turned by
    the image's median turn (where a sample leaves the image: where it was)."""
    uq = candidate_pose(pose, 0.0, roll).project(camera, X)[0]
    c = np.array([camera.cx, camera.cy])
    a0, a1 = uv - c, uq - c
    turn = np.arctan2(a0[:, 0] * a1[:, 1] - a0[:, 1] * a1[:, 0], np.sum(a0 * a1, axis=1))
    ok = np.isfinite(turn) & (np.linalg.norm(a0, axis=1) > 20.0)
    phi = float(np.median(turn[ok])) if ok.any() else 0.0
    cs, sn = np.cos(phi), np.sin(phi)
    nq = np.stack([cs * nrm[:, 0] - sn * nrm[:, 1], sn * nrm[:, 0] + cs * nrm[:, 1]], axis=1)
    return np.where(np.isfinite(uq), uq, uv), nq


def _translation_levels(options: JointOptions) -> list[tuple[float, float, int, float, bool]]:
    """The levels of the common world translation search: `(half width m, step m, downsampling,
    smoothing σ in downsampled pixels, whole range)`.

    The grid of `translation_step_m` up to ±`translation_max_m` is searched coarse to fine: the
    whole range on a grid of at most 7 nodes per axis (the step doubled as often as needed, the
    frames smoothed in proportion), then at every halved step down to `translation_step_m` the
    nodes within two steps of that level's best (whole-range levels, `half width` the range),
    then ±step around each of the best on the `coarse_*` frames to a quarter step. When the whole
    range fits in 7 nodes per axis (the units' narrow search) this is the plain two-level search.
    """
    step = float(options.translation_step_m)
    ds, sigma = int(options.translation_downsample), float(options.translation_sigma_px)
    coarse = step
    while options.translation_max_m / coarse > 3.0 + 1e-9:
        coarse *= 2.0
    half = float(options.translation_max_m)
    levels = [(half, coarse, ds, sigma * coarse / step, True)]
    while coarse > step + 1e-9:
        coarse /= 2.0
        levels.append((half, coarse, ds, sigma * coarse / step, True))
    levels.append((step, step / 4.0, max(int(options.coarse_downsample), 1), options.coarse_sigma_px, False))
    return levels


def _translation_search(
    camera: Camera, samples: list[tuple], images: Mapping[int, np.ndarray],
    fine_grads: dict[int, tuple[np.ndarray, float]], options: JointOptions,
) -> list[np.ndarray]:
    """The best common world translations `(3,)` (metres, best first) of the coarse search's
    samples (`_coarse_candidates`: frame, points, ..., normals, weights) by the oriented-gradient
    score summed over frames, level by level (`_translation_levels`): on the whole range the
    `translation_candidates` best local maxima two `translation_step_m` apart (twice as many
    on coarser levels, one step apart), then the best around each. `fine_grads`: the frames'
    gradients at (`coarse_downsample`, `coarse_sigma_px`)."""
    cache = {(max(int(options.coarse_downsample), 1), float(options.coarse_sigma_px)): fine_grads}
    keep, step = int(options.translation_candidates), float(options.translation_step_m)
    centres = [np.zeros(3)]
    for lev, (half, st, lds, sig, whole) in enumerate(_translation_levels(options)):
        grads = cache.get((lds, float(sig)))
        if grads is None:
            grads = cache[(lds, float(sig))] = {fr.index: downsampled_gradient(images[fr.index], lds, sig)
                                               for fr, *_ in samples}
        if not whole:  # the best around each centre
            ax = np.arange(-half, half + 1e-9, st)
            offsets = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), axis=-1).reshape(-1, 3)
            found = []
            for c0 in centres:
                tot = _translation_scores(camera, samples, grads, lds, c0 + offsets)
                found.append((float(tot.max()), c0 + offsets[int(np.argmax(tot))]))
            found.sort(key=lambda t: -t[0])
            centres = [c for _, c in found]
            continue
        # whole range: every node at the first level, later those within a coarser step of the
        # previous level's best; unevaluated nodes score -inf
        r = round(half / st)
        ax = np.arange(-r, r + 1) * st
        nodes = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), axis=-1).reshape(-1, 3)
        near = np.ones(len(nodes), bool) if lev == 0 else \
            np.any([np.all(np.abs(nodes - c) <= 2 * st + 1e-9, axis=1) for c in centres], axis=0)
        score = np.full(len(nodes), -np.inf)
        score[near] = _translation_scores(camera, samples, grads, lds, nodes[near])
        last = st <= step + 1e-9
        n, sep = (keep, 2 if last else 1) if last else (2 * keep, 1)
        shape = (len(ax),) * 3
        centres = [nodes[np.ravel_multi_index(k, shape)] for k in _peaks(score.reshape(shape), n, sep)]
    return centres


def _translation_scores(camera: Camera, samples: list[tuple], grads: dict[int, tuple[np.ndarray, float]],
                        ds: int, dcs: np.ndarray) -> np.ndarray:
    """Oriented-gradient score `(K,)` summed over the frames of `samples` for common world
    translations `dcs` `(K, 3)` (metres) of every camera, on `grads` (downsampled by `ds`)."""
    tot = np.zeros(len(dcs))
    for fr, X, _, nrm, w, _ in samples:
        R = fr.prior.R_world_from_cam
        uvk = camera.project(((X - fr.prior.center) @ R)[None] - (dcs @ R)[:, None])
        tot += oriented_gradient_score(grads[fr.index], ds, uvk, nrm, w)
    return tot


def _fine(
    camera: Camera, wireframe: FrameWireframes, raycaster: RayCaster, data: list[_Frame], delta0: np.ndarray,
    prior_info: np.ndarray, iterations: int, options: JointOptions, fo: FrameFitOptions, eo: EdgeOptions,
    prior_options: PriorOptions, radius_start: float | None = None,
) -> JointFit:
    """Gauss-Newton of the common correction `δ` and the per-frame deviations `ε_i` (information
    `F` from `prior_options`, `priors.frame_noise_information`) from `delta0` over the frames of
    `data`: frame i is corrected by `x_i = δ + ε_i`; the `ε_i` are eliminated (Schur complement)
    so every step solves 6 × 6 systems only."""
    delta = np.asarray(delta0, dtype=np.float64).copy()
    x = {fr.index: delta.copy() for fr in data}
    F = frame_noise_information(prior_options)
    r0 = options.radius_start_px if radius_start is None else radius_start
    vis: dict[int, VisibleWireframe] = {}
    Hc = prior_info.copy()
    for it in range(iterations):
        poses = {fr.index: apply_delta(fr.prior, x[fr.index]) for fr in data}
        if it % 4 == 0:
            vis = {fr.index: wireframe.visible(fr.index, poses[fr.index], raycaster, eo, fo.max_samples,
                                               options.visibility_reuse_px) for fr in data}
        R_e = max(fo.edge_radius_min_px, r0 * options.radius_decay**it)
        fo_it = replace(fo, tukey_min_px=max(fo.tukey_min_px, R_e / 3))
        Hc = prior_info.copy()
        Hs, gs = edge_equations(camera, [poses[fr.index] for fr in data], [vis[fr.index] for fr in data],
                                [fr.feats for fr in data], R_e, fo_it)  # all frames at once
        blocks = {}
        for fr, Hi, gi in zip(data, Hs, gs, strict=True):
            Hc += Hi
            blocks[fr.index] = (Hi, gi)
        S = prior_info.copy()
        b = -prior_info @ delta
        parts = {}
        for fr in data:
            Hi, gi = blocks[fr.index]
            B = np.linalg.inv(Hi + F)
            c = gi - F @ (x[fr.index] - delta)
            parts[fr.index] = (B, c)
            S += F - F @ B @ F
            b += F @ (x[fr.index] - delta) + F @ B @ c
        try:
            dd = np.linalg.solve(S, b)
        except np.linalg.LinAlgError:
            break
        dd = bounded_step(dd, 3.0, 2.0)
        delta = delta + dd
        big = 0.0
        for fr in data:
            B, c = parts[fr.index]
            dx = bounded_step(B @ (c + F @ dd), 3.0, 2.0)
            x[fr.index] = x[fr.index] + dx
            big = max(big, float(np.linalg.norm(dx[3:])))
        small = np.linalg.norm(dd[:3]) < 5e-5 and np.linalg.norm(dd[3:]) < 5e-3 and big < 5e-3
        if R_e <= fo.edge_radius_min_px + 1e-9 and small:
            break
    support: dict[int, float] = {}
    chi2, n = 0.0, 0
    for fr in data:
        pose = apply_delta(fr.prior, x[fr.index])
        got = edge_support(camera, wireframe.wireframe, raycaster, pose, fr.feats, eo, fo,
                           visible=wireframe.visible(fr.index, pose, raycaster, eo, fo.max_samples,
                                                     options.visibility_reuse_px))
        if got is None:
            continue
        support[fr.index], _, inl, _ = got
        chi2 += float(np.sum(inl**2))
        n += len(inl)
    s0 = max(1.0, chi2 / max(n - 6, 1) / fo.sigma_edge_px**2)
    try:
        cov = np.linalg.inv(Hc) * s0
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.nan)
    mean = float(np.mean(list(support.values()))) if support else 0.0
    return JointFit(delta=delta, covariance=cov, support=support, mean_support=mean, frame_delta=x)

"""The coregistered block's similarity corrected once more by the model's edges: what the facade
planes leave open (the height under walls only, a single facade's in-plane shift, its turn
about the normal and the scale) taken from the roof, eave, ground and corner lines the frames see.

Why: walls fix only horizontal shifts, two tilts and the turn about the vertical; a drive sees
walls, so the block's height stays at the GNSS/INS placement's (bench seed 1, 60 frames: every
frame 0.21 m low after the plane adjustment, 0 % of pairs below 1 px), and on a single facade
the shift along it, the turn about its normal and the scale of a short part stay at what the
noisy centres of a few frames give (bench seeds 2 and 3: placement scales 0.91 and 0.95 over 25
frames). The block's shape is right (ties to 0.1–0.4 px): one similarity moves it, observed by
the edges of every frame at once, tied to what the planes fixed by the plane fit's information.

Method: per iteration, per frame (at most `edge_frames`, evenly along the part) the visible
model-edge samples (`orientation.edge_observations`: hidden-edge removal, 1-D search along each
projected edge's normal for the strongest image edge, Tukey weights) give the normal equations
`(H_f, g_f)` of the frame's pose correction `δ_f = (ω_cam, dC_world)`; the similarity
`q = (ω, τ, σ)` about the pivot `c` (the camera centres' mean) moves frame `f` by
`ω_cam = R_fᵀ ω`, `dC = ω × (C_f − c) + τ + σ (C_f − c)`, so `Σ J_fᵀ H_f J_f` and `Σ J_fᵀ g_f`
with the prior information of `q` (the plane fit's) give the step; the search radius shrinks
from `edge_radius_start_px` to `edge_radius_min_px`. Kept when the edge support (share of
samples within `support_px` of an image edge, over the frames) rises by `edge_min_gain` or
more. Before it, a grid search of the block's shift along the directions the prior leaves open
(`coarse_shift`) brings the edges within the search radius.

In: camera, caster, scene wireframe (model CRS), poses of the part (model CRS), their images,
the pivot `(3,)`, the `(7, 7)` prior information of `q` (rad⁻², m⁻², 1), `ReconstructionOptions`.
Out: `EdgePlacement` (correction `model_from_placed`, its covariance, support before/after) or
None when too few frames see model edges.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.edge_observations import (
    FrameWireframes,
    frame_box,
    image_normals,
    normal_equations,
)
from workers.pipeline.orientation.features import (
    FeatureError,
    FeatureOptions,
    ImageFeatures,
    extract_features,
)
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.oriented_gradient import downsampled_gradient, oriented_gradient_score
from workers.pipeline.orientation.wireframe import EdgeOptions, Wireframe
from workers.pipeline.reconstruction.options import ReconstructionOptions
from workers.pipeline.reconstruction.similarity import Similarity, similarity_about


@dataclass(frozen=True, eq=False)
class EdgePlacement:
    """Result of `fit_on_edges`: `correction` (`model_from_placed`), its parameters `q` `(7,)`
    and their `covariance` `(7, 7)` (`(ω [rad], τ [m], σ)` about the pivot), the edge support
    before and after, the frames with edges, whether it is kept."""

    correction: Similarity
    q: np.ndarray
    covariance: np.ndarray
    support_before: float
    support_after: float
    frames: int
    kept: bool
    offset_before_px: float = float("nan")
    offset_after_px: float = float("nan")

    def to_dict(self) -> dict:
        """The `report.json` figures."""
        return {
            "frames": self.frames,
            "support_before": round(self.support_before, 3),
            "support_after": round(self.support_after, 3),
            "offset_before_px": round(self.offset_before_px, 3),
            "offset_after_px": round(self.offset_after_px, 3),
            "rotation_deg": [round(float(np.degrees(x)), 3) for x in self.q[:3]],
            "shift_m": [round(float(x), 3) for x in self.q[3:6]],
            "scale": round(self.correction.scale, 4),
            "shift_sigma_m": round(self.shift_sigma_m, 3),
            "kept": self.kept,
        }

    @property
    def shift_sigma_m(self) -> float:
        """σ (m) of the least determined shift direction (largest eigenvalue of the shift block
        of `covariance`): what edges and planes together leave open."""
        return float(np.sqrt(max(np.linalg.eigvalsh(self.covariance[3:6, 3:6])[-1], 0.0)))


def _frame_jacobian(pose: Pose, pivot: np.ndarray) -> np.ndarray:
    """`(6, 7)`: `δ_f = (ω_cam, dC_world)` of frame `pose` per `q = (ω, τ, σ)` about `pivot`."""
    d = pose.center - pivot
    J = np.zeros((6, 7))
    J[:3, :3] = pose.R_world_from_cam.T
    J[3:, :3] = -np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    J[3:, 3:6] = np.eye(3)
    J[3:, 6] = d
    return J


def fit_on_edges(
    camera: Camera,
    caster: RayCaster,
    wireframe: Wireframe,
    poses: Mapping[int, Pose],
    images: Mapping[int, np.ndarray],
    pivot: np.ndarray,
    prior_info: np.ndarray,
    options: ReconstructionOptions,
) -> EdgePlacement | None:
    """Fit the similarity correction of the block `poses` to the model edges (module docstring)."""
    fo = FrameFitOptions()
    eo = EdgeOptions()
    frames = sorted(poses)
    if len(frames) > options.edge_frames:
        frames = [frames[int(k)] for k in np.linspace(0, len(frames) - 1, options.edge_frames).round()]
    wfs = FrameWireframes(wireframe, camera)
    feats: dict[int, ImageFeatures] = {}
    for f in frames:
        vis = wfs.visible(f, poses[f], caster, eo, fo.max_samples)
        if len(vis.points) < fo.min_samples:
            continue
        roi = frame_box(camera, poses[f], vis, options.edge_radius_start_px + 8)
        if roi is None:
            continue
        try:
            feats[f] = extract_features(images[f], FeatureOptions(), roi, points=False)
        except FeatureError:
            continue
    if len(feats) < options.edge_min_frames:
        return None
    c = np.asarray(pivot, dtype=np.float64)
    q = np.zeros(7)
    support0, cost0 = _support(camera, caster, wfs, eo, fo, poses, feats, Similarity.identity())
    q[3:6] = coarse_shift(camera, caster, wfs, eo, fo, poses, images, sorted(feats), prior_info, options)
    radius = options.edge_radius_start_px
    N = prior_info.copy()
    for _ in range(options.edge_iterations):
        S = similarity_about(q, c)
        N = prior_info.copy()
        b = -prior_info @ q
        for f, ft in feats.items():
            p = S.pose(poses[f])
            vis = wfs.visible(f, p, caster, eo, fo.max_samples, reuse_px=0.5)
            if len(vis.points) < fo.min_samples:
                continue
            H, g, *_ = normal_equations(camera, p, vis, ft, np.zeros((0, 2)), radius, fo.point_radius_min_px,
                                        p, np.zeros((6, 6)), fo)
            J = _frame_jacobian(p, c)
            N += J.T @ H @ J
            b += J.T @ g
        try:
            step = np.linalg.solve(N, b)
        except np.linalg.LinAlgError:
            return None
        q = q + step
        radius = max(fo.edge_radius_min_px, radius * options.edge_radius_decay)
    S = similarity_about(q, c)
    support1, cost1 = _support(camera, caster, wfs, eo, fo, poses, feats, S)
    better = support1 >= support0 + options.edge_min_gain or (
        support1 >= support0 - options.edge_max_support_loss
        and cost1 <= cost0 * (1.0 - options.edge_min_offset_gain)
    )
    kept = bool(np.all(np.isfinite(q)) and better)
    return EdgePlacement(S, q, np.linalg.inv(N), support0, support1, len(feats), kept, cost0, cost1)


def coarse_shift(
    camera: Camera,
    caster: RayCaster,
    wfs: FrameWireframes,
    eo: EdgeOptions,
    fo: FrameFitOptions,
    poses: Mapping[int, Pose],
    images: Mapping[int, np.ndarray],
    frames: list[int],
    prior_info: np.ndarray,
    options: ReconstructionOptions,
) -> np.ndarray:
    """The block's shift `(3,)` (metres, model CRS) that best lays the visible model edges on
    image edges of their direction (`oriented_gradient_score`, summed over `frames`), searched on
    a grid along the shift directions the prior leaves open (marginal σ beyond
    `edge_coarse_min_sigma_m`; ±3σ, at most ±`edge_coarse_max_m`, steps of `edge_coarse_step_m`
    or coarser, at most `edge_coarse_max_candidates` shifts):
    the Gauss-Newton fit's search radius does not reach a GNSS/INS height error of decimetres at
    close range (0.35 m at 10 m: 27 px). Zero when no direction is open or no candidate scores
    `edge_coarse_min_gain` above the start."""
    w, V = np.linalg.eigh(np.linalg.inv(prior_info)[3:6, 3:6])
    open_ = w > options.edge_coarse_min_sigma_m**2
    if not open_.any():
        return np.zeros(3)
    axes = []
    reach = np.minimum(3.0 * np.sqrt(w[open_]), options.edge_coarse_max_m)
    # at most `edge_coarse_max_candidates` shifts: coarser steps when three directions are open
    per_axis = options.edge_coarse_max_candidates ** (1.0 / len(reach))
    step = max(options.edge_coarse_step_m, float(2.0 * reach.max() / max(per_axis - 1.0, 1.0)))
    for r, v in zip(reach, V[:, open_].T, strict=True):
        steps = np.arange(-r, r + 1e-9, step)
        axes.append(steps[:, None] * v[None, :])
    shifts = np.zeros((1, 3))
    for a in axes:  # every combination of the open directions' steps
        shifts = (shifts[:, None, :] + a[None, :, :]).reshape(-1, 3)
    total = np.zeros(len(shifts))
    ds = options.edge_coarse_downsample
    for f in frames:
        vis = wfs.visible(f, poses[f], caster, eo, fo.max_samples)
        if len(vis.points) < fo.min_samples:
            continue
        uv, _ = poses[f].project(camera, vis.points)
        nrm = image_normals(camera, poses[f], vis, uv)
        # the block shifted by τ: the model seen from C + τ, i.e. the samples moved by −τ
        cand, _ = poses[f].project(camera, (vis.points[None, :, :] - shifts[:, None, :]).reshape(-1, 3))
        grad = downsampled_gradient(images[f], ds, options.edge_coarse_blur)
        total += oriented_gradient_score(grad, ds, cand.reshape(len(shifts), -1, 2), nrm, vis.weight)
    k0 = int(np.argmin(np.linalg.norm(shifts, axis=1)))
    best = int(np.argmax(total))
    if total[best] - total[k0] < options.edge_coarse_min_gain * max(len(frames), 1):
        return np.zeros(3)
    return shifts[best]


def _support(
    camera: Camera,
    caster: RayCaster,
    wfs: FrameWireframes,
    eo: EdgeOptions,
    fo: FrameFitOptions,
    poses: Mapping[int, Pose],
    feats: Mapping[int, ImageFeatures],
    S: Similarity,
) -> tuple[float, float]:
    """(support: weighted share of the frames' visible edge samples within `support_px` of an
    image edge, at the final search radius; offset: the weighted mean distance (px, at most
    that radius) of the samples that found an edge) with the poses moved by `S`. The support
    counts samples within 1.5 px and misses sub-pixel moves the offset sees (bench seed 1,
    homogeneous facades: a block 0.04 m low, support 0.766 -> 0.759 when corrected, offset
    0.33 -> 0.29 px)."""
    hit = tot = cost = hits = 0.0
    for f, ft in feats.items():
        p = S.pose(poses[f])
        vis = wfs.visible(f, p, caster, eo, fo.max_samples)
        if len(vis.points) < fo.min_samples:
            continue
        _, _, _, off, found, *_ = normal_equations(
            camera, p, vis, ft, np.zeros((0, 2)), fo.edge_radius_min_px, fo.point_radius_min_px, p,
            np.zeros((6, 6)), fo,
        )
        hit += float(np.sum(vis.weight * (found & (np.abs(off) <= fo.support_px))))
        r = fo.edge_radius_min_px
        w = vis.weight * found
        cost += float(np.sum(w * np.minimum(np.abs(np.where(found, off, 0.0)), r)))
        tot += float(np.sum(vis.weight))
        hits += float(np.sum(w))
    return (hit / tot if tot > 0 else 0.0), (cost / hits if hits > 0 else float("inf"))

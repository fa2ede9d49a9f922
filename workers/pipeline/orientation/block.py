"""Block orientation of a building's frames: feature tracks and a bundle adjustment with the model.

In: `Camera`, the building's wireframe and the wireframe of its scene (building and neighbours),
the `RayCaster` of the scene, the building's frames (recording order) with their images, prior
poses (GNSS/INS, calibrated when a sequence calibration was accepted) and start poses, the
prior's information matrix, options. Out: `{frame: RefinedPose}`.

Why: a close-range drive frame rarely fixes its own pose (one vertical corner, no eave, no
ground line) while its GNSS/INS position is decimetres off from frame to frame. Points tracked
over the facades (`tracks`) tie the frames together; the bundle adjustment (`bundle`) places the
tied block in the model with the edges of the scene wireframe, the points' model planes and the
priors (a common error of the block plus each frame's own noise).

The common error's prior is the prior's accuracy floored at `common_sigma_floor_*`: a sequence
calibration gives a good start, but along one street a pan of degrees and a lateral offset are
nearly interchangeable for it (one 2.4 s drive calibrated to 4° of pan with 1.3 m of offset,
accepted with a claimed σ of 0.2°), and a tight common prior would hold the block there. When
the ties of the adjusted block fit worse than their σ, the tracks are made again from its poses
(their predictions and plane-induced warps came from poses too far off) and the block is
adjusted once more.

Acceptance: the block must see model edges somewhere and its correction must be plausible;
otherwise every frame keeps its prior. Around each frame, the frames within `anchor_frames` that
see model edges must support the refined poses (`anchoring`: mean edge support ≥
`min_mean_support`, above the null support of samples moved off their edges by
`min_support_gain`); a frame with no such frames around it relies on the ties and its covariance.
Then a frame is `"refined"` when it is observed (at least `min_ties` tie points, or at least
`fit.min_edges` matched model edges with an edge support of `fit.min_support`) with residuals
below `fit.max_rms_px`, and the predicted
uncertainty of the building's vertices in it (the frame's covariance from the adjustment) is at
most `max_sigma_px`; else it keeps its prior with status `"prior"`.

`rms_px` is the RMS of the frame's inlier tie residuals and edge offsets; `matches` counts its
inlier tie points plus its matched model edges.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import pose_delta, project_jacobian
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.block_recheck import RecheckOptions, recheck_block
from workers.pipeline.orientation.bundle import BundleOptions, BundleResult, bundle_adjust
from workers.pipeline.orientation.edge_observations import FrameWireframes, edge_support, frame_edges
from workers.pipeline.orientation.features import FeatureOptions
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.priors import PriorOptions, frame_noise_covariance
from workers.pipeline.orientation.tracks import TrackerFrames, TrackOptions, Tracks, track_sequence
from workers.pipeline.orientation.wireframe import EdgeOptions, Wireframe
from workers.pipeline.results import RefinedPose

__all__ = [
    "BlockOptions",
    "UnitSequence",
    "accept_frames",
    "adjust_block",
    "anchoring",
    "block_reason",
    "refine_block",
    "refine_from_sequence",
    "sigma_px",
]


@dataclass(frozen=True)
class BlockOptions:
    """Parameters of the block orientation (pixels, metres, degrees)."""

    tracks: TrackOptions = field(default_factory=TrackOptions)
    bundle: BundleOptions = field(default_factory=BundleOptions)
    # floors of the common error's prior σ (see the module docstring)
    common_sigma_floor_m: float = 1.0
    common_sigma_floor_deg: float = 2.0
    # track again from the adjusted poses when the ties fit clearly worse than their σ (σ0 of
    # unit weight above this): tracked from poses too far off, the warps were wrong (σ0 0.9 on a
    # drive calibrated 4° off, 0.3–0.5 otherwise)
    retrack_sigma0: float = 0.8
    # the block found the model around a frame (`anchoring`): mean edge support of the frames
    # within this many frames that see model edges, and its gain over their null support
    anchor_frames: int = 10
    min_mean_support: float = 0.3
    min_support_gain: float = 0.15
    # a building unit's check of the sequence's poses (`refine_from_sequence`) is a contradiction
    # test, not a search for the model: the sequence acceptance already found the model with every
    # building's edges, so the building's own edges need only stand clearly above their null
    # support (`min_support_gain`) with this lower floor of mean support (a building leaving the
    # view: 0.29-0.34 support against 0.01 null at poses good to 0.07 px kept their priors at 0.3;
    # at 0.1 the 300-frame NRW drive's pairs < 1 px rose from 0.930 to 0.956, the 60-frame
    # flight's from 0.994 to 0.999; 0.0 gave the same as 0.1, 0.2 gave 0.951)
    confirm_min_mean_support: float = 0.1
    # largest plausible common correction of the block
    max_correction_m: float = 9.0
    max_correction_deg: float = 8.0
    # a frame is refined with at least this many inlier tie points (or the frame fit's matched
    # edges and edge support) and a predicted uncertainty of the building's vertices of at most
    # this (px)
    min_ties: int = 8
    max_sigma_px: float = 1.5
    # a building unit checks the sequence's pose of a frame with the building's own edges where at
    # least this many of them are matched at that pose (`refine_from_sequence`)
    min_matched_edges: int = 1
    # frames whose model edges contradict the adjusted pose (a short wrong track bent them):
    # their ties dropped, restarted from the neighbours' correction, adjusted again (`block_recheck`)
    recheck: RecheckOptions = field(default_factory=RecheckOptions)


@dataclass(frozen=True, eq=False)
class UnitSequence:
    """What a building unit takes from the sequence orientation (`sequence.orient_sequence`) for its
    frames.

    Attributes:
        poses: `{frame: Pose}` refined by the sequence orientation (the frames it oriented).
        covariance: `{frame: (6, 6)}` of `(ω_cam [rad], dC_world [m])` of those poses (each
            frame's marginal covariance from its block).
        ties: `{frame: inlier tie observations}` and `tie_rms_px` `{frame: their RMS}` there.
    """

    poses: dict[int, Pose]
    covariance: dict[int, np.ndarray]
    ties: dict[int, int] = field(default_factory=dict)
    tie_rms_px: dict[int, float] = field(default_factory=dict)


def sigma_px(camera: Camera, pose: Pose, X: np.ndarray, cov: np.ndarray) -> float:
    """RMS predicted reprojection uncertainty (px) of points `X` `(N, 3)` in the frame for a pose
    with covariance `cov` `(6, 6)` of `(ω_cam, dC_world)`; inf when none is in the frame."""
    uv, z, J = project_jacobian(camera, pose, X)
    inside = (z > 0.5) & camera.in_image(uv)
    if not inside.any() or not np.all(np.isfinite(cov)):
        return float("inf")
    return float(np.sqrt(np.mean(np.einsum("nki,ij,nkj->n", J[inside], cov, J[inside]))))


def adjust_block(
    camera: Camera,
    scene_wf: Wireframe,
    raycaster: RayCaster,
    frames: Sequence[int],
    images: Mapping[int, np.ndarray],
    prior: Mapping[int, Pose],
    start: Mapping[int, Pose],
    prior_info: np.ndarray,
    options: BlockOptions = BlockOptions(),
    fit_options: FrameFitOptions = FrameFitOptions(),
    edge_options: EdgeOptions = EdgeOptions(),
    feature_options: FeatureOptions = FeatureOptions(),
    prior_options: PriorOptions = PriorOptions(),
) -> tuple[BundleResult, Tracks, list[int]]:
    """Tracks through `frames` and the bundle adjustment of the block against `scene_wf`, tracked
    and adjusted again when the ties fit worse than their σ (`retrack_sigma0`; module docstring),
    then the frames whose model edges contradict their adjusted pose rechecked
    (`block_recheck.recheck_block`: their ties dropped, adjusted again from their neighbours'
    correction). Returns the adjustment, its tracks (the rechecked frames' ties left out) and the
    frames rechecked (empty when the first adjustment stood).

    Args:
        camera: interior orientation.
        scene_wf: the wireframe whose edges are observed.
        raycaster: the scene (hidden-edge removal, track points).
        frames: at least 2 frame indices in recording order.
        images: `(H, W)` float32 physical values per frame.
        prior: prior pose per frame (world = model CRS).
        start: start pose per frame (the prior, or the prior with a common correction).
        prior_info: `(6, 6)` information of the prior's common error on `δ` (rad⁻², m⁻²),
            floored at the common σ floors.
        options, fit_options, edge_options, feature_options: parameters.
        prior_options: the per-frame deviation from the block's common error, the null shift of
            the edge support.
    """
    frames = list(frames)
    white = np.linalg.inv(frame_noise_covariance(prior_options.frame_sigma_deg, prior_options.frame_sigma_m))
    frame_info = dict.fromkeys(frames, white)
    common_info = _floored(prior_info, options)
    poses = dict(start)
    # made once for both passes: the tracker's inputs, the frames' parts of the wireframe
    prepared = TrackerFrames(frames, images, options.tracks)
    frame_wf = FrameWireframes(scene_wf, camera)
    for k in range(2):
        tracks = track_sequence(camera, frames, images, poses, raycaster, options.tracks, prepared)
        res = bundle_adjust(
            camera,
            frames,
            images,
            poses,
            prior,
            frame_info,
            common_info,
            tracks,
            frame_wf,
            raycaster,
            options.bundle,
            fit_options,
            edge_options,
            feature_options,
            prior_options,
            options.retrack_sigma0 if k == 0 else float("inf"),  # a first pass tracked again: no figures
        )
        poses = res.poses
        if res.sigma0 <= options.retrack_sigma0:
            break

    def readjust(begin: Mapping[int, Pose], kept: Tracks) -> BundleResult:
        return bundle_adjust(camera, frames, images, begin, prior, frame_info, common_info, kept, frame_wf,
                             raycaster, options.bundle, fit_options, edge_options, feature_options,
                             prior_options)  # fmt: skip

    return recheck_block(frames, prior, res, tracks, readjust, options.recheck)


def refine_block(
    camera: Camera,
    building_wf: Wireframe,
    scene_wf: Wireframe,
    raycaster: RayCaster,
    frames: Sequence[int],
    images: Mapping[int, np.ndarray],
    prior: Mapping[int, Pose],
    start: Mapping[int, Pose],
    prior_info: np.ndarray,
    options: BlockOptions = BlockOptions(),
    fit_options: FrameFitOptions = FrameFitOptions(),
    edge_options: EdgeOptions = EdgeOptions(),
    feature_options: FeatureOptions = FeatureOptions(),
    prior_options: PriorOptions = PriorOptions(),
) -> tuple[dict[int, RefinedPose], BundleResult | None, str]:
    """Orient the building's `frames` as one block (`adjust_block`, then the acceptance of the
    module docstring); `building_wf` gives the vertices of the predicted uncertainty.

    Returns:
        (`{frame: RefinedPose}`, the adjustment or None, why the block was rejected or "").
    """
    frames = list(frames)
    if len(frames) < 2:
        keep = {i: RefinedPose(i, prior[i], "prior", float("nan"), 0) for i in frames}
        return keep, None, "fewer than 2 frames"
    res, _, _ = adjust_block(
        camera,
        scene_wf,
        raycaster,
        frames,
        images,
        prior,
        start,
        prior_info,
        options,
        fit_options,
        edge_options,
        feature_options,
        prior_options,
    )
    reason = block_reason(frames, prior, res, options)
    if reason:
        return {i: RefinedPose(i, prior[i], "prior", _rms(res, i), 0) for i in frames}, res, reason
    anchor = anchoring(frames, res.edge_support, res.null_support, options)
    eligible = {i for i, a in anchor.items() if a is not False}
    if not any(anchor.values()):
        return (
            {i: RefinedPose(i, prior[i], "prior", _rms(res, i), 0) for i in frames},
            res,
            "the block found the model nowhere (edge support)",
        )
    return (
        accept_frames(
            camera, building_wf.vertices, frames, prior, res, options, fit_options, eligible=eligible
        ),
        res,
        "",
    )


def refine_from_sequence(
    camera: Camera,
    building_wf: Wireframe,
    raycaster: RayCaster,
    frames: Sequence[int],
    images: Mapping[int, np.ndarray],
    prior: Mapping[int, Pose],
    sequence: UnitSequence,
    options: BlockOptions = BlockOptions(),
    fit_options: FrameFitOptions = FrameFitOptions(),
    edge_options: EdgeOptions = EdgeOptions(),
    feature_options: FeatureOptions = FeatureOptions(),
    prior_options: PriorOptions = PriorOptions(),
) -> tuple[dict[int, RefinedPose], str]:
    """The building's frames after the sequence orientation (`sequence.orient_sequence`): each takes its
    sequence pose, checked against the BUILDING's own edges (`anchoring` of their edge support at
    those poses with the floor `confirm_min_mean_support`, in the frames where any of them is
    matched: where they contradict the pose, the frame keeps its prior) and accepted when the
    pose's marginal covariance from the sequence, projected onto the building's vertices, is at
    most `max_sigma_px` (`"refined"`); else `"prior"`. The sequence adjustment already used every
    building's edges and the tie points: adjusting again with them would count them twice (and
    independent priors from correlated marginal covariances would count the block's common
    uncertainty once per frame).

    Returns:
        (`{frame: RefinedPose}`, "" or why the building's edges reject the sequence's poses
        everywhere: the caller then orients the building on its own).
    """
    frames = list(frames)
    oriented = [i for i in frames if i in sequence.covariance and np.all(np.isfinite(sequence.covariance[i]))]
    margin = fit_options.edge_radius_min_px + fit_options.roi_margin_px
    edges = frame_edges(
        camera,
        building_wf,
        raycaster,
        oriented,
        images,
        sequence.poses,
        margin,
        fit_options,
        edge_options,
        feature_options,
    )
    support: dict[int, float] = {}
    null: dict[int, float] = {}
    matched: dict[int, int] = {}
    rms: dict[int, float] = {}
    for i, ed in edges.items():
        got = edge_support(
            camera,
            building_wf,
            raycaster,
            sequence.poses[i],
            ed.feats,
            edge_options,
            fit_options,
            prior_options.null_shift_px,
            visible=ed.vis,  # `frame_edges` saw the building from this very pose
        )
        if got is not None:
            support[i], null[i], off, matched[i] = got
            rms[i] = float(np.sqrt(np.mean(off**2))) if len(off) else float("nan")
    # a frame where none of the building's edges is matched shows nothing of them to check (the
    # 300-frame NRW drive: support 0.1 at the TRUE poses of a building's 21 frames, which the
    # sequence had to 0.05 px; the check kept their priors, 5 px off)
    seen = {i for i in support if matched[i] >= options.min_matched_edges}
    anchor = anchoring(frames, {i: support[i] for i in seen}, {i: null[i] for i in seen}, options,
                       options.confirm_min_mean_support)
    if seen and not any(anchor.values()):
        keep = {i: RefinedPose(i, prior[i], "prior", float("nan"), 0) for i in frames}
        return keep, "the building's edges confirm the sequence orientation nowhere"
    out = {}
    for i in frames:
        pose = sequence.poses.get(i)
        ties = sequence.ties.get(i, 0)
        n = ties + matched.get(i, 0)
        r = _combined_rms(ties, sequence.tie_rms_px.get(i, float("nan")), rms.get(i, float("nan")))
        if (
            pose is None
            or i not in oriented
            or anchor.get(i) is False
            or sigma_px(camera, pose, building_wf.vertices, sequence.covariance[i]) > options.max_sigma_px
        ):
            out[i] = RefinedPose(i, prior[i], "prior", r, n)
        else:
            out[i] = RefinedPose(i, pose, "refined", r, n)
    return out, ""


def accept_frames(
    camera: Camera,
    X: np.ndarray,
    frames: Sequence[int],
    prior: Mapping[int, Pose],
    res: BundleResult,
    options: BlockOptions,
    fit_options: FrameFitOptions,
    eligible: set[int] | None = None,
) -> dict[int, RefinedPose]:
    """Per-frame acceptance of an adjusted block (module docstring): `"refined"` with the adjusted
    pose when the frame is `eligible` (None: all; where the block found the model, `anchoring`)
    and observed (tie points or edges) with residuals below `fit.max_rms_px`, and the predicted
    uncertainty of the points `X` `(N, 3)` (the building's vertices) in it is at most
    `max_sigma_px`; else `"prior"`."""
    out = {}
    fo = fit_options
    for i in frames:
        if eligible is not None and i not in eligible:
            matches = res.ties[i] + res.matched_edges.get(i, 0)
            out[i] = RefinedPose(i, prior[i], "prior", _rms(res, i), matches)
            continue
        pose = res.poses[i]
        ties, edges = res.ties[i], res.matched_edges.get(i, 0)
        rms = _rms(res, i)
        seen = ties >= options.min_ties or (
            edges >= fo.min_edges and res.edge_support.get(i, 0.0) >= fo.min_support
        )
        ok_rms = not np.isfinite(rms) or rms <= fo.max_rms_px
        if seen and ok_rms and sigma_px(camera, pose, X, res.covariance[i]) <= options.max_sigma_px:
            out[i] = RefinedPose(i, pose, "refined", rms, ties + edges)
        else:
            out[i] = RefinedPose(i, prior[i], "prior", rms, ties + edges)
    return out


def _floored(info: np.ndarray, options: BlockOptions) -> np.ndarray:
    """`info` `(6, 6)` with its standard deviations floored at the common σ floors (rotation
    block in rad, position block in m; the correlations are dropped where a floor applies)."""
    cov = np.linalg.inv(info)
    sd = np.sqrt(np.diag(cov))
    floor = np.r_[[np.radians(options.common_sigma_floor_deg)] * 3, [options.common_sigma_floor_m] * 3]
    if np.all(sd >= floor):
        return info
    return np.diag(1.0 / np.maximum(sd, floor) ** 2)


def _rms(res: BundleResult, i: int) -> float:
    """RMS (px) of frame i's inlier tie residuals and edge offsets together."""
    return _combined_rms(res.ties[i], res.tie_rms_px[i], res.edge_rms_px.get(i, float("nan")))


def block_reason(
    frames: Sequence[int],
    prior: Mapping[int, Pose],
    res: BundleResult,
    options: BlockOptions,
    need_edges: bool = True,
) -> str:
    """Why the block as a whole is not trusted ("" when it is): no frame sees model edges (with
    `need_edges`), or the median correction is beyond the plausible range. Where the block found
    the model is decided frame by frame (`anchoring`; the sequence orientation:
    `sequence_acceptance`)."""
    if need_edges and not res.edge_support:
        return "no frame of the block sees model edges"
    d = np.array([pose_delta(prior[i], res.poses[i]) for i in frames])
    med = np.median(d, axis=0)
    if (
        np.linalg.norm(med[3:]) > options.max_correction_m
        or np.degrees(np.linalg.norm(med[:3])) > options.max_correction_deg
    ):
        return "correction beyond the plausible range"
    return ""


def anchoring(
    frames: Sequence[int], support: Mapping[int, float], null: Mapping[int, float], options: BlockOptions,
    min_mean_support: float | None = None,
) -> dict[int, bool | None]:
    """Whether the block found the model around each frame: among the frames within
    `anchor_frames` of it (frame indices: frames of another pass of a loop are not its
    neighbours) that see model edges (`support`, `null`: edge support and null support per
    frame), the mean edge support reaches `min_mean_support` (the option's, unless given) and
    exceeds their mean null support (samples moved off the edges) by `min_support_gain`. None
    when no frame around it sees model edges (a long blank facade: the ties carry the
    orientation from further away, and its covariance says how well).

    A 120-frame block of a drive down a street of tall blocks sees model edges in a third of its
    frames; one test over the whole block would reject the part that found the model with the part
    that had nothing to find."""
    idx = np.asarray(frames, dtype=np.int64)
    sup = np.array([support.get(f, np.nan) for f in frames])
    gain = sup - np.array([null.get(f, np.nan) for f in frames])
    out: dict[int, bool | None] = {}
    K = options.anchor_frames
    floor = options.min_mean_support if min_mean_support is None else min_mean_support
    for f in frames:
        near = (np.abs(idx - f) <= K) & np.isfinite(sup)
        if not near.any():
            out[f] = None
            continue
        out[f] = bool(
            np.mean(sup[near]) >= floor and np.mean(gain[near]) >= options.min_support_gain
        )
    return out


def _combined_rms(ties: int, tie_rms: float, edge_rms: float) -> float:
    """RMS (px) of a frame's inlier tie residuals (`ties` of RMS `tie_rms`) and edge offsets
    (RMS `edge_rms`, weighted as ten observations)."""
    parts, n = 0.0, 0
    if ties and np.isfinite(tie_rms):
        parts += tie_rms**2 * ties * 2
        n += 2 * ties
    if np.isfinite(edge_rms):
        parts += edge_rms**2 * 10
        n += 10
    return float(np.sqrt(parts / n)) if n else float("nan")

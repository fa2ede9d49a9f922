"""Whether an adjusted block of the sequence orientation is confirmed, frame by frame.

In: the block's frames (recording order), their prior poses (world = model CRS), the
adjustment (`bundle.BundleResult`: poses, edge support, tie inliers, adjusted points), its
tracks (`tracks.Tracks`, with the model plane of every point), the camera, the per-frame
information of the priors, options. Out: `Confirmation`: per frame whether it takes the adjusted
pose, why the block is rejected ("" when it is not), and the figures of `report.json`.

The rule (`docs/results-format.md`, `sequence_orientation`):

1. Edges where they exist: among the frames within `BlockOptions.anchor_frames` of a frame
   that see model edges, the mean edge support must reach `min_mean_support` and exceed their
   null support by `min_support_gain` (`block.anchoring`). A frame whose neighbours' edges
   contradict the adjusted poses keeps its prior; a block whose edges confirm it nowhere is
   rejected (edges seen but not confirming: the block is not confirmed).
2. Planes and tracks where no edge is seen around a frame (a long blank facade, a close-range
   sequence of one facade whose outline stays outside the frames): the frame is confirmed when
   it has at least `min_ties` inlier tie observations, spread over the image (their standard
   deviation along u and along v at least `min_spread` of the image's width and height: points
   on one line leave a rotation open), its tracked points lie on their model planes after the
   adjustment (RMS distance at most `max_plane_rms_m`, at most `max_off_plane_share` of them
   beyond the Tukey constant of the bundle's plane re-weighting), and the ties fit
   (σ0 of the block at most `max_sigma0`). A block where no frame sees edges is rejected when
   fewer than `min_confirmed_share` of its frames are confirmed so.
3. Consistency with the priors, every frame: the adjusted pose's deviation from the block's
   common correction (the median correction of the block's frames), weighed with the per-frame
   information of the priors, must not exceed `max_frame_chi2` (χ² with 6 degrees of freedom;
   22.5 is its 99.9 % quantile) for a frame that only the planes and tracks confirm, and
   `max_frame_chi2_edges` for a frame whose neighbours' edges confirm the block (the model of a
   common error plus white noise is approximate: in the turns of a calibrated drive a residual
   time delay leaves degrees of heading, χ² up to 35, on poses the edges confirm to a pixel). A
   block torn apart by wrong ties, or shifted by one window of a regular facade in part of its
   frames, moves frames by many times their σ; those frames keep their priors, and when more
   than `max_inconsistent_share` of the frames do, the block is rejected.

4. Determined, every frame: the adjusted pose's covariance projected onto the frame's own tie
   points (`block.sigma_px`, RMS px) must be at most `max_sigma_px` (a frame without tie points
   is not tested here). The bound is loose (10 px): it catches poses the adjustment leaves open,
   not the fine acceptance, which the building units make with their own 1.5 px on the
   building's vertices (a calibrated drive's well-oriented windows predict about 2 px). Edge
   support is measured on the edges visible at the adjusted pose: a walk along one facade
   placed 2.2 m too high shows only the wall's vertical ends, which fit at any height, while
   the ground line that would contradict it projects below the frames; the ties cannot fix
   that height either, and the covariance says so (σ 6 m, 470 px).

What rule 2 confirms is the block's shape and its distance and tilt to the planes; sliding along
a single plane (and turning about its normal) is left to the priors and edges, and rule 4 keeps
the frames where they leave the pose open (the building units check the covariance again,
projected onto the building: `block.refine_from_sequence`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import pose_delta
from workers.pipeline.orientation.block import BlockOptions, anchoring, sigma_px
from workers.pipeline.orientation.bundle import BundleOptions, BundleResult
from workers.pipeline.orientation.tracks import Tracks

__all__ = ["ConfirmOptions", "Confirmation", "confirm_block"]


@dataclass(frozen=True)
class ConfirmOptions:
    """Parameters of the confirmation without edges and of the consistency with the priors."""

    # rule 2: tie observations of a frame and their spread (share of the image's width, height)
    min_ties: int = 8
    min_spread: float = 0.08
    # rule 2: the tracked points' distances from their model planes (metres), the share beyond
    # the bundle's Tukey constant, the ties' σ0, the share of frames a block needs
    max_plane_rms_m: float = 0.1
    max_off_plane_share: float = 0.2
    max_sigma0: float = 1.5
    min_confirmed_share: float = 0.5
    # rule 3: χ² (6 degrees of freedom) of a frame's deviation from the common correction,
    # without and with edges confirming it around, and the share of frames beyond it that
    # rejects the block
    max_frame_chi2: float = 22.5
    max_frame_chi2_edges: float = 100.0
    max_inconsistent_share: float = 0.25
    # rule 4: the pose's covariance projected onto the frame's tie points, RMS px
    max_sigma_px: float = 10.0


@dataclass(frozen=True, eq=False)
class Confirmation:
    """Result of `confirm_block`.

    Attributes:
        reason: why the block is rejected ("" when it is accepted).
        taken: `{frame: bool}`: the frame takes the adjusted pose (False: it keeps its prior).
        anchor: `{frame: True | False | None}` of rule 1 (`block.anchoring`; None: no edges around).
        by_planes: frames confirmed by rule 2.
        inconsistent: frames beyond rule 3.
        undetermined: frames beyond rule 4.
        plane_rms_m: RMS distance of the block's tracked points from their planes (NaN: none).
    """

    reason: str
    taken: dict[int, bool]
    anchor: dict[int, bool | None]
    by_planes: list[int] = field(default_factory=list)
    inconsistent: list[int] = field(default_factory=list)
    undetermined: list[int] = field(default_factory=list)
    plane_rms_m: float = float("nan")


def frame_chi2(
    frames: Sequence[int], prior: Mapping[int, Pose], res: BundleResult, frame_info: np.ndarray
) -> dict[int, float]:
    """χ² `{frame: float}` of each frame's correction `δ_f = (ω_cam, dC_world)` from its prior
    minus the block's median correction, with the per-frame information `frame_info` `(6, 6)`."""
    d = np.array([pose_delta(prior[f], res.poses[f]) for f in frames])
    rho = d - np.median(d, axis=0)
    return {f: float(r @ frame_info @ r) for f, r in zip(frames, rho, strict=True)}


def plane_figures(
    tracks: Tracks, points: np.ndarray, inlier: np.ndarray, tukey_m: float
) -> tuple[np.ndarray, float, float]:
    """Per track with inlier observations (`inlier` `(M,)` per observation of `tracks`): whether
    its adjusted point (`points` `(T, 3)`) is on its model plane (`(T,)` bool, within `tukey_m`
    metres), the RMS plane distance of those within (m) and the share beyond."""
    used = np.zeros(tracks.n_tracks, bool)
    used[tracks.track[inlier]] = True
    dist = np.abs(np.asarray(tracks.offset) - np.sum(tracks.normal * points, axis=1))
    on = dist <= tukey_m
    if not used.any():
        return on & used, float("nan"), float("nan")
    within = used & on
    rms = float(np.sqrt(np.mean(dist[within] ** 2))) if within.any() else float("nan")
    return on & used, rms, float(np.mean(~on[used]))


def confirm_block(
    camera: Camera,
    frames: Sequence[int],
    prior: Mapping[int, Pose],
    res: BundleResult,
    tracks: Tracks,
    frame_info: np.ndarray,
    block_options: BlockOptions = BlockOptions(),
    options: ConfirmOptions = ConfirmOptions(),
    bundle_options: BundleOptions = BundleOptions(),
) -> Confirmation:
    """Which frames of an adjusted block take their adjusted poses (module docstring).

    Args:
        camera: interior orientation (the image's size for the spread of the ties).
        frames: the block's frames, recording order.
        prior: prior pose per frame (world = model CRS).
        res: the block's adjustment.
        tracks: the block's tracks (their observations in the order of `res.inlier`).
        frame_info: `(6, 6)` information of a frame's deviation from the common correction.
        block_options: the edge rule (`anchor_frames`, `min_mean_support`, `min_support_gain`).
        options: rules 2 and 3.
        bundle_options: the Tukey constant of the plane distances (`plane_tukey_m`).
    """
    frames = list(frames)
    inlier = np.zeros(len(tracks.track), bool)  # the adjustment's inliers among all observations
    inlier[np.isin(tracks.frame, frames)] = res.inlier
    anchor = anchoring(frames, res.edge_support, res.null_support, block_options)
    on_plane, plane_rms, off_share = plane_figures(tracks, res.points, inlier, bundle_options.plane_tukey_m)
    planes_ok = bool(
        res.converged
        and res.sigma0 <= options.max_sigma0
        and np.isfinite(plane_rms)
        and plane_rms <= options.max_plane_rms_m
        and off_share <= options.max_off_plane_share
    )
    by_planes = [
        f
        for f in frames
        if anchor[f] is None and planes_ok and _frame_geometry(camera, f, tracks, inlier, on_plane, options)
    ]
    chi2 = frame_chi2(frames, prior, res, frame_info)
    gate = {f: options.max_frame_chi2_edges if anchor[f] else options.max_frame_chi2 for f in frames}
    inconsistent = [f for f in frames if not chi2[f] <= gate[f]]
    undetermined = [
        f for f in frames if not _determined(camera, f, tracks, inlier, res, options.max_sigma_px)
    ]
    taken = {
        f: bool((anchor[f] or f in by_planes) and f not in inconsistent and f not in undetermined)
        for f in frames
    }
    reason = ""
    if res.edge_support and not any(anchor.values()):
        reason = "the block found the model nowhere (edge support)"
    elif not res.edge_support and len(by_planes) < options.min_confirmed_share * len(frames):
        reason = "no frame sees model edges, and the planes and tracks confirm too few frames"
    elif len(inconsistent) > options.max_inconsistent_share * len(frames):
        reason = "the adjusted poses contradict their priors (per-frame deviation)"
    elif not any(taken.values()):
        reason = "the adjustment leaves every confirmed pose undetermined (covariance)"
    if reason:
        taken = dict.fromkeys(frames, False)
    return Confirmation(reason, taken, anchor, by_planes, inconsistent, undetermined, plane_rms)


def _determined(
    camera: Camera, frame: int, tracks: Tracks, inlier: np.ndarray, res: BundleResult, max_sigma_px: float
) -> bool:
    """Rule 4 for one frame: the covariance of its adjusted pose projected onto its inlier tie
    points is at most `max_sigma_px` (RMS, px); True without tie points."""
    m = (tracks.frame == frame) & inlier
    if not m.any():
        return True
    X = res.points[tracks.track[m]]
    return sigma_px(camera, res.poses[frame], X, res.covariance[frame]) <= max_sigma_px


def _frame_geometry(
    camera: Camera,
    frame: int,
    tracks: Tracks,
    inlier: np.ndarray,
    on_plane: np.ndarray,
    options: ConfirmOptions,
) -> bool:
    """Rule 2 for one frame: at least `min_ties` inlier tie observations (`inlier` `(M,)`) of
    points on their planes (`on_plane` `(T,)`), spread over the image by at least `min_spread`
    along u and along v."""
    m = (tracks.frame == frame) & inlier & on_plane[tracks.track]
    if int(m.sum()) < options.min_ties:
        return False
    sd = np.std(tracks.uv[m], axis=0)
    return bool(sd[0] >= options.min_spread * camera.width and sd[1] >= options.min_spread * camera.height)

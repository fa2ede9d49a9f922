"""A model-free multi-view block of a frame sequence: image tracks, triangulation from the priors
and the project's bundle adjustment with the GNSS/INS priors (no planes, no edges).

In: frames in recording order (`load(i)`, as `dense_stereo`), their `Camera`, a prior pose per
frame (world = model CRS, metres: the calibrated GNSS/INS poses) and `MultiViewOptions`.
Out: `MultiViewBlock`: the adjusted poses (one per frame; a frame the adjustment could not tie
keeps its prior) and the figures (tracks, observations, tie RMS, frames tied).

Why (Hoegner & Stilla's method 3 needs TIR clouds that are not bent): the dense clouds of a block
come from stereo pairs of consecutive frames; their relative orientation from the per-frame
GNSS/INS poses (0.2 m and 0.2° of noise) is useless for stereo, and from two views alone
(`dense_stereo.refine_relative`) it is 0.24-0.52° off on a street of facades, which bends the
cloud by decimetres (measured on `bench/orientation_rgb.py`: with the true poses the TIR cloud
lies 0.08 m from the surfaces, with the two-view orientations 0.24-0.32 m). Tracks over many
frames (`image_tracks`) tie every frame to all its neighbours; the bundle adjustment
(`orientation.bundle.bundle_adjust`, the sequence orientation's, without model planes and
edges) then gives relative orientations consistent along the block, while the priors (a common
error of the block plus each frame's white noise and vibration) hold its gauge: the block's
position, attitude and scale stay with the GNSS/INS (the ICP onto the RGB cloud then removes
the common offset).

Steps: start poses: the priors smoothed over `start_smoothing_frames`
(`orientation.smoothing.smooth_poses`) → tracks (`image_tracks.image_tracks`; partners from the
priors, or with the optional epipolar band both from the start poses) → optionally, observations
that do not fit their track's point triangulated from the start poses dropped
(`consistent_tracks`, `start_max_px`: false matches along the epipolar line, which the pairs'
essential matrices keep, bent the block of the bench's seed 2 by 1.1 m and it was refused) →
every track of `min_track_length` views triangulated from them (`colmap.triangulate`) → `bundle_adjust` with
the priors (common σ `common_sigma_m` / `common_sigma_deg`, per-frame σ `frame_sigma_m` /
`frame_sigma_deg`), tie σ `tie_sigma_px`. The result is kept when the adjustment converged and
its tie RMS is below `max_tie_rms_px` and its frames moved on average no farther from their
priors than `max_common_shift_m` / `max_common_turn_deg` (the ties cannot place the block: a
mean move is a bent block); else the priors come back (`accepted` False).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import so3_log
from workers.pipeline.orientation.bundle import bundle_adjust
from workers.pipeline.orientation.bundle_types import BundleOptions
from workers.pipeline.orientation.priors import frame_noise_covariance
from workers.pipeline.orientation.smoothing import smooth_poses
from workers.pipeline.orientation.tracks import Tracks
from workers.pipeline.reconstruction.colmap import triangulate
from workers.pipeline.reconstruction.image_tracks import ImageTrackOptions, image_tracks
from workers.pipeline.reconstruction.options import ReconstructionOptions


@dataclass(frozen=True)
class MultiViewOptions:
    """Parameters of `multiview_block` (pixels, metres, degrees, frames)."""

    tracks: ImageTrackOptions = field(default_factory=ImageTrackOptions)
    start_smoothing_frames: float = 4.0  # Gaussian σ of the start poses' smoothing, frames
    min_track_length: int = 3  # views a track needs to be triangulated
    min_angle_deg: float = 1.0  # smallest largest-angle between a track's rays
    min_depth_m: float = 2.0  # nearer points (or behind a camera) are not triangulated
    # `consistent_tracks`' limit (px; None: every track as matched). Off by default: measured
    # on `bench/orientation_rgb.py --consistent-tracks 8` (48 frames, load 5): seed 1 cloud
    # distance 0.0666 -> 0.0503 m, TIR position 0.162 -> 0.089 m; seed 2 the block accepted
    # (was refused: moved 1.12 m) and the distance 0.455 -> 0.048 m, but the position 0.159 ->
    # 0.740 m: the rigid ICP leaves the poses 0.66 m high, where the mean distance equals the truth's
    # (0.0467 vs 0.0475 m: these facades leave the height to a few window reveals)
    start_max_px: float | None = None
    start_rounds: int = 3  # ... its rounds of triangulation and dropping
    tie_sigma_px: float = 0.5  # σ of a SIFT keypoint's position (Huber at twice it)
    outlier_px: float = 2.0  # tie observations beyond this after convergence are dropped
    common_sigma_m: float = 5.0  # a-priori σ of the block's common position error
    common_sigma_deg: float = 0.5  # ... and attitude error (what the calibration leaves)
    frame_sigma_m: float = 0.3  # each frame's own deviation (white noise) from the common error
    frame_sigma_deg: float = 0.3  # ... (white noise and vibration)
    min_frame_ties: int = 20  # a frame with fewer tie observations keeps its prior
    max_tie_rms_px: float = 1.0  # a block whose ties fit worse is refused
    # ties carry nothing about where the block lies: a block whose tied frames moved on average
    # farther than this from their priors was bent by false tracks (repetitive windows) and is
    # refused (bench seed 1: 0.05 m / 0.07°, the 16-frame drive of the tests 0.03 m / 0.21°;
    # seed 2, 29 of 48 frames tied: 2.25 m / 0.62°, the frames 1 m further from the truth)
    max_common_shift_m: float = 0.3
    max_common_turn_deg: float = 0.4


@dataclass(frozen=True, eq=False)
class MultiViewBlock:
    """Outcome of `multiview_block`: `poses` (one per frame, world), whether the adjustment was
    `accepted` (else `poses` are the priors; `reason` says why), the frames `tied` (enough tie
    observations), the tracks used and the tie RMS (px) of the inlier observations."""

    poses: tuple[Pose, ...]
    accepted: bool
    reason: str
    tied: tuple[int, ...]
    n_tracks: int
    n_observations: int
    tie_rms_px: float

    def figures(self) -> dict[str, Any]:
        """The figures as plain JSON values."""
        return {
            "accepted": self.accepted, "reason": self.reason, "frames_tied": len(self.tied),
            "tracks": self.n_tracks, "observations": self.n_observations,
            "tie_rms_px": round(self.tie_rms_px, 3) if np.isfinite(self.tie_rms_px) else None,
        }  # fmt: skip


def multiview_block(
    load: Callable[[int], np.ndarray],
    camera: Camera,
    priors: Sequence[Pose],
    options: MultiViewOptions = MultiViewOptions(),
) -> MultiViewBlock:
    """Adjust the block of frames `0 … F-1` (see the module docstring)."""
    priors = list(priors)
    frames = list(range(len(priors)))
    prior_map = dict(enumerate(priors))
    times = {f: float(f) for f in frames}
    start = smooth_poses(prior_map, frames, times, options.start_smoothing_frames)
    guided = options.tracks.epipolar_band_px is not None  # the band from the smoothed poses
    tracks = image_tracks(load, camera, [start[f] for f in frames] if guided else priors, options.tracks)
    refused = _refusal(priors, tracks)
    ro = ReconstructionOptions(
        min_track_length=options.min_track_length, min_angle_deg=options.min_angle_deg,
        min_depth_m=options.min_depth_m,
    )  # fmt: skip
    if options.start_max_px is not None:
        tracks = consistent_tracks(camera, tracks, start, ro, options.start_max_px, options.start_rounds)
    ids, X = triangulate(camera, tracks, start, ro)
    if len(ids) < options.min_frame_ties:
        return refused(f"too few triangulated tracks ({len(ids)})")
    keep = np.isin(tracks.track, ids)  # ids ascending: track ids renumbered in their order
    z = np.zeros_like(X)
    renumbered = np.searchsorted(ids, tracks.track[keep])
    kept = Tracks(renumbered, tracks.frame[keep], tracks.uv[keep], X, z, z[:, 0])
    white = np.linalg.inv(frame_noise_covariance(options.frame_sigma_deg, options.frame_sigma_m))
    common = np.linalg.inv(frame_noise_covariance(options.common_sigma_deg, options.common_sigma_m))
    bo = BundleOptions(
        edges=False, tie_sigma_px=options.tie_sigma_px, tie_huber_px=2 * options.tie_sigma_px,
        outlier_px=options.outlier_px,
    )  # fmt: skip
    res = bundle_adjust(
        camera, frames, {}, start, prior_map, dict.fromkeys(frames, white), common, kept, None, None, bo  # type: ignore[arg-type]
    )
    n_obs = int(sum(res.ties.values()))
    rms = _tie_rms(res.ties, res.tie_rms_px)
    if not res.converged:
        return refused("the adjustment did not converge", kept.n_tracks, n_obs, rms)
    if not rms <= options.max_tie_rms_px:
        return refused(f"tie RMS {rms:.2f} px > {options.max_tie_rms_px}", kept.n_tracks, n_obs, rms)
    tied = tuple(f for f in frames if res.ties.get(f, 0) >= options.min_frame_ties)
    poses = tuple(res.poses[f] if f in tied else priors[f] for f in frames)
    shift, turn = common_move([poses[f] for f in tied], [priors[f] for f in tied])
    if shift > options.max_common_shift_m or turn > options.max_common_turn_deg:
        reason = f"the block moved {shift:.2f} m / {turn:.2f} deg from its priors on average"
        return refused(reason, kept.n_tracks, n_obs, rms)
    return MultiViewBlock(poses, True, "", tied, kept.n_tracks, n_obs, rms)


def consistent_tracks(
    camera: Camera, tracks: Tracks, start: dict[int, Pose], options: ReconstructionOptions,
    max_px: float, rounds: int,
) -> Tracks:  # fmt: skip
    """`tracks` without the observations that do not fit their track's point triangulated from
    the `start` poses (world) by more than `max_px` (pixels): `rounds` rounds of triangulation
    each dropping a track's worst observation beyond the limit, then every observation still
    beyond it; tracks left with fewer than `options.min_track_length`
    observations, or not triangulated, are dropped (`Tracks.subset`: ids renumbered).

    Why: the essential matrix of a pair cannot reject a false match along its epipolar line, and
    on a drive past facades the epipolar lines run along the rows of repeated windows; a false
    match then joins two points into one track that no single point explains from three or more
    views. The start poses (smoothed priors) are a few pixels off; a false match of the next
    window is tens to hundreds.
    """
    for r in range(rounds + 1):
        err = _start_errors(camera, tracks, start, options)
        if r < rounds:  # each track's worst observation beyond the limit
            order = np.lexsort((-err, tracks.track))
            first = np.r_[True, np.diff(tracks.track[order]) != 0]
            worst = order[first]
            keep = np.ones(len(err), dtype=bool)
            keep[worst[err[worst] > max_px]] = False
        else:  # the last round: every observation beyond it
            keep = err <= max_px
        length = np.bincount(tracks.track[keep], minlength=tracks.n_tracks)
        keep &= length[tracks.track] >= options.min_track_length
        if np.all(keep):
            return tracks
        tracks = tracks.subset(keep)
    return tracks


def _start_errors(
    camera: Camera, tracks: Tracks, start: dict[int, Pose], options: ReconstructionOptions
) -> np.ndarray:
    """`(M,)` pixel distance of every observation from its track's point triangulated from
    `start` (`colmap.triangulate`); inf where the track was not triangulated."""
    ids, X = triangulate(camera, tracks, start, options)
    err = np.full(len(tracks.track), np.inf)
    if not len(ids):
        return err
    row = np.minimum(np.searchsorted(ids, tracks.track), len(ids) - 1)
    known = ids[row] == tracks.track
    for f in np.unique(tracks.frame[known]):
        o = np.flatnonzero(known & (tracks.frame == f))
        q, _ = start[int(f)].project(camera, X[row[o]])
        err[o] = np.linalg.norm(q - tracks.uv[o], axis=1)
    return err


def common_move(poses: Sequence[Pose], priors: Sequence[Pose]) -> tuple[float, float]:
    """The mean move of `poses` from `priors` (world): the length of the mean centre shift
    (metres) and the angle of the mean rotation vector of `R_pose R_priorᵀ` (degrees); (0, 0)
    for no poses.

    >>> q = [Pose(np.eye(3), np.zeros(3)), Pose(np.eye(3), np.ones(3))]
    >>> p = [Pose(np.eye(3), np.array([0.3, 0.0, 0.0])), Pose(np.eye(3), np.array([1.1, 1.0, 1.0]))]
    >>> tuple(round(v, 6) for v in common_move(p, q))
    (0.2, 0.0)
    """
    if not poses:
        return 0.0, 0.0
    pairs = list(zip(poses, priors, strict=True))
    d = np.mean([p.center - q.center for p, q in pairs], axis=0)
    w = np.mean([so3_log(p.R_world_from_cam @ q.R_world_from_cam.T) for p, q in pairs], axis=0)
    return float(np.linalg.norm(d)), float(np.degrees(np.linalg.norm(w)))


def _refusal(priors: list[Pose], tracks: Tracks) -> Callable[..., MultiViewBlock]:
    """A constructor of the refused block (the priors) with a reason and figures."""

    def refused(
        reason: str, n_tracks: int | None = None, n_obs: int = 0, rms: float = float("nan")
    ) -> MultiViewBlock:
        n = tracks.n_tracks if n_tracks is None else n_tracks
        return MultiViewBlock(tuple(priors), False, reason, (), n, n_obs, rms)

    return refused


def _tie_rms(ties: dict[int, int], rms: dict[int, float]) -> float:
    """RMS (px) over the frames' tie RMS values weighted by their observation counts."""
    e = [(rms[f], n) for f, n in ties.items() if n and np.isfinite(rms.get(f, np.nan))]
    if not e:
        return float("inf")
    v, w = np.array(e).T
    return float(np.sqrt(np.average(v**2, weights=w)))

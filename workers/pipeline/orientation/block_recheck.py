"""Frames of an adjusted block whose model edges contradict their pose: the ties they carry
dropped, the frames restarted from their neighbours' correction, the block adjusted again.

In: the block's frames (recording order), their prior poses (world = model CRS), the adjustment
(`bundle.BundleResult`: poses, per-frame edge RMS and support at the adjusted poses), its tracks
(`tracks.Tracks`), and a function that adjusts the block again from given start poses with given
tracks (the same bundle adjustment, `block.adjust_block`). Out: the adjustment to keep, its
tracks, and the frames rechecked (empty when the first adjustment stands).

Why (issue 15, the 30-frame NRW drive with the default GNSS/INS errors): a frame tied to the
block by one short track bends to fit that track. One track of three observations (frames 4-6,
one tie each; 17-24 px apart from itself at the true poses, a point about 1 m off the facade it
was put on) fitted to 0.03 px at poses up to 0.86° and 0.6 m off, 17-33 px at a building 94 m
away; frame 21 (5 ties) was bent 0.4° by another short track (its point 11 m off its plane).
Their own model edges fitted worse than anywhere else in the block (RMS 0.6-1.1 px against a
median of 0.36 px; edge support 0.36-0.41 against 0.51-0.56 at the true poses). The tie σ
(0.15 px) gives a single track the weight of many edges and its residuals at the bent poses are
small, so neither the outlier test on the ties nor the frames' covariance (σ 0.03°) sees it.
What does see it is the frames' edge fit.

Rule: a frame is suspect when it is weakly tied (fewer than `max_ties` inlier tie observations)
and its edge RMS exceeds `rms_ratio` × the block's median edge RMS and `min_rms_px`. A frame
held by many tracks is not rechecked: where its edges disagree with many ties (a frame of the
procedural test drive whose edges meet unmodelled detail), the edges are the ones to doubt, and
dropping its ties cost it 0.3 -> 2 px there. The suspects' tie observations are dropped (tracks
left with fewer than two observations go), each suspect restarts from its prior with the
correction (`pose_delta`) of the other frames interpolated linearly in block position, the
others from their adjusted poses, and the block is adjusted again. The new adjustment is kept
when the edge RMS of some suspect falls to at most `max_rms_share` of what it was, no suspect's
rises above `max_rms_rise` of it, and the block's mean edge support does not fall by more than
`max_loss`; else the first stands. (A mean over the suspects hid seven frames of the 300-frame
NRW drive that came back from 0.63 to 0.31-0.48 px among ten whose RMS, 0.8-1.1 px, stayed;
in another window three frames' RMS rose by 28-40 %: not kept.) (Edge support
alone does not tell: on the procedural drive it stayed at 0.86-0.87 while the frames came back
from 8 px to 0.8 px.) Restarting the suspects with their tie kept left them bent (the track holds
them there), and dropping the tie but restarting every frame from its prior let another frame
fall into a wrong minimum of its edges (0.08° -> 0.72°); both parts are needed. On the NRW
errors drive the window's frames end within 0.1° and 0.11 m of the truth (before: 0.86°).

Figures (this machine, loaded): `bench/texture.py --quick`, the drive with the default errors:
RMSE 0.453 -> 0.170 K, ratio to true poses 2.99 -> 1.12 (bar 1.5), 1 -> 0 hidden surfaces
textured, 3 -> 0 frames rejected by the texture's consistency test; the flight with errors 1.009
as before (no frame rechecked). `bench/pipeline_speed.py --skip cost,flight` (300-frame drive,
two windows; the second rechecks 20 frames): pairs < 1 px 0.934 -> 0.942, median 0.125 ->
0.118 px, texture RMSE 0.2027 -> 0.1888 K. Cost: one more adjustment of a window with suspects,
not its tracking: the drive's orient stage 21.3 -> 28.0 CPU s (one process, back to back with
the base).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import apply_delta, pose_delta
from workers.pipeline.orientation.bundle_types import BundleResult
from workers.pipeline.orientation.tracks import Tracks

__all__ = ["RecheckOptions", "recheck_block", "restart_poses", "suspect_frames"]

#: adjusts the block again: (start pose per frame, tracks) -> the adjustment
Readjust = Callable[[Mapping[int, Pose], Tracks], BundleResult]


@dataclass(frozen=True)
class RecheckOptions:
    """Parameters of the recheck (module docstring); `enabled` False keeps every first
    adjustment."""

    enabled: bool = True
    # a suspect: fewer inlier tie observations than this (weakly tied: a short track can bend
    # it; a frame held by many tracks is not, and where its edges disagree with them the edges
    # are the ones to doubt), and an edge RMS above this multiple of the block's median edge RMS
    # and this many px
    max_ties: int = 8
    rms_ratio: float = 1.5
    min_rms_px: float = 0.1
    # the new adjustment is kept when the edge RMS of a suspect falls to at most `max_rms_share`
    # of what it was, none rises above `max_rms_rise` of it, and the block's mean edge support
    # falls by at most `max_loss`
    max_rms_share: float = 0.8
    max_rms_rise: float = 1.1
    max_loss: float = 0.01
    # frames with edge figures the block needs for a median
    min_frames: int = 3


def suspect_frames(
    frames: Sequence[int], res: BundleResult, options: RecheckOptions = RecheckOptions()
) -> list[int]:
    """Frames (recording order) with fewer than `max_ties` inlier tie observations
    (`res.ties`) whose edge RMS at the adjusted pose (`res.edge_rms_px`, px) exceeds `rms_ratio`
    × the median over the block's frames with edge figures and `min_rms_px`; none when fewer than
    `min_frames` frames have edge figures."""
    rms = {f: float(res.edge_rms_px[f]) for f in frames if np.isfinite(res.edge_rms_px.get(f, np.nan))}
    if len(rms) < options.min_frames:
        return []
    limit = max(options.rms_ratio * float(np.median(list(rms.values()))), options.min_rms_px)
    return [f for f in frames if rms.get(f, 0.0) > limit and res.ties.get(f, 0) < options.max_ties]


def restart_poses(
    frames: Sequence[int], prior: Mapping[int, Pose], poses: Mapping[int, Pose], suspects: Sequence[int]
) -> dict[int, Pose]:
    """Start poses of the second adjustment: `poses` for the frames not in `suspects`; a suspect
    takes its prior with the correction `δ = pose_delta(prior, pose)` `(6,)` of the others
    interpolated linearly in block position (the nearest one's beyond the ends); `poses` as they
    are when every frame is a suspect."""
    frames = list(frames)
    bad = set(suspects)
    pos = np.arange(len(frames), dtype=np.float64)
    good = np.array([f not in bad for f in frames])
    out = {f: poses[f] for f in frames}
    if not good.any():
        return out
    D = np.array([pose_delta(prior[f], poses[f]) for f, g in zip(frames, good, strict=True) if g])
    for k, f in enumerate(frames):
        if f in bad:
            d = np.array([np.interp(pos[k], pos[good], D[:, j]) for j in range(6)])
            out[f] = apply_delta(prior[f], d)
    return out


def recheck_block(
    frames: Sequence[int],
    prior: Mapping[int, Pose],
    res: BundleResult,
    tracks: Tracks,
    readjust: Readjust,
    options: RecheckOptions = RecheckOptions(),
) -> tuple[BundleResult, Tracks, list[int]]:
    """The recheck of an adjusted block (module docstring).

    Args:
        frames: the block's frames, recording order.
        prior: prior pose per frame (world = model CRS).
        res: the block's adjustment, with its edge figures.
        tracks: its tracks (observations in the order of `res.inlier`).
        readjust: adjusts the block again from start poses with tracks.
        options: the rule's parameters.

    Returns:
        (the adjustment kept, its tracks, the suspects when the second adjustment was kept, else []).
    """
    if not options.enabled:
        return res, tracks, []
    frames = list(frames)
    suspects = suspect_frames(frames, res, options)
    if not suspects:
        return res, tracks, []
    kept = tracks.subset(~np.isin(tracks.frame, suspects))
    again = readjust(restart_poses(frames, prior, res.poses, suspects), kept)
    if not again.converged:
        return res, tracks, []
    before = np.array([res.edge_rms_px[f] for f in suspects])
    after = np.array([again.edge_rms_px.get(f, np.inf) for f in suspects])
    loss = _mean_support(res, frames) - _mean_support(again, frames)
    better = bool(np.any(after <= options.max_rms_share * before))
    worse = bool(np.any(~(after <= options.max_rms_rise * before)))
    if better and not worse and not loss > options.max_loss:
        return again, kept, suspects
    return res, tracks, []


def _mean_support(res: BundleResult, frames: Sequence[int]) -> float:
    """Mean edge support of `frames` (0 for a frame without edge figures); NaN without frames."""
    if not frames:
        return float("nan")
    return float(np.mean([res.edge_support.get(f, 0.0) for f in frames]))

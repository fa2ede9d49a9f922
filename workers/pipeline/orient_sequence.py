"""Sequence orientation: every frame's pose refined in overlapping blocks of consecutive frames
(feature tracks and a bundle adjustment with the city model), once per sequence, before the
building units.

In: `Camera`, a `RayCaster` over the buildings near the cameras (its mesh gives the scene
wireframe), the frames in recording order with their times (seconds), a `FrameSource`, the
(calibrated) prior pose per frame with its a-priori `Accuracy`, options.
Out: `SequenceOrientation`: per frame the refined pose and its covariance (or the prior where a
block was rejected), per block its figures, and the tracks with their adjusted points, which the
building units reuse (`SequenceOrientation.for_frames`).

Why (Hoegner & Stilla, method 2; DESIGN.md "calibrate ... once per sequence"): a close-range
drive frame rarely shows enough model edges to fix its pose, and a building often shows none in
a run of frames (a long blank facade, a party wall); tied by feature tracks to the frames before
and after it, which see other buildings' edges, such a frame is still well determined. A block of
one building's frames alone would lose exactly those neighbours.

Method: the frames are split where the time between two frames exceeds `max_gap_s`, then into
windows of `window_frames` overlapping by `overlap_frames`; each window is one block
(`coregister_block.adjust_block`: tracks, bundle adjustment against the scene wireframe with a
common prior error of the block and per-frame noise, tracked again when the ties fit badly). A
frame whose neighbours with model edges do not support the adjusted poses
(`coregister_block.anchoring`) keeps its prior; a frame with no model edges around it keeps the
adjusted pose and its covariance (the units decide whether it is determined well enough). A
frame in two windows takes the pose of the one where it lies further from the window's ends.
"""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from workers.pipeline.camera import Camera
from workers.pipeline.coregister import CoregisterOptions, prior_information
from workers.pipeline.coregister_block import (
    BlockOptions,
    UnitSequence,
    adjust_block,
    anchoring,
    block_reason,
)
from workers.pipeline.model_edges import WireframeError, mesh_wireframe
from workers.pipeline.pose import Pose
from workers.pipeline.raycast import RayCaster
from workers.pipeline.sequence import Accuracy, FrameSource
from workers.pipeline.tracks import Tracks

__all__ = [
    "SEQUENCE_PLATFORMS",
    "SequenceOrientation",
    "SequenceOrientationOptions",
    "UnitSequence",
    "orient_sequence",
]

#: platforms whose sequences are oriented in blocks before the units (close range: a frame alone
#: rarely fixes its pose); flights orient frame by frame in the units
SEQUENCE_PLATFORMS = ("drive", "terrestrial")


@dataclass(frozen=True)
class SequenceOrientationOptions:
    """Parameters of the sequence orientation (frames, seconds)."""

    block: BlockOptions = field(default_factory=BlockOptions)
    # the prior's σ (metres, degrees) come from the accuracy as for a building unit
    coregister: CoregisterOptions = field(default_factory=CoregisterOptions)
    # windows of consecutive frames, their overlap (a frame near a window's end has less context:
    # it takes its pose from the neighbouring window), a gap longer than this splits the sequence
    window_frames: int = 120
    overlap_frames: int = 30
    max_gap_s: float = 1.0


@dataclass(frozen=True, eq=False)
class SequenceOrientation:
    """Result of `orient_sequence`.

    Attributes:
        poses: `{frame: Pose}` for every frame: refined, or the prior where no block oriented it.
        covariance: `{frame: (6, 6)}` of the refined poses (frames a block oriented).
        blocks: per window `{"frames": [first, last], "accepted": bool, "reason": str,
            "mean_edge_support": float, "null_support": float, "sigma0": float, "tracks": int,
            "tie_observations": int}`.
        tracks: the tracks of the accepted windows (track points as adjusted), ids unique.
    """

    poses: dict[int, Pose]
    covariance: dict[int, np.ndarray]
    blocks: list[dict]
    tracks: Tracks

    @property
    def oriented(self) -> list[int]:
        """Frames a block oriented, in index order."""
        return sorted(self.covariance)

    def for_frames(self, frames: Sequence[int]) -> UnitSequence:
        """The part a building unit over `frames` needs (see `UnitSequence`)."""
        fs = [int(f) for f in frames]
        keep = np.isin(self.tracks.frame, fs)
        sub = _subset(self.tracks, keep)
        return UnitSequence(
            poses={f: self.poses[f] for f in fs if f in self.covariance},
            covariance={f: self.covariance[f] for f in fs if f in self.covariance},
            tracks=sub,
        )

    def to_dict(self) -> dict:
        """The report.json `orientation` block: frames oriented, and the blocks."""
        return {"frames": len(self.poses), "frames_oriented": len(self.covariance), "blocks": self.blocks}


def windows(times: Sequence[float], options: SequenceOrientationOptions) -> list[tuple[int, int]]:
    """Windows `(start, stop)` (positions into `times`, stop exclusive) of consecutive frames:
    runs split where the time step exceeds `max_gap_s`, each run into windows of
    `window_frames` overlapping by `overlap_frames` (the last window is taken back so that it is
    full when the run allows).

    >>> windows([0.0, 0.1, 0.2, 0.3, 5.0, 5.1], SequenceOrientationOptions(window_frames=3, overlap_frames=1))
    [(0, 3), (1, 4), (4, 6)]
    """
    t = np.asarray(times, dtype=np.float64)
    if len(t) == 0:
        return []
    cuts = [0, *(np.flatnonzero(np.diff(t) > options.max_gap_s) + 1).tolist(), len(t)]
    W = max(int(options.window_frames), 2)
    step = max(W - int(options.overlap_frames), 1)
    out: list[tuple[int, int]] = []
    for a, b in itertools.pairwise(cuts):
        if b - a <= W:
            out.append((a, b))
            continue
        starts = list(range(a, b - W + 1, step))
        if starts[-1] + W < b:
            starts.append(b - W)
        out.extend((s, s + W) for s in starts)
    return out


def orient_sequence(
    camera: Camera,
    raycaster: RayCaster,
    frames: Sequence[int],
    frame_source: FrameSource,
    prior: Mapping[int, Pose],
    times: Mapping[int, float],
    accuracy: Accuracy | None,
    options: SequenceOrientationOptions = SequenceOrientationOptions(),
    progress: Callable[[int, int], None] | None = None,
) -> SequenceOrientation:
    """Orient every frame of the sequence in blocks (see the module docstring).

    Args:
        camera: interior orientation.
        raycaster: the buildings near the cameras (model planes, hidden-edge removal).
        frames: frame indices in recording order.
        frame_source: `load(i) -> (H, W)` float32 physical values.
        prior: (calibrated) prior camera pose per frame (world = model CRS).
        times: frame times in seconds.
        accuracy: a-priori σ of the priors (calibrated accuracy, or the manifest's).
        options: parameters.
        progress: called with (windows done, windows) after each window.
    """
    frames = [int(f) for f in frames]
    poses = {f: prior[f] for f in frames}
    covariance: dict[int, np.ndarray] = {}
    blocks: list[dict] = []
    parts: list[Tracks] = []
    scene_wf = None
    with contextlib.suppress(WireframeError):
        scene_wf = mesh_wireframe(raycaster.mesh, options.coregister.edges)
    if scene_wf is None or len(frames) < 2:
        return SequenceOrientation(poses, covariance, blocks, _empty_tracks())
    # position of each frame in the window that owns it: distance to the window's ends
    best: dict[int, int] = {}
    spans = windows([times[f] for f in frames], options)
    for k_win, (a, b) in enumerate(spans):
        if progress is not None:
            progress(k_win, len(spans))
        block = frames[a:b]
        images = {f: frame_source.load(f) for f in block}
        info = prior_information(prior[block[len(block) // 2]], accuracy, options.coregister)
        co = options.coregister
        res, tracks = adjust_block(camera, scene_wf, raycaster, block, images, prior, prior, info,
                                   options.block, co.fit, co.edges, co.features)
        reason = block_reason(block, prior, res, options.block)
        anchor = anchoring(block, res, options.block) if not reason else {}
        if not reason and not any(anchor.values()):
            reason = "the block found the model nowhere (edge support)"
        sup = [res.edge_support[f] for f in block if f in res.edge_support]
        nul = [res.null_support[f] for f in block if f in res.null_support]
        taken = [f for f in block if anchor.get(f) is not False]
        blocks.append({
            "frames": [block[0], block[-1]],
            "accepted": not reason,
            "reason": reason,
            "frames_anchored": sum(1 for f in block if anchor.get(f)),
            "frames_without_edges_around": sum(1 for f in block if anchor.get(f, False) is None),
            "mean_edge_support": round(float(np.mean(sup)), 3) if sup else None,
            "null_support": round(float(np.mean(nul)), 3) if nul else None,
            "sigma0": round(float(res.sigma0), 3),
            "tracks": int(tracks.n_tracks),
            "tie_observations": int(np.sum(res.inlier)),
        })
        if reason:
            continue
        for k, f in enumerate(block):
            depth = min(k, len(block) - 1 - k)
            if f in taken and depth >= best.get(f, -1):
                best[f] = depth
                poses[f] = res.poses[f]
                covariance[f] = res.covariance[f]
        parts.append(_with_points(tracks, res.points))
    if progress is not None:
        progress(len(spans), len(spans))
    return SequenceOrientation(poses, covariance, blocks, _concat(parts))


def _empty_tracks() -> Tracks:
    z3 = np.zeros((0, 3))
    return Tracks(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 2)), z3, z3, np.zeros(0, int))


def _with_points(tracks: Tracks, points: np.ndarray) -> Tracks:
    """`tracks` with their points replaced by the adjusted `points` `(T, 3)` (the model planes
    stay)."""
    return Tracks(tracks.track, tracks.frame, tracks.uv, np.asarray(points), tracks.normal, tracks.polygon,
                  tracks.offset)


def _concat(parts: list[Tracks]) -> Tracks:
    """One `Tracks` of several, track ids made unique."""
    if not parts:
        return _empty_tracks()
    offs = np.cumsum([0] + [p.n_tracks for p in parts[:-1]])
    return Tracks(
        track=np.concatenate([p.track + o for p, o in zip(parts, offs, strict=True)]),
        frame=np.concatenate([p.frame for p in parts]),
        uv=np.concatenate([p.uv for p in parts]),
        point=np.concatenate([p.point for p in parts]),
        normal=np.concatenate([p.normal for p in parts]),
        polygon=np.concatenate([p.polygon for p in parts]),
        offset=np.concatenate([np.asarray(p.offset) for p in parts]),
    )


def _subset(tracks: Tracks, keep: np.ndarray) -> Tracks:
    """The observations `keep` `(M,)` of `tracks`; tracks left with fewer than 2 are dropped and
    the rest renumbered."""
    t = tracks.track[keep]
    length = np.bincount(t, minlength=tracks.n_tracks)
    alive = length >= 2
    m = alive[t]
    new_id = np.cumsum(alive) - 1
    return Tracks(
        track=new_id[t[m]],
        frame=tracks.frame[keep][m],
        uv=tracks.uv[keep][m],
        point=tracks.point[alive],
        normal=tracks.normal[alive],
        polygon=tracks.polygon[alive],
        offset=np.asarray(tracks.offset)[alive],
    )

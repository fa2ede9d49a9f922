"""Sequence orientation: every frame's pose refined in overlapping blocks of consecutive frames
(feature tracks and a bundle adjustment with the city model), once per sequence, before the
building units.

In: `Camera`, a `RayCaster` over the buildings near the cameras (its mesh gives the scene
wireframe), the frames in recording order with their times (seconds), a `FrameSource`, the
(calibrated) prior pose per frame with its a-priori `Accuracy`, options.
Out: `SequenceOrientation`: per frame the refined pose and its covariance (or the prior where a
block was rejected), per block its figures, and the tracks with their adjusted points, which the
building units reuse (`SequenceOrientation.for_frames`).

Why (Hoegner & Stilla, method 2; README.md, Commands): a close-range
drive frame rarely shows enough model edges to fix its pose, and a building often shows none in
a run of frames (a long blank facade, a party wall); tied by feature tracks to the frames before
and after it, which see other buildings' edges, such a frame is still well determined. A block of
one building's frames alone would lose exactly those neighbours.

Method: the frames are split where the time between two frames exceeds `max_gap_s`, then into
windows of `window_frames` overlapping by `overlap_frames`; each window is one block
(`block.adjust_block`: tracks, bundle adjustment against the scene wireframe with a
common prior error of the block and per-frame noise, tracked again when the ties fit badly).
Which frames take the adjusted poses is decided by `sequence_acceptance.confirm_block`: model
edges where the frames around see them (`block.anchoring`), the model planes and the tracks'
geometry where they do not (a close-range sequence of one facade whose outline stays outside the
frames), and every frame's consistency with its prior; a frame not confirmed keeps its prior, a
block not confirmed is rejected. A frame taken keeps the adjusted pose and its covariance (the
units decide whether it is determined well enough). A frame in two windows takes the pose of the
one where it lies further from the window's ends.

Windows as tasks (issue 18): `plan_windows` cuts the sequence into picklable `WindowTask`s,
`orient_window` (`sequence_windows`) adjusts and confirms one window as a pure function of its
task, and `merge_windows` applies the rule above to the results in any order. `orient_sequence`
runs them through its `map_windows` argument: the built-in `map` here, a process pool
(`citytherm run --workers N`) or Celery tasks (the service) give the same orientation.

Calibrated or not (issue 19): after an accepted sequence calibration the priors carry a common
error of decimetres and white noise; without one (a close-range sequence the calibration
rejects: "too few frames see the model") they are the manifest's GNSS/INS poses, common error
and all, which the block's common correction takes up the same way. What the tracker cannot
take is white noise beyond the per-frame σ the blocks assume (`PriorOptions`: 0.3 m, 0.3°;
a hand-held GNSS/INS: 0.5 m and 1° from frame to frame, 50 px of wrong prediction that lock
the tracks onto the next window of a regular facade). So the priors' white noise is measured
from the priors themselves (`smoothing.prior_noise`); where it exceeds that σ clearly
(`noisy_factor`), the tracking and the adjustment start from the priors smoothed over
`start_smoothing_s` (`smoothing.smooth_poses`), the per-frame σ is raised to the measured noise
(the priors stay the observations) and every block is adjusted a second time from its adjusted
poses. Calibrated drives with the default error model (0.2 m, 0.05°) stay below it and run as
before.
"""

from __future__ import annotations

import contextlib
import itertools
import uuid
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.manifest import Accuracy, FrameSource
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.block import UnitSequence
from workers.pipeline.orientation.priors import prior_information
from workers.pipeline.orientation.sequence_windows import (
    SequenceOrientationOptions,
    WindowResult,
    WindowTask,
    orient_window,
)
from workers.pipeline.orientation.smoothing import prior_noise, smooth_poses
from workers.pipeline.orientation.tracks import Tracks
from workers.pipeline.orientation.wireframe import Wireframe, WireframeError, mesh_wireframe

__all__ = [
    "SEQUENCE_PLATFORMS",
    "SequenceOrientation",
    "SequenceOrientationOptions",
    "UnitSequence",
    "WindowMap",
    "WindowPlan",
    "WindowResult",
    "WindowTask",
    "merge_windows",
    "orient_sequence",
    "orient_window",
    "plan_windows",
]

#: platforms whose sequences are oriented in blocks before the units, calibration accepted or not:
#: close range (a frame alone rarely fixes its pose), and flights (a frame sees dozens of buildings:
#: oriented once against all of them, not once per building in every unit; issue 18)
SEQUENCE_PLATFORMS = ("drive", "terrestrial", "flight")


@dataclass(frozen=True, eq=False)
class SequenceOrientation:
    """Result of `orient_sequence`.

    Attributes:
        poses: `{frame: Pose}` for every frame: refined, or the prior where no block oriented it.
        covariance: `{frame: (6, 6)}` of the refined poses (frames a block oriented).
        blocks: per window `{"frames": [first, last], "accepted": bool, "reason": str,
            "frames_anchored": int, "frames_without_edges_around": int, "mean_edge_support":
            float | None, "null_support": float | None, "sigma0": float, "tracks": int,
            "tie_observations": int, "frames_confirmed_by_planes": int,
            "frames_inconsistent_with_priors": int, "frames_undetermined": int,
            "plane_rms_m": float | None,
            "frames_taken": int, "frames_rechecked": int}` (`sequence_acceptance.confirm_block`;
            `block_recheck`).
        tracks: the tie observations of each frame from the window its pose came from (track
            points as adjusted, ids unique; the overlapping windows tracked the same points).
        ties, tie_rms_px: inlier tie observations of each oriented frame and their RMS (px).
        prior_noise: the priors' white noise `{"attitude_deg", "position_m"}` (`prior_noise`)
            and whether the blocks started from the smoothed priors (`"smoothed_start"`).
    """

    poses: dict[int, Pose]
    covariance: dict[int, np.ndarray]
    blocks: list[dict]
    tracks: Tracks
    ties: dict[int, int] = field(default_factory=dict)
    tie_rms_px: dict[int, float] = field(default_factory=dict)
    prior_noise: dict = field(default_factory=dict)

    @property
    def oriented(self) -> list[int]:
        """Frames a block oriented, in index order."""
        return sorted(self.covariance)

    def for_frames(self, frames: Sequence[int]) -> UnitSequence:
        """The part a building unit over `frames` needs (see `UnitSequence`)."""
        fs = [int(f) for f in frames if int(f) in self.covariance]
        return UnitSequence(
            poses={f: self.poses[f] for f in fs},
            covariance={f: self.covariance[f] for f in fs},
            ties={f: self.ties.get(f, 0) for f in fs},
            tie_rms_px={f: self.tie_rms_px.get(f, float("nan")) for f in fs},
        )

    def to_dict(self, priors: str | None = None) -> dict:
        """The report.json `sequence_orientation` block: which `priors` the blocks started from
        (`"calibrated"` or `"manifest"`; left out when None), frames, frames oriented, the priors'
        white noise, the blocks."""
        head = {} if priors is None else {"priors": priors}
        return {
            **head,
            "frames": len(self.poses),
            "frames_oriented": len(self.covariance),
            "prior_noise": self.prior_noise,
            "blocks": self.blocks,
        }


def windows(times: Sequence[float], options: SequenceOrientationOptions) -> list[tuple[int, int]]:
    """Windows `(start, stop)` (positions into `times`, stop exclusive) of consecutive frames:
    runs split where the time step exceeds `max_gap_s` (runs of a single frame give no window).
    A run of up to `min_window_frames` is one window; a longer one of `n` frames is cut into `m`
    equal windows spread evenly over it (consecutive ones overlap by at least `overlap_frames`):
    `m` is the fewest windows of at most `window_frames` rounded up to a multiple of
    `min_windows` (the workers that orient them at once finish together), each of
    `max(min_window_frames, ceil((n + (m − 1) · overlap) / m))` frames.

    >>> o = SequenceOrientationOptions(window_frames=3, overlap_frames=1, min_window_frames=3)
    >>> windows([0.0, 0.1, 0.2, 0.3, 5.0, 5.1], o)
    [(0, 3), (1, 4), (4, 6)]
    >>> windows([0.0, 5.0, 5.1], o)
    [(1, 3)]
    >>> [windows(np.arange(n) * 0.1, SequenceOrientationOptions()) for n in (60, 100)]
    [[(0, 60)], [(0, 70), (30, 100)]]
    >>> windows(np.arange(300) * 0.1, SequenceOrientationOptions())  # four windows of 98 / 31
    [(0, 98), (67, 165), (135, 233), (202, 300)]
    >>> len(windows(np.arange(3000) * 0.1, SequenceOrientationOptions()))
    34
    """
    t = np.asarray(times, dtype=np.float64)
    if len(t) == 0:
        return []
    cuts = [0, *(np.flatnonzero(np.diff(t) > options.max_gap_s) + 1).tolist(), len(t)]
    W_max, overlap = int(options.window_frames), int(options.overlap_frames)
    W_min = min(int(options.min_window_frames), W_max)
    k = max(int(options.min_windows), 1)
    out: list[tuple[int, int]] = []
    for a, b in itertools.pairwise(cuts):
        n = b - a
        if n < 2:
            continue
        if n <= W_min:
            out.append((a, b))
            continue
        m = max(k, -(-(n - overlap) // (W_max - overlap)))  # fewest windows of at most W_max
        m = -(-m // k) * k
        W = max(W_min, -(-(n + (m - 1) * overlap) // m))
        if n <= W:
            out.append((a, b))
            continue
        out.extend((s, s + W) for s in (a + np.rint(np.linspace(0, n - W, m)).astype(int)).tolist())
    return out


#: how windows run: `map(orient_window, tasks)` in task order (built-in `map`, a process pool's
#: `Executor.map`, ...); the results may arrive lazily
WindowMap = Callable[[Callable[[WindowTask], WindowResult], Iterable[WindowTask]], Iterable[WindowResult]]


@dataclass(frozen=True, eq=False)
class WindowPlan:
    """The windows of a sequence as independent tasks (`plan_windows`).

    Attributes:
        frames: every frame index in recording order.
        prior: the prior pose per frame (world = model CRS).
        tasks: one `WindowTask` per window, in order (empty: nothing to orient).
        prior_noise: the priors' white noise figures (`SequenceOrientation.prior_noise`).
    """

    frames: tuple[int, ...]
    prior: dict[int, Pose]
    tasks: tuple[WindowTask, ...]
    prior_noise: dict


def plan_windows(
    camera: Camera,
    raycaster: RayCaster,
    frames: Sequence[int],
    frame_source: FrameSource,
    prior: Mapping[int, Pose],
    times: Mapping[int, float],
    accuracy: Accuracy | None,
    options: SequenceOrientationOptions = SequenceOrientationOptions(),
    wireframe: Wireframe | None = None,
) -> WindowPlan:
    """Cut the sequence into windows (`windows`), each a `WindowTask` with its start poses and
    prior information; no tasks when the scene has no wireframe or there are fewer than 2 frames.
    Arguments as `orient_sequence`."""
    frames = [int(f) for f in frames]
    base = {f: prior[f] for f in frames}
    scene_wf = wireframe
    if scene_wf is None:
        with contextlib.suppress(WireframeError):
            scene_wf = mesh_wireframe(raycaster.mesh, options.coregister.edges)
    if scene_wf is None or len(frames) < 2:
        return WindowPlan(tuple(frames), base, (), {})
    start, options, noise = _start_poses(prior, frames, times, options)
    key = uuid.uuid4().hex
    tasks = []
    for k, (a, b) in enumerate(windows([times[f] for f in frames], options)):
        block = frames[a:b]
        info = prior_information(prior[block[len(block) // 2]], accuracy, options.coregister)
        own_prior, own_start = {f: base[f] for f in block}, {f: start[f] for f in block}
        task = WindowTask(k, camera, tuple(block), frame_source, own_prior, own_start, info, options, key,
                          raycaster.mesh, raycaster, scene_wf)  # fmt: skip
        tasks.append(task)
    return WindowPlan(tuple(frames), base, tuple(tasks), noise)


def merge_windows(plan: WindowPlan, results: Iterable[WindowResult]) -> SequenceOrientation:
    """The sequence orientation from the windows' results (any order): a frame taken by several
    windows gets the pose of the one where it lies furthest from the window's ends (the later
    window on a tie), and its tie observations from that window (the overlapping windows tracked
    the same points again)."""
    done = {r.index: r for r in results}
    missing = [t.index for t in plan.tasks if t.index not in done]
    if missing:
        raise ValueError(f"windows {missing} of {len(plan.tasks)} have no result")
    poses = dict(plan.prior)
    covariance: dict[int, np.ndarray] = {}
    ties: dict[int, int] = {}
    tie_rms: dict[int, float] = {}
    best: dict[int, int] = {}  # depth of each frame in the window that owns it
    owner: dict[int, int] = {}
    ordered = [done[t.index] for t in plan.tasks]
    for r in ordered:
        for k, f in enumerate(r.frames):
            depth = min(k, len(r.frames) - 1 - k)
            if f in r.poses and depth >= best.get(f, -1):
                best[f], owner[f] = depth, r.index
                poses[f], covariance[f] = r.poses[f], r.covariance[f]
                ties[f], tie_rms[f] = r.ties[f], r.tie_rms_px[f]
    kept = [
        r.tracks.subset(np.array([owner.get(int(f)) == r.index for f in r.tracks.frame], bool))
        for r in ordered
        if r.tracks is not None
    ]
    blocks = [r.summary for r in ordered]
    tracks = Tracks.concat(kept)
    return SequenceOrientation(poses, covariance, blocks, tracks, ties, tie_rms, plan.prior_noise)


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
    map_windows: WindowMap = map,
    wireframe: Wireframe | None = None,
) -> SequenceOrientation:
    """Orient every frame of the sequence in blocks (see the module docstring): `plan_windows`,
    `orient_window` over the windows through `map_windows`, `merge_windows`.

    Args:
        camera: interior orientation.
        raycaster: the buildings near the cameras (model planes, hidden-edge removal).
        frames: frame indices in recording order.
        frame_source: `load(i) -> (H, W)` float32 physical values (picklable when `map_windows`
            runs in other processes).
        prior: (calibrated) prior camera pose per frame (world = model CRS).
        times: frame times in seconds.
        accuracy: a-priori σ of the priors (calibrated accuracy, or the manifest's).
        options: parameters.
        progress: called with (windows done, windows) before the first and after each window.
        map_windows: runs the windows (`WindowMap`): the built-in `map` here, one after the other;
            a process pool's `map` gives the same result.
        wireframe: `mesh_wireframe(raycaster.mesh, options.coregister.edges)` when the caller has
            it already (the calibrate stage made the same one); None: made here.
    """
    plan = plan_windows(camera, raycaster, frames, frame_source, prior, times, accuracy, options, wireframe)
    if not plan.tasks:
        return SequenceOrientation(dict(plan.prior), {}, [], Tracks.empty())
    n = len(plan.tasks)
    results = []
    if progress is not None:
        progress(0, n)
    for k, r in enumerate(map_windows(orient_window, plan.tasks)):
        results.append(r)
        if progress is not None:
            progress(k + 1, n)
    return merge_windows(plan, results)


def _start_poses(
    prior: Mapping[int, Pose],
    frames: Sequence[int],
    times: Mapping[int, float],
    options: SequenceOrientationOptions,
) -> tuple[dict[int, Pose], SequenceOrientationOptions, dict]:
    """The start poses of the blocks, the options for them, and the `prior_noise` figures (module
    docstring): the priors as they are, or where their measured white noise exceeds the per-frame
    σ clearly, the smoothed priors with that noise as the per-frame σ and a second pass of every
    block from its adjusted poses (`BlockOptions.retrack_sigma0` 0: the first pass's edge search
    started from poses too far off; a hand-held facade sequence after a calibration that
    traded 2.4° of pan for 0.8 m of offset ended 6 px off after one pass, 0.06 px after two)."""
    co = options.coregister
    deg, m = prior_noise(prior, frames)
    k = options.noisy_factor
    noisy = options.start_smoothing_s > 0 and (
        deg > k * co.prior.frame_sigma_deg or m > k * co.prior.frame_sigma_m
    )
    figures = {"attitude_deg": round(deg, 3), "position_m": round(m, 3), "smoothed_start": noisy}
    if not noisy:
        return {f: prior[f] for f in frames}, options, figures
    pr = replace(
        co.prior,
        frame_sigma_deg=max(co.prior.frame_sigma_deg, deg),
        frame_sigma_m=max(co.prior.frame_sigma_m, m),
    )
    noisy_options = replace(
        options, coregister=replace(co, prior=pr), block=replace(options.block, retrack_sigma0=0.0)
    )
    return smooth_poses(prior, frames, times, options.start_smoothing_s), noisy_options, figures

"""One window of the sequence orientation as an independent, picklable task (issue 18, item 3).

`sequence.plan_windows` cuts a sequence into `WindowTask`s; `orient_window(task)` adjusts one
window as a block and decides which of its frames take the adjusted poses; `sequence.merge_windows`
gives every frame the pose of the window where it lies furthest from the ends. The windows do not
depend on each other (each starts from the priors, or the smoothed priors, never from a
neighbour's result), so they may run in any order, in this process, in a process pool
(`citytherm run --workers N`) or as Celery tasks on other machines (the service), and give the
same result as one after the other.

A task pickles without its ray caster (an Open3D scene, not picklable): it carries the scene mesh
and rebuilds the caster once per process and plan (`WindowTask.scene`), keyed by the plan's
`scene_key`; it carries the planner's scene wireframe (plain arrays, a pure function of the mesh
and the edge options: remaking it took about 7 % of a window's time). In the process that planned
it the caster and the scene wireframe are the planner's own objects.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.manifest import FrameSource
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster, SceneMesh
from workers.pipeline.orientation.block import BlockOptions, adjust_block, block_reason
from workers.pipeline.orientation.building_options import CoregisterOptions
from workers.pipeline.orientation.bundle import BundleResult
from workers.pipeline.orientation.priors import frame_noise_information
from workers.pipeline.orientation.sequence_acceptance import Confirmation, ConfirmOptions, confirm_block
from workers.pipeline.orientation.tracks import Tracks
from workers.pipeline.orientation.wireframe import Wireframe, mesh_wireframe

__all__ = ["SequenceOrientationOptions", "WindowResult", "WindowTask", "orient_window"]


@dataclass(frozen=True)
class SequenceOrientationOptions:
    """Parameters of the sequence orientation (frames, seconds)."""

    block: BlockOptions = field(default_factory=BlockOptions)
    # the prior's σ (metres, degrees) come from the accuracy as for a building unit, the per-frame
    # deviation and the null shift from its `prior`
    coregister: CoregisterOptions = field(default_factory=CoregisterOptions)
    # windows of consecutive frames, their overlap (a frame near a window's end has less context:
    # it takes its pose from the neighbouring window), a gap longer than this splits the sequence.
    # A run is cut into a multiple of `min_windows` windows of at least `min_window_frames` (so
    # that two workers orient a short drive at once: the service's window tasks, `citytherm run
    # --workers 2`), of at most `window_frames` otherwise (`sequence.windows`). Issue 14: the service bench's
    # 100-frame drive is two windows of 70 (0-69, 30-99) and keeps the accuracy of one window of
    # 100 (drive past the Berlin model, seed 1: frames below 1 px 0.90 (0.90), median 0.26 px
    # (0.25), 90th percentile 0.80 px (0.93), texture RMSE 0.260 K (0.259), misregistration 0.111
    # texel (0.108); windows of 60 / 20 lost some: 0.89, 0.29 px, 1.1 px, 0.299 K, 0.120 texel).
    # Long drives keep windows of 120: the block's cost is linear in its frames, and windows of
    # 70 / 30 would cost +31 % orient CPU there (70 / 40 frame-windows per frame against 120 / 90).
    # Issue 18: the number of windows is a multiple of `min_windows`, all of one length, so that
    # the workers finish together: a 300-frame drive is four windows of 98 (0-97, 67-164,
    # 135-232, 202-299), two per worker of `--workers 2` (three of 120 kept one worker busy
    # twice as long; two of 165 gave pairs within 1 px 0.934 against 0.941 on the seed-1 bench
    # drive, but on seed 3 2 x 165 / 3 x 120 / 4 x 98 gave 0.918 / 0.913 / 0.919: where the
    # windows are cut matters more than their length)
    window_frames: int = 120
    min_window_frames: int = 70
    min_windows: int = 2
    overlap_frames: int = 30
    max_gap_s: float = 1.0
    # when the priors' white noise (`smoothing.prior_noise`) exceeds `noisy_factor` × the
    # per-frame σ of `coregister.prior`, the start poses of tracking and adjustment are the
    # priors smoothed over time with this Gaussian σ (seconds; 0: never) and the per-frame σ is
    # raised to the noise. The factor keeps drives out: their corners turn 30–60°/s, which a
    # local linear fit over a second bends by degrees (a calibrated drive whose noise measured
    # 0.30 m lost two frames so), and their default noise (0.2 m) measures up to 0.3 m
    start_smoothing_s: float = 1.0
    noisy_factor: float = 1.5
    # which frames of an adjusted block are confirmed (`sequence_acceptance`: edges where they
    # exist, planes and tracks where they do not, consistency with the priors)
    confirm: ConfirmOptions = field(default_factory=ConfirmOptions)

    def __post_init__(self) -> None:
        if self.window_frames < 2 or not 0 <= self.overlap_frames < self.window_frames:
            raise ValueError(
                f"windows of {self.window_frames} frames overlapping by {self.overlap_frames}: "
                "need at least 2 frames and an overlap smaller than the window"
            )


#: per process: the scene of the last plan whose windows ran here, `(scene_key, caster, wireframe)`
_SCENE: list[tuple[str, RayCaster, Wireframe]] = []


@dataclass(frozen=True, eq=False)
class WindowTask:
    """Everything one window's block needs (picklable; see the module docstring).

    Attributes:
        index: the window's position in the plan (0-based).
        camera: interior orientation.
        frames: the window's frame indices in recording order.
        frame_source: `load(i) -> (H, W)` float32 physical values.
        prior: the window's prior camera poses (world = model CRS), `camera_from_world` as `Pose`.
        start: the poses tracking and adjustment start from (the priors, or the smoothed priors).
        info: `(6, 6)` information of the block's common prior error (`priors.prior_information`
            of the window's middle frame).
        options: the sequence options as the window runs them (the noisy-prior variant included).
        scene_key: identifies the plan's scene mesh (the per-process caster cache key).
        mesh: the buildings near the cameras (model CRS, local origin).
        caster, wireframe: the planner's ray caster over `mesh` (not pickled) and the scene
            wireframe (pickled with the task).
    """

    index: int
    camera: Camera
    frames: tuple[int, ...]
    frame_source: FrameSource
    prior: dict[int, Pose]
    start: dict[int, Pose]
    info: np.ndarray
    options: SequenceOrientationOptions
    scene_key: str
    mesh: SceneMesh
    caster: RayCaster | None = field(default=None, repr=False)
    wireframe: Wireframe | None = field(default=None, repr=False)

    def __getstate__(self) -> dict[str, Any]:
        """Pickled without the ray caster (rebuilt from `mesh` where it runs)."""
        state = dict(self.__dict__)
        state["caster"] = None
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)

    def scene(self) -> tuple[RayCaster, Wireframe]:
        """The ray caster over `mesh` and its wireframe: the planner's, else built once per
        process and plan (the wireframe: the one the task carries, else made from `mesh`)."""
        if self.caster is not None and self.wireframe is not None:
            return self.caster, self.wireframe
        if not _SCENE or _SCENE[0][0] != self.scene_key:
            caster = RayCaster(self.mesh)
            wf = self.wireframe
            if wf is None:
                wf = mesh_wireframe(self.mesh, self.options.coregister.edges)
            _SCENE[:] = [(self.scene_key, caster, wf)]
        return _SCENE[0][1], _SCENE[0][2]


@dataclass(frozen=True, eq=False)
class WindowResult:
    """One window's outcome (picklable).

    Attributes:
        index: the window's position in the plan.
        frames: the window's frames in recording order.
        summary: its entry of `SequenceOrientation.blocks`.
        poses, covariance: adjusted pose and `(6, 6)` covariance of each frame taken (empty when
            the block was rejected).
        ties, tie_rms_px: inlier tie observations of each frame taken and their RMS (px).
        tracks: the block's tracks with the adjusted points (None when rejected).
    """

    index: int
    frames: tuple[int, ...]
    summary: dict
    poses: dict[int, Pose]
    covariance: dict[int, np.ndarray]
    ties: dict[int, int]
    tie_rms_px: dict[int, float]
    tracks: Tracks | None

    @property
    def accepted(self) -> bool:
        """True when the block was confirmed (its taken frames may take its poses)."""
        return self.tracks is not None


def orient_window(task: WindowTask) -> WindowResult:
    """Adjust one window as a block (`block.adjust_block`) and confirm its frames
    (`sequence_acceptance.confirm_block`); a pure function of `task`."""
    caster, scene_wf = task.scene()
    options, co = task.options, task.options.coregister
    block = list(task.frames)
    images = {f: task.frame_source.load(f) for f in block}
    res, tracks, rechecked = adjust_block(
        task.camera,
        scene_wf,
        caster,
        block,
        images,
        task.prior,
        task.start,
        task.info,
        options.block,
        co.fit,
        co.edges,
        co.features,
        co.prior,
    )
    frame_info = frame_noise_information(co.prior)
    conf = confirm_block(
        task.camera, block, task.prior, res, tracks, frame_info, options.block, options.confirm,
        options.block.bundle,
    )  # fmt: skip
    reason = block_reason(block, task.prior, res, options.block, need_edges=False) or conf.reason
    summary = _block_summary(block, res, tracks, conf, reason, rechecked)
    if reason:
        return WindowResult(task.index, task.frames, summary, {}, {}, {}, {}, None)
    taken = [f for f in block if conf.taken[f]]
    return WindowResult(
        task.index,
        task.frames,
        summary,
        {f: res.poses[f] for f in taken},
        {f: res.covariance[f] for f in taken},
        {f: res.ties[f] for f in taken},
        {f: res.tie_rms_px[f] for f in taken},
        tracks.with_points(res.points),
    )


def _block_summary(
    block: Sequence[int],
    res: BundleResult,
    tracks: Tracks,
    conf: Confirmation,
    reason: str,
    rechecked: Sequence[int] = (),
) -> dict:
    """One window's entry of `SequenceOrientation.blocks` (see there); `rechecked`: the frames
    `block_recheck` adjusted again."""
    anchor = conf.anchor
    sup = [res.edge_support[f] for f in block if f in res.edge_support]
    nul = [res.null_support[f] for f in block if f in res.null_support]
    return {
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
        "frames_confirmed_by_planes": len(conf.by_planes),
        "frames_inconsistent_with_priors": len(conf.inconsistent),
        "frames_undetermined": len(conf.undetermined),
        "plane_rms_m": round(conf.plane_rms_m, 3) if np.isfinite(conf.plane_rms_m) else None,
        "frames_taken": sum(1 for f in block if conf.taken[f] and not reason),
        "frames_rechecked": len(rechecked),
    }

"""Method 3 (Hoegner & Stilla): the TIR block registered onto an RGB block by ICP of dense clouds.

In: the TIR frames (`load(i)` -> `(H, W)` float32 kelvin), camera and poses (world = model CRS,
metres; `Pose.R_world_from_cam`, centre: the GNSS/INS priors or the orient stage's poses), and
the RGB camera's frames (`load(j)` -> `(H, W, 3)` uint8), camera and poses (the package's
`rgb_camera`, usually more accurate: a photogrammetric block with ground control).
Out: `RgbRegistration`: the corrected TIR poses, the block's rigid transform
`world_from_tir_world` (the rigid ICP's `target_from_source`) and the figures (points per cloud,
TIR-RGB cloud distances before / after, ICP fitness and inlier RMSE, per-frame figures).

Steps: the TIR frames adjusted as one block (`multiview.multiview_block`: tracks from the images,
the bundle adjustment with the GNSS/INS priors; `options.multiview`), then a dense cloud per block
(`dense_stereo.dense_cloud`: SGBM on rectified consecutive pairs, each pair's points triangulated
in its first camera's frame; for TIR with the block's poses, or, without the block or when it is
refused, with each pair's relative orientation from its two images, as the per-frame GNSS/INS
noise is far above what stereo tolerates),
then `icp_register.register_clouds` (point-to-plane, Tukey kernel, coarse to fine from the
priors' alignment: one rigid transform for the block, `R' = R_T · R_world_from_cam`,
`C' = R_T · C + t_T`, applied to the poses the cloud was placed with), then, with `per_frame`,
`frame_icp.register_frames`: every frame's own points (camera frame) registered onto the RGB
cloud, the frames tied by the pairs' relative orientations measured in the images and held by
their priors about a common offset (one rigid transform cannot remove the per-frame GNSS/INS
noise of 0.2 m and the vibration). The per-frame result is refused (the rigid one kept) when a
frame would move more than `max_frame_change_m` / `max_frame_change_deg` from the rigid solution.
`per_frame` is off by default: on the bench drive the TIR pairs' relative orientations from two
views are 0.24–0.52° off (the TIR clouds are bent by that, 0.24–0.32 m from the true surfaces
with true poses), and registering every frame onto the RGB cloud then lowers the cloud distance
while turning the frames away from the truth (rotation error 0.26° -> 0.4–0.8°). It needs TIR
clouds from a multi-view adjusted block; with exact clouds it is tested to a few centimetres.
`orient_with_rgb` is the orient stage's entry.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.georef import prior_poses
from workers.pipeline.geometry.manifest import SequenceManifest
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.reconstruction.dense_stereo import (
    DenseCloud,
    DenseOptions,
    anchored_poses,
    dense_cloud,
    smoothed_centers,
)
from workers.pipeline.reconstruction.frame_icp import FrameIcpOptions, FrameIcpResult, register_frames
from workers.pipeline.reconstruction.icp_register import IcpOptions, IcpResult, nn_distances, register_clouds
from workers.pipeline.reconstruction.multiview import MultiViewBlock, MultiViewOptions, multiview_block

#: TIR: weak, smooth texture and per-frame pose noise -> larger blocks, stricter filters,
#: relative orientation of each pair from the images
TIR_DENSE = DenseOptions(
    block_size=11, uniqueness_ratio=20, speckle_window=200, min_texture=4.0, smooth_positions=True
)
#: TIR after the multi-view block (`multiview`): the adjusted poses as they are (consistent
#: relative orientations and baselines: neither the images' two-view orientation nor smoothing),
#: and a point needs points of another pair near it (`DenseOptions.min_views`: false matches out;
#: bench seed 1: cloud distance 0.116 -> 0.062 m, TIR position 0.125 -> 0.116 m). Not on the
#: two-view fallback: there the ICP corrected the filtered cloud, not the poses (seed 2: distance
#: 0.400 -> 0.080 m while the position error grew 1.10 -> 1.22 m)
TIR_BLOCK_DENSE = replace(TIR_DENSE, refine_relative=False, smooth_positions=False, min_views=2)
#: RGB: rich texture and accurate poses -> the poses as they are (centres smoothed: the relative
#: position of neighbours sets the stereo scale, 5 mm of noise on 1.5 m is 4 cm at 12 m)
RGB_DENSE = DenseOptions(refine_relative=False, block_size=5, min_texture=2.0, smooth_positions=True)


@dataclass(frozen=True)
class RgbRegistrationOptions:
    """Parameters of `register_tir_on_rgb`: the dense clouds of each block and the ICP."""

    tir: DenseOptions = field(default_factory=lambda: TIR_DENSE)  # without the block (or refused)
    multiview: MultiViewOptions | None = field(default_factory=MultiViewOptions)  # None: no block
    tir_block: DenseOptions = field(default_factory=lambda: TIR_BLOCK_DENSE)  # with the block
    rgb: DenseOptions = field(default_factory=lambda: RGB_DENSE)
    icp: IcpOptions = field(default_factory=IcpOptions)
    min_points: int = 500  # per cloud; fewer: no registration (poses unchanged)
    min_fitness: float = 0.3  # below: the ICP is not trusted (poses unchanged)
    per_frame: bool = False  # after the block's rigid ICP, every frame's pose (`frame_icp`)
    frames: FrameIcpOptions = field(default_factory=FrameIcpOptions)
    max_frame_change_m: float = 1.0  # a frame moved farther from the rigid solution: per-frame refused
    max_frame_change_deg: float = 0.6  # 3 × the per-frame attitude prior (0.2°)


@dataclass(frozen=True, eq=False)
class RgbRegistration:
    """Outcome of `register_tir_on_rgb` (see the module docstring).

    Attributes:
        poses: corrected TIR poses (the input poses when `accepted` is False).
        world_from_tir_world: `(4, 4)` rigid transform applied (identity when not accepted).
        accepted: whether the ICP was applied; `reason` says why not.
        n_points_tir / n_points_rgb: points of the filtered dense clouds.
        pairs_tir / pairs_rgb: stereo pairs matched; refined_tir: TIR pairs oriented from images.
        icp: the block's rigid ICP figures (None when a cloud was too small).
        frame_icp: the per-frame registration (None when it did not run or was refused;
            `frame_reason` says why).
        distances_after: mean / median / trimmed-mean TIR-RGB distance (`nn_distances`, every
            point of the TIR cloud, none filtered out) with the final poses, metres.
    """

    poses: tuple[Pose, ...]
    world_from_tir_world: np.ndarray
    accepted: bool
    reason: str
    n_points_tir: int
    n_points_rgb: int
    pairs_tir: int
    pairs_rgb: int
    refined_tir: int
    icp: IcpResult | None
    frame_icp: FrameIcpResult | None = None
    frame_reason: str = ""
    distances_after: tuple[float, float, float] | None = None
    block: MultiViewBlock | None = None

    def figures(self) -> dict[str, Any]:
        """The figures as plain JSON values (for `report.json` and benches)."""
        T = self.world_from_tir_world
        angle = float(np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1.0, 1.0))))
        out: dict[str, Any] = {
            "accepted": self.accepted, "reason": self.reason,
            "points_tir": self.n_points_tir, "points_rgb": self.n_points_rgb,
            "pairs_tir": self.pairs_tir, "pairs_rgb": self.pairs_rgb, "refined_pairs_tir": self.refined_tir,
            "translation_m": T[:3, 3].tolist(), "rotation_deg": angle, "transform": T.tolist(),
        }  # fmt: skip
        if self.icp is not None:
            i = self.icp
            out |= {
                "fitness": i.fitness, "inlier_rmse_m": i.inlier_rmse,
                "mean_distance_before_m": i.mean_before_m, "mean_distance_after_m": i.mean_after_m,
                "median_distance_before_m": i.median_before_m, "median_distance_after_m": i.median_after_m,
                "trimmed_mean_before_m": i.trimmed_mean_before_m,
                "trimmed_mean_after_m": i.trimmed_mean_after_m,
                "observed_directions": i.observed_directions,
            }  # fmt: skip
        if self.block is not None:
            out["multiview"] = self.block.figures()
        out["per_frame"] = self.frame_icp is not None
        out["per_frame_reason"] = self.frame_reason
        if self.frame_icp is not None and self.distances_after is not None:
            f, (mean, med, trim) = self.frame_icp, self.distances_after
            out |= {
                "rigid_mean_distance_after_m": out.get("mean_distance_after_m"),
                "mean_distance_after_m": mean, "median_distance_after_m": med, "trimmed_mean_after_m": trim,
                "frames_with_points": int(np.count_nonzero(f.points_used)),
                "frame_rms_median_m": float(np.nanmedian(f.rms_m)) if np.any(np.isfinite(f.rms_m)) else None,
            }  # fmt: skip
        return out


def corrected_poses(poses: Sequence[Pose], world_from_old: np.ndarray) -> list[Pose]:
    """Poses moved by a rigid world transform `(4, 4)`: `R' = R_T R`, `C' = R_T C + t_T`."""
    R, t = world_from_old[:3, :3], world_from_old[:3, 3]
    return [Pose(R @ p.R_world_from_cam, R @ p.center + t) for p in poses]


def rgb_prior_poses(manifest: SequenceManifest, model_crs: str | None) -> list[Pose]:
    """World poses of the package's RGB frames: their positions / attitudes through the RGB
    mounting, transformed like the TIR frames' (`georef.prior_poses`). Raises `ValueError`
    when the manifest has no `rgb_camera`."""
    rgb = manifest.rgb
    if rgb is None:
        raise ValueError("rgb_camera: the sequence has no second camera")
    shadow = replace(
        manifest, camera=rgb.camera, mounting=rgb.mounting, frames=rgb.frames, imu=None, gcps=None
    )
    return prior_poses(shadow, model_crs)


def register_tir_on_rgb(
    tir_load: Callable[[int], np.ndarray],
    tir_camera: Camera,
    tir_poses: Sequence[Pose],
    rgb_load: Callable[[int], np.ndarray],
    rgb_camera: Camera,
    rgb_poses: Sequence[Pose],
    options: RgbRegistrationOptions = RgbRegistrationOptions(),
) -> RgbRegistration:
    """Method 3 (see the module docstring). Frames are taken in index order."""
    tir = tir_cloud(tir_load, tir_camera, tir_poses, options)
    rgb = dense_cloud(rgb_load, rgb_camera, rgb_poses, options.rgb)
    return replace(register_clouds_of_blocks(tir.cloud, rgb, tir.placed, options), block=tir.block)


@dataclass(frozen=True, eq=False)
class TirCloud:
    """The TIR block's dense cloud (`cloud`), the poses it was placed with (`placed`: what the
    ICP transform corrects) and the multi-view block (None: not run)."""

    cloud: DenseCloud
    placed: list[Pose]
    block: MultiViewBlock | None


def tir_cloud(
    load: Callable[[int], np.ndarray], camera: Camera, poses: Sequence[Pose], options: RgbRegistrationOptions
) -> TirCloud:
    """The TIR frames `load(i)` with their priors `poses` (world) as a dense cloud: with
    `options.multiview`, the frames adjusted as one block first (`multiview.multiview_block`) and
    the cloud made with the adjusted poses (`options.tir_block`); without it, or when the block
    is refused, from the priors with the pairs' two-view orientations (`options.tir`)."""
    block = None if options.multiview is None else multiview_block(load, camera, poses, options.multiview)
    if block is not None and block.accepted:
        start, dense = list(block.poses), options.tir_block
    else:
        start, dense = list(poses), options.tir
    return TirCloud(dense_cloud(load, camera, start, dense), block_poses(start, dense), block)


def orient_with_rgb(
    frames_load: Callable[[int], np.ndarray],
    camera: Camera,
    poses: Sequence[Pose],
    rgb_load: Callable[[int], np.ndarray],
    rgb_camera: Camera,
    rgb_priors: Sequence[Pose],
    options: RgbRegistrationOptions = RgbRegistrationOptions(),
) -> RgbRegistration:
    """The orient stage's entry to method 3: the TIR frames `frames_load(i)`, `i = 0 … F-1` in
    recording order, with `poses` (`F`, world: the calibrated priors), registered onto the RGB
    block (`rgb_load(j)`, `rgb_priors`: the package's `rgb_camera` poses, `rgb_prior_poses`).
    Returns the corrected TIR poses (`accepted`; else the input `poses` unchanged)
    and the figures for `report.json` (`RgbRegistration.figures()`). Rigid ICP of the block, then
    every frame's pose (`options.per_frame`)."""
    reg = register_tir_on_rgb(frames_load, camera, poses, rgb_load, rgb_camera, rgb_priors, options)
    return reg if reg.accepted else replace(reg, poses=tuple(poses))


def block_poses(poses: Sequence[Pose], options: DenseOptions) -> list[Pose]:
    """The poses the dense cloud of a block was placed with: `poses`, with the smoothed centres
    when `options.smooth_positions` (what the ICP transform then corrects)."""
    if not options.smooth_positions:
        return list(poses)
    centers = np.array([p.center for p in poses], dtype=np.float64)
    return anchored_poses(poses, smoothed_centers(centers, options.smooth_window))


def register_clouds_of_blocks(
    tir: DenseCloud, rgb: DenseCloud, tir_poses: Sequence[Pose], options: RgbRegistrationOptions
) -> RgbRegistration:
    """The ICP step of `register_tir_on_rgb` on dense clouds already made."""
    base = dict(
        n_points_tir=len(tir.points), n_points_rgb=len(rgb.points), pairs_tir=len(tir.pairs),
        pairs_rgb=len(rgb.pairs), refined_tir=tir.refined,
    )  # fmt: skip
    if min(len(tir.points), len(rgb.points)) < options.min_points:
        reason = f"too few dense points (tir {len(tir.points)}, rgb {len(rgb.points)} < {options.min_points})"
        return RgbRegistration(tuple(tir_poses), np.eye(4), False, reason, icp=None, **base)
    icp = register_clouds(tir.points, rgb.points, options.icp)
    if icp.fitness < options.min_fitness:
        reason = f"icp fitness {icp.fitness:.2f} < {options.min_fitness}"
        return RgbRegistration(tuple(tir_poses), np.eye(4), False, reason, icp=icp, **base)
    T = icp.target_from_source
    rigid = corrected_poses(tir_poses, T)
    if not options.per_frame or not tir.relative:
        return RgbRegistration(tuple(rigid), T, True, "", icp=icp, **base)
    frame, reason, after = per_frame(tir, rgb, tir_poses, rigid, options)
    poses = frame.poses if frame is not None else tuple(rigid)
    return RgbRegistration(poses, T, True, "", icp=icp, frame_icp=frame, frame_reason=reason,
                           distances_after=after, **base)  # fmt: skip


def frame_points(cloud: DenseCloud, poses: Sequence[Pose]) -> list[np.ndarray]:
    """Each frame's points of a dense cloud in its camera frame `(N_a, 3)` (metres): the cloud's
    points carried by frame `a`, brought back with the pose `poses[a]` they were placed with."""
    return [poses[a].cam_from_world(cloud.points[cloud.frame == a]) for a in range(len(poses))]


def per_frame(
    tir: DenseCloud,
    rgb: DenseCloud,
    placed: Sequence[Pose],
    rigid: Sequence[Pose],
    options: RgbRegistrationOptions,
) -> tuple[FrameIcpResult | None, str, tuple[float, float, float] | None]:
    """The per-frame step: every TIR frame's pose registered from the rigid solution `rigid`
    (`frame_icp.register_frames`, frames tied by the pairs' relative orientations measured in
    the images), the cloud having been placed with `placed`. Returns (result or None when
    refused, the reason, the final TIR-RGB distances over every TIR point)."""
    pts = frame_points(tir, placed)
    rel = [(a, b, R, t) for (a, b), (R, t, ok) in zip(tir.pairs, tir.relative, strict=True) if ok]
    res = register_frames(pts, rigid, rel, rgb.points, options.frames)
    pairs = list(zip(res.poses, rigid, strict=True))
    move = max(float(np.linalg.norm(p.center - q.center)) for p, q in pairs)
    turn = max(_angle_deg(p.R_world_from_cam.T @ q.R_world_from_cam) for p, q in pairs)
    if move > options.max_frame_change_m or turn > options.max_frame_change_deg:
        reason = f"per-frame refused: a frame moved {move:.2f} m / {turn:.2f} deg from the rigid ICP"
        return None, reason, None
    P = np.concatenate([p.world_from_cam(x) for p, x in zip(res.poses, pts, strict=True)])
    d = nn_distances(P, rgb.points, options.icp.report_max_distance_m)
    near = d[d < options.icp.report_max_distance_m]
    trim = float(near.mean()) if len(near) else float("nan")
    return res, "", (float(d.mean()), float(np.median(d)), trim)


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))

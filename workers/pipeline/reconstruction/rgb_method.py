"""Method 3 (Hoegner & Stilla): the TIR block registered onto an RGB block by ICP of dense clouds.

In: the TIR frames (`load(i)` -> `(H, W)` float32 kelvin), camera and poses (world = model CRS,
metres; `Pose.R_world_from_cam`, centre: the GNSS/INS priors or the orient stage's poses), and
the RGB camera's frames (`load(j)` -> `(H, W, 3)` uint8), camera and poses (the package's
`rgb_camera`, usually more accurate: a photogrammetric block with ground control).
Out: `RgbRegistration`: the TIR poses (with the smoothed trajectory's centres when the TIR
dense options smooth positions, as the cloud was placed) corrected by one rigid transform
`world_from_tir_world`
(the ICP's `target_from_source`), and the figures (points per cloud, TIR-RGB cloud distances
before / after, ICP fitness and inlier RMSE).

Steps: a dense cloud per block (`dense_stereo.dense_cloud`: SGBM on rectified consecutive pairs;
for TIR the pairs' relative orientation comes from the images, as its per-frame GNSS/INS noise
is far above what stereo tolerates), then `icp_register.register_clouds` (point-to-plane, Tukey
kernel, coarse to fine from the priors' alignment), and every TIR pose moved by the transform:
`R' = R_T · R_world_from_cam`, `C' = R_T · C + t_T`.
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
from workers.pipeline.reconstruction.icp_register import IcpOptions, IcpResult, register_clouds

#: TIR: weak, smooth texture and per-frame pose noise -> larger blocks, stricter filters,
#: relative orientation of each pair from the images
TIR_DENSE = DenseOptions(
    block_size=11, uniqueness_ratio=20, speckle_window=200, min_texture=4.0, smooth_positions=True
)
#: RGB: rich texture and accurate poses -> the poses as they are (centres smoothed: the relative
#: position of neighbours sets the stereo scale, 5 mm of noise on 1.5 m is 4 cm at 12 m)
RGB_DENSE = DenseOptions(refine_relative=False, block_size=5, min_texture=2.0, smooth_positions=True)


@dataclass(frozen=True)
class RgbRegistrationOptions:
    """Parameters of `register_tir_on_rgb`: the dense clouds of each block and the ICP."""

    tir: DenseOptions = field(default_factory=lambda: TIR_DENSE)
    rgb: DenseOptions = field(default_factory=lambda: RGB_DENSE)
    icp: IcpOptions = field(default_factory=IcpOptions)
    min_points: int = 500  # per cloud; fewer: no registration (poses unchanged)
    min_fitness: float = 0.3  # below: the ICP is not trusted (poses unchanged)


@dataclass(frozen=True, eq=False)
class RgbRegistration:
    """Outcome of `register_tir_on_rgb` (see the module docstring).

    Attributes:
        poses: corrected TIR poses (the input poses when `accepted` is False).
        world_from_tir_world: `(4, 4)` rigid transform applied (identity when not accepted).
        accepted: whether the ICP was applied; `reason` says why not.
        n_points_tir / n_points_rgb: points of the filtered dense clouds.
        pairs_tir / pairs_rgb: stereo pairs matched; refined_tir: TIR pairs oriented from images.
        icp: the ICP figures (None when a cloud was too small).
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
    tir = dense_cloud(tir_load, tir_camera, tir_poses, options.tir)
    rgb = dense_cloud(rgb_load, rgb_camera, rgb_poses, options.rgb)
    return register_clouds_of_blocks(tir, rgb, block_poses(tir_poses, options.tir), options)


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
    return RgbRegistration(tuple(corrected_poses(tir_poses, T)), T, True, "", icp=icp, **base)

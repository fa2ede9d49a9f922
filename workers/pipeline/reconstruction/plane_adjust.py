"""The coregistered reconstruction adjusted once more with its facade points held to the model's
planes: a bundle adjustment whose point-to-plane distances keep the block from bending.

Why: one 7-parameter similarity moves the whole block; what the reconstruction's own adjustment
leaves weakly determined (a straight drive along near-planar facades: a slow rotation drift along
the sequence, the points sliding with it, the ends least constrained) it cannot remove. On the
homogeneous-facade bench drive (`bench/orientation_methods.py --frames 40 --scenes homogeneous`,
seed 1) the rotation errors after the similarity run from 0.12° at the first frame to 0.02° in
the middle while the centres are within 2 cm: the frames at the start miss the model's edges by
1–1.7 px. The distances of the facade points from their planes see that bending (a camera turned
about its centre moves the intersections of its rays in depth as well as along the facade), so
the block adjustment of the sequence orientation (`orientation.bundle.bundle_adjust`: tie points,
model-plane distances, the priors as a common error plus per-frame noise; no model edges) is run
seeded from the coregistered poses and points. `orient` runs it only where the facades fix both
horizontal shift directions: on a single facade the in-plane shift, the scale and the turn about
its normal are left to the per-frame priors, whose noise then bends the block instead.

In: the reconstruction's `Adjusted` part, its coregistered poses and points (model CRS), the
`PlaneAssignment` of the facade fit, the (calibrated) priors with their a-priori σ.
Out: the adjusted poses and points, or None when the adjustment failed (normal system not
positive definite) or fits the ties worse than `plane_adjust_max_sigma0_px`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.bundle import bundle_adjust
from workers.pipeline.orientation.bundle_types import BundleOptions
from workers.pipeline.orientation.priors import frame_noise_covariance
from workers.pipeline.orientation.tracks import Tracks
from workers.pipeline.reconstruction.colmap import Adjusted
from workers.pipeline.reconstruction.options import ReconstructionOptions
from workers.pipeline.reconstruction.planes import PlaneAssignment


@dataclass(frozen=True, eq=False)
class PlaneAdjusted:
    """Result of `adjust_on_planes`: `poses` `{frame: Pose}` and `points` `(K, 3)` (model CRS,
    the rows of `Adjusted.points`), the tie RMS (px) of the inlier observations, the RMS (m) of
    the assigned points' plane distances after the adjustment."""

    poses: dict[int, Pose]
    points: np.ndarray
    tie_rms_px: float
    point_to_plane_rms_m: float

    def to_dict(self) -> dict:
        """The `report.json` figures: tie RMS (px), point-to-plane RMS (m)."""
        return {
            "tie_rms_px": round(self.tie_rms_px, 3),
            "point_to_plane_rms_m": round(self.point_to_plane_rms_m, 3),
        }


def adjust_on_planes(
    camera: Camera,
    caster: RayCaster,
    adj: Adjusted,
    poses: Mapping[int, Pose],
    points: np.ndarray,
    assignment: PlaneAssignment,
    prior: Mapping[int, Pose],
    sig_m: float,
    sig_deg: float,
    options: ReconstructionOptions,
) -> PlaneAdjusted | None:
    """Adjust the coregistered block (module docstring).

    Args:
        camera: interior orientation.
        caster: the scene (unused by the adjustment without edges; `bundle_adjust` takes it).
        adj: the reconstruction part (observations: `obs_track`, `obs_frame`, `obs_uv`).
        poses: `{frame: Pose}` coregistered poses of `adj`'s frames (model CRS).
        points: `(K, 3)` coregistered points, rows as `adj.points`.
        assignment: the facade fit's assignment (indices into `points`, planes).
        prior: the (calibrated) GNSS/INS prior of each frame (model CRS).
        sig_m, sig_deg: a-priori σ of the priors' common error (metres, degrees).
        options: `plane_sigma_m`, `frame_sigma_m`, `frame_sigma_deg` (per-frame prior noise),
            `plane_adjust_tie_sigma_px`, `plane_adjust_max_sigma0_px`.
    """
    frames = sorted(poses)
    normal = np.zeros_like(points)
    offset = np.zeros(len(points))
    normal[assignment.index] = assignment.normal
    offset[assignment.index] = assignment.offset
    row = {int(t): k for k, t in enumerate(adj.track_ids)}
    track = np.array([row[int(t)] for t in adj.obs_track], dtype=np.int64)
    tracks = Tracks(track, adj.obs_frame.copy(), adj.obs_uv.copy(), points.copy(), normal, offset)
    white = np.linalg.inv(frame_noise_covariance(options.frame_sigma_deg, options.frame_sigma_m))
    common = np.linalg.inv(frame_noise_covariance(sig_deg, sig_m))
    bo = BundleOptions(
        edges=False,
        plane_sigma_m=options.plane_sigma_m,
        tie_sigma_px=options.plane_adjust_tie_sigma_px,
        tie_huber_px=2 * options.plane_adjust_tie_sigma_px,
    )
    res = bundle_adjust(
        camera, frames, {}, poses, prior, dict.fromkeys(frames, white), common, tracks, None, caster, bo
    )
    if not res.converged:
        return None
    e = [res.tie_rms_px[f] for f in frames if np.isfinite(res.tie_rms_px.get(f, np.nan))]
    w = [res.ties[f] for f in frames if np.isfinite(res.tie_rms_px.get(f, np.nan))]
    tie_rms = float(np.sqrt(np.average(np.square(e), weights=w))) if sum(w) else float("inf")
    if not tie_rms <= options.plane_adjust_max_sigma0_px:
        return None
    d = assignment.distances(res.points)
    return PlaneAdjusted(dict(res.poses), res.points, tie_rms, float(np.sqrt(np.mean(d**2))))

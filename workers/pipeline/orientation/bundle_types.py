"""The parameters (`BundleOptions`) and the result (`BundleResult`) of the block adjustment
(`orientation.bundle.bundle_adjust`, and its Ceres oracle `orientation.bundle_ceres`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.pose import Pose


@dataclass(frozen=True)
class BundleOptions:
    """Parameters of the bundle adjustment (pixels, metres)."""

    # tie points: standard deviation, Huber threshold (both px); observations beyond
    # `outlier_px` after convergence are dropped
    tie_sigma_px: float = 0.15
    tie_huber_px: float = 0.3
    outlier_px: float = 2.0
    # planes: standard deviation and the Tukey constant of the distance re-weighting (m)
    plane_sigma_m: float = 0.05
    plane_tukey_m: float = 0.5
    # model edges: on/off, weight of the edge normal equations, search radius at the start
    # (shrinks by `radius_decay` to the frame fit's minimum), visibility recomputed every n-th
    # iteration and for the final figures, unless no visible sample moved more than
    # `visibility_reuse_px` in the image since it was last computed (0: always recomputed;
    # hidden-edge removal and sample spacing are a visibility decision, not a derivative)
    edges: bool = True
    edge_weight: float = 1.0
    edge_radius_start_px: float = 16.0
    radius_decay: float = 0.75
    revisibility_every: int = 4
    visibility_reuse_px: float = 0.5
    # Gauss-Newton iterations before and after the outlier removal (undamped: Levenberg damping of
    # the diagonal slowed the weak directions, a tilt traded against a height that only a few
    # inclined edges see, from 0.18 px to 3.6 px after ten iterations; the steps are bounded to
    # `max_step_deg` and `max_step_m` instead; after the outlier removal a frame held off by a
    # mismatched tie comes back by degrees: 4 polish iterations left it moving 0.4 m per step)
    iterations: int = 12
    polish_iterations: int = 8
    max_step_deg: float = 2.0
    max_step_m: float = 1.0
    # tie observations of points nearer than this along the optical axis (or behind), and of tracks
    # with fewer inlier observations in the block, are left out; σ of the points' step damping (m)
    min_depth_m: float = 0.5
    min_track_observations: int = 2
    point_step_sigma_m: float = 100.0
    # a phase has converged when no frame moves by more than this (metres; rotations as the
    # motion they cause at 10 m)
    converged_m: float = 5e-4
    # ... or when no frame moves by more than this share of its own σ (`sqrt(δᵀ S_ff δ)` with the
    # frame's block of the reduced normal matrix: the uncertainty its observations leave it with
    # the other frames held; 0: only `converged_m`). A frame or two of a 120-frame window kept
    # stepping 1-2 cm (0.3-0.8 of their σ) to the iteration caps while the median step was 0.01
    # cm; the 300-frame NRW drive's windows ran 109 of 120 iterations at 0.25 (95 at 1.0), its
    # frames within 1 px of the truth unchanged (0.967)
    converged_sigma: float = 0.25


@dataclass(frozen=True, eq=False)
class BundleResult:
    """Result of `bundle_adjust`.

    Attributes:
        poses: `{frame: Pose}` refined.
        covariance: `{frame: (6, 6)}` of `(ω_cam [rad], dC_world [m])`, variance factor applied.
        ties: `{frame: inlier tie observations}`.
        tie_rms_px: `{frame: RMS of its inlier tie residuals}` (NaN without ties).
        edge_rms_px, edge_support, null_support, matched_edges: per frame that sees model edges,
            at its refined pose (`edge_observations.edge_support`, null shift
            `PriorOptions.null_shift_px`):
            RMS of the inlier edge offsets, support, null support, matched model edges.
        points: `(T, 3)` adjusted track points (world).
        inlier: `(M,)` bool per tie observation of the tracks (of the block's frames).
        sigma0: a-posteriori standard deviation of unit weight of the ties (≥ 1 is applied to
            `covariance`).
        converged: False when a normal system was not positive definite (the iterations stopped
            there; covariances NaN).
    """

    poses: dict[int, Pose]
    covariance: dict[int, np.ndarray]
    ties: dict[int, int]
    tie_rms_px: dict[int, float]
    edge_rms_px: dict[int, float]
    edge_support: dict[int, float]
    null_support: dict[int, float]
    matched_edges: dict[int, int]
    points: np.ndarray
    inlier: np.ndarray
    sigma0: float = 1.0
    converged: bool = True

"""Parameters of fitting one frame's pose to model edges (`frame_fit`), shared by the stages built on it.

`FrameFitOptions` holds the coarse edge-distance search (`coarse`), the 1-D edge search along the
projected edges' normals and its robust weights (`edge_observations`), the iterations and the
acceptance tests of the per-frame fit (`frame_fit`). The joint fit (`common_correction`), the
block orientation (`block`, `bundle`) and the calibration (`calibration`) observe edges with the
same search and weights, so they take these options too. Pixels, metres, degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["FrameFitOptions"]


@dataclass(frozen=True)
class FrameFitOptions:
    """Parameters of the per-frame adjustment (pixels, metres, degrees)."""

    # coarse stage: pyramid level (downsampling factor) of the distance-transform search
    coarse_level: int = 4
    # coarse stage: largest image shift searched, full-resolution pixels
    coarse_radius_px: float = 160.0
    # coarse stage: depth offsets along the optical axis, as shares of the median sample depth ...
    coarse_depth_steps: tuple[float, ...] = (-0.3, -0.15, 0.0, 0.15, 0.3)
    # ... capped at this many metres
    coarse_max_depth_m: float = 6.0
    # coarse stage: penalty per level pixel of shift, in level pixels of mean distance (favours
    # the nearest of equally good minima)
    coarse_shift_penalty: float = 0.01
    # coarse stage: the best candidate must lower the typical (median) score by this share and
    # lie inside the search window, else the start pose is kept
    coarse_min_gain: float = 0.35
    # coarse stage: an image shift is explained by a camera rotation and a camera translation
    # across the optical axis, split by these a-priori standard deviations (a shift of angle θ
    # at depth Z: rotation share σ_r² / (σ_r² + (σ_t / Z)²)) — translation dominates at close
    # range (drives), rotation from far away (flights)
    coarse_rotation_sigma_deg: float = 2.0
    coarse_translation_sigma_m: float = 3.0
    # fine stage: edge search radius along the normal, at the start and at the end, pixels
    edge_radius_start_px: float = 24.0
    edge_radius_min_px: float = 3.0
    # a gradient counts as an edge when its normal component exceeds this share of the ROI's
    # robust gradient scale, and the gradient is within edge_max_angle_deg of the normal
    edge_min_gradient_rel: float = 0.15
    edge_max_angle_deg: float = 30.0
    # among edges on the search line, the strongest wins after a Gaussian distance penalty of
    # this share of the search radius (nearer edges are preferred as the radius shrinks)
    edge_distance_scale: float = 0.6
    # corner search radius, at the start and at the end, pixels
    point_radius_start_px: float = 10.0
    point_radius_min_px: float = 2.5
    # standard deviations of the observations, pixels
    sigma_edge_px: float = 1.0
    sigma_point_px: float = 1.5
    # weight of one edge sample (samples along an edge are correlated), relative to 1/σ²
    edge_sample_weight: float = 0.3
    # Tukey biweight: c = max(tukey_min_px, 4.685 × robust scale of the residuals)
    tukey_min_px: float = 2.0
    # Gauss-Newton iterations of the fine stage
    iterations: int = 12
    # visibility is recomputed at these iterations (pose may have moved)
    revisibility_at: tuple[int, ...] = (4,)
    # acceptance: share of visible edge samples with an image edge within support_px
    min_support: float = 0.5
    support_px: float = 1.5
    # acceptance: RMS of inlier residuals, pixels
    max_rms_px: float = 1.5
    # acceptance: predicted RMS reprojection uncertainty of the building's vertices, pixels
    max_sigma_px: float = 1.0
    # acceptance: at least this many inlier edge samples, and this many distinct edges
    min_edge_inliers: int = 15
    min_edges: int = 2
    # acceptance: largest correction from the start pose (beyond it: a wrong minimum)
    max_correction_m: float = 9.0
    max_correction_deg: float = 8.0
    # fewer visible edge samples than this: no refinement; more than max_samples: thinned evenly
    min_samples: int = 10
    max_samples: int = 400
    # ROI margin around the projected wireframe, pixels (added to the coarse radius)
    roi_margin_px: float = 24.0

"""Coregistration of one frame to one building: coarse edge-distance search, then iterative
robust least squares of the six exterior-orientation parameters.

In: `Camera`, building `Wireframe` (`wireframe`), `RayCaster` over the scene, the frame `(H, W)`
float32 (its `ImageFeatures` are extracted around the projected wireframe, `features`), the
GNSS/INS prior pose with its information matrix, a start pose, `FrameFitOptions`
(`fit_options`). Out: `FrameFit` (refined pose, acceptance, residuals, matches, predicted
reprojection uncertainty).

Pose parameters: a correction `δ = (ω, dC)` with `R_world_from_cam ← R · exp([ω]×)` (ω in the
camera frame, radians) and `C ← C + dC` (world, metres), `geometry.pose_increments`.
Observations (`edge_observations.normal_equations`):

- edge samples of the visible wireframe, each matched by a 1-D search along the projected edge's
  normal for the strongest image gradient parallel to that normal (point-to-line residual),
- model corners matched to the nearest Förstner or segment-intersection point within a search
  radius R (2-D residuals),
- the prior pose as a weighted observation of `δ = 0`.

Weights: class weight of the edge × Tukey biweight of the residual; R shrinks with the fit.
A coarse stage (`coarse.coarse_search`) first minimises the mean truncated distance-transform
value of the projected edge samples (correspondence-free) over depth offsets along the optical
axis and image shifts (`cv2.matchTemplate` on a downsampled pyramid level), so that metres and
degrees of prior error are recovered before the local adjustment.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import apply_delta, bounded_step, pose_delta, project_jacobian
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.coarse import coarse_search
from workers.pipeline.orientation.edge_observations import (
    frame_box,
    matched_edges,
    normal_equations,
    visible_samples,
)
from workers.pipeline.orientation.features import (
    FeatureError,
    FeatureOptions,
    ImageFeatures,
    extract_features,
    with_points,
)
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.wireframe import EdgeOptions, Wireframe

__all__ = ["FrameFit", "fit_frame"]


@dataclass(frozen=True, eq=False)
class FrameFit:
    """Result of fitting one frame to one building.

    Attributes:
        pose: refined pose (the start pose when nothing could be fitted).
        accepted: the refinement passed every acceptance test.
        reason: why it was rejected ("" when accepted).
        rms_px: RMS of inlier residuals (edge distances and corner distances), pixels.
        matches: inlier corner matches + edges with inlier samples.
        support: share of visible edge samples with an image edge within `support_px`.
        sigma_px: predicted RMS reprojection uncertainty of the building's vertices, pixels.
        covariance: `(6, 6)` of `(ω, dC)` (rad, m).
        corner_ids: `(M,)` wireframe vertex indices of matched corners (inliers).
        corner_uv: `(M, 2)` image points they were matched to.
        image_points: `(K, 2)` all extracted interest points (Förstner, intersections) used.
        converged: every acceptance test but the one on `sigma_px` passed (the fit found the
            building; the frame alone may still leave some pose directions open).
        information: `(6, 6)` information of the image observations alone (prior excluded),
            divided by the variance factor.
    """

    pose: Pose
    accepted: bool
    reason: str = ""
    rms_px: float = float("nan")
    matches: int = 0
    support: float = 0.0
    sigma_px: float = float("inf")
    covariance: np.ndarray = field(default_factory=lambda: np.full((6, 6), np.nan))
    corner_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    corner_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    image_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    converged: bool = False
    information: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)))


def fit_frame(
    camera: Camera,
    wireframe: Wireframe,
    raycaster: RayCaster,
    image: np.ndarray,
    prior: Pose,
    prior_info: np.ndarray,
    start: Pose,
    options: FrameFitOptions = FrameFitOptions(),
    edge_options: EdgeOptions = EdgeOptions(),
    feature_options: FeatureOptions = FeatureOptions(),
    coarse: bool = True,
) -> FrameFit:
    """Refine `start` against the frame `image` `(H, W)` float32; `prior` with information
    `prior_info` `(6, 6)` (on `(ω, dC)`, rad⁻², m⁻²) is a weighted observation. See the module
    docstring. Features are computed in a box around the projected wireframe only."""
    vis = visible_samples(wireframe, camera, start, raycaster, edge_options, options.max_samples)
    if len(vis.points) < options.min_samples:
        return FrameFit(pose=start, accepted=False, reason="too few visible model edges")
    margin = (options.coarse_radius_px if coarse else options.edge_radius_start_px) + options.roi_margin_px
    roi = frame_box(camera, start, vis, margin)
    if roi is None:
        return FrameFit(pose=start, accepted=False, reason="building not in the frame")
    try:
        feats = extract_features(image, feature_options, roi, points=False)
    except FeatureError as exc:
        return FrameFit(pose=start, accepted=False, reason=str(exc))
    pose = start
    if coarse:
        pose = coarse_search(camera, start, vis, feats, options)
        vis2 = visible_samples(wireframe, camera, pose, raycaster, edge_options, options.max_samples)
        if len(vis2.points) >= options.min_samples:
            vis = vis2
    box = frame_box(camera, pose, vis, options.edge_radius_start_px + options.point_radius_start_px)
    if box is not None:
        feats = with_points(feats, box, feature_options)
    points = feats.points
    rms_prev = np.inf
    sig_e2 = options.sigma_edge_px**2
    sig_p2 = options.sigma_point_px**2
    for it in range(options.iterations):
        if it in options.revisibility_at:
            vis2 = visible_samples(wireframe, camera, pose, raycaster, edge_options, options.max_samples)
            if len(vis2.points) >= options.min_samples:
                vis = vis2
        R_e = max(options.edge_radius_min_px, min(options.edge_radius_start_px * 0.8**it, 3 * rms_prev + 1))
        R_p = max(options.point_radius_min_px, min(options.point_radius_start_px * 0.8**it, 3 * rms_prev + 1))
        H, g, w_e, off, _, rc, wc, _ = normal_equations(
            camera, pose, vis, feats, points, R_e, R_p, prior, prior_info, options
        )
        try:
            delta = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        delta = bounded_step(delta, 3.0, 2.0)  # a single step: 3 degrees, 2 metres (linearisation)
        pose = apply_delta(pose, delta)
        inl = w_e > 0
        res = np.concatenate([off[inl], np.linalg.norm(rc[wc > 0], axis=1)]) if len(rc) else off[inl]
        rms_prev = float(np.sqrt(np.mean(res**2))) if len(res) else np.inf
        small = np.linalg.norm(delta[:3]) < 5e-5 and np.linalg.norm(delta[3:]) < 5e-3
        if small and R_e <= options.edge_radius_min_px + 1e-9:
            break
    fit = _evaluate(
        camera, wireframe, raycaster, feats, prior, prior_info, start, pose, options, edge_options, sig_e2,
        sig_p2,
    )
    return replace(fit, image_points=points)


def _evaluate(
    camera: Camera,
    wireframe: Wireframe,
    raycaster: RayCaster,
    feats: ImageFeatures,
    prior: Pose,
    prior_info: np.ndarray,
    start: Pose,
    pose: Pose,
    options: FrameFitOptions,
    edge_options: EdgeOptions,
    sig_e2: float,
    sig_p2: float,
) -> FrameFit:
    """Residuals, support, covariance and the acceptance tests at the final pose."""
    vis = visible_samples(wireframe, camera, pose, raycaster, edge_options, options.max_samples)
    if len(vis.points) < options.min_samples:
        return FrameFit(pose=start, accepted=False, reason="model left the frame")
    R_min = options.edge_radius_min_px
    H, _, w_e, off, found, rc, wc, idx = normal_equations(
        camera, pose, vis, feats, feats.points, R_min, options.point_radius_min_px, prior, prior_info, options
    )
    near = found & (np.abs(off) <= options.support_px)
    support = float(np.sum(vis.weight * near) / max(np.sum(vis.weight), 1e-12))
    inl_e = w_e > 0
    inl_c = wc > 0
    res = np.concatenate([off[inl_e], np.linalg.norm(rc[inl_c], axis=1)])
    rms = float(np.sqrt(np.mean(res**2))) if len(res) else float("inf")
    n_edges = matched_edges(vis.edge, near, len(wireframe.edges))
    matches = int(inl_c.sum()) + n_edges
    # a-posteriori variance factor (unit weight), never below 1
    chi2 = float(np.sum(w_e * off**2) * sig_e2 / max(options.edge_sample_weight, 1e-9))
    chi2 += float(np.sum(wc * np.sum(rc**2, axis=1)))
    dof = max(int(inl_e.sum()) + 2 * int(inl_c.sum()) - 6, 1)
    s0 = max(1.0, chi2 / dof)
    try:
        cov = np.linalg.inv(H) * s0
    except np.linalg.LinAlgError:
        return FrameFit(pose=start, accepted=False, reason="singular normal equations")
    Xv = wireframe.vertices
    uvv, zv, Jv = project_jacobian(camera, pose, Xv)
    inside = (zv > 0.5) & camera.in_image(uvv)
    if not inside.any():
        inside = zv > 0.5
    var = np.einsum("nki,ij,nkj->n", Jv[inside], cov, Jv[inside])
    sigma_px = float(np.sqrt(np.mean(var))) if inside.any() else float("inf")
    d = pose_delta(start, pose)
    reason = ""
    determined = sigma_px <= options.max_sigma_px
    if support < options.min_support:
        reason = f"edge support {support:.2f} < {options.min_support}"
    elif rms > options.max_rms_px:
        reason = f"rms {rms:.2f} px > {options.max_rms_px}"
    elif int(inl_e.sum()) < options.min_edge_inliers or n_edges < options.min_edges:
        reason = f"too few inliers ({int(inl_e.sum())} samples, {n_edges} edges)"
    elif np.linalg.norm(d[3:]) > options.max_correction_m or np.degrees(np.linalg.norm(d[:3])) > \
            options.max_correction_deg:
        reason = "correction beyond the plausible range"
    converged = not reason
    if converged and not determined:
        reason = f"pose not determined: sigma {sigma_px:.2f} px > {options.max_sigma_px}"
    return FrameFit(
        pose=pose,
        converged=converged,
        information=(H - prior_info) / s0,
        accepted=not reason,
        reason=reason,
        rms_px=rms,
        matches=matches,
        support=support,
        sigma_px=sigma_px,
        covariance=cov,
        corner_ids=vis.corners[inl_c] if len(wc) else np.zeros(0, int),
        corner_uv=feats.points[idx[inl_c]] if len(wc) else np.zeros((0, 2)),
    )

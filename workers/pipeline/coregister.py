"""Per-building orientation: coregister every frame that sees a building to the building model.

In: `Camera`, the top-level `Building` (parts included), a `RayCaster` over the building and its
neighbours (whole-scene hidden-edge removal), frame indices, a `FrameSource`, the GNSS/INS prior
pose per frame with the manifest's `Accuracy`, options, optional frame times (seconds).
Out: `{frame: RefinedPose}` with status `"refined"` or `"prior"`.

Method (after Avbelj, Iwaszczuk, Stilla & Oštir 2012, extended):

1. per frame: model wireframe with hidden edges removed (`model_edges`), Förstner points, LSD
   segments and their intersections, gradients and an edge distance pyramid (`features`);
   coarse correspondence-free search on edge distances, then iterative robust least squares of
   the six exterior-orientation parameters with the prior as a weighted observation, search
   radii shrinking (`coregister_frame`); accepted only when well determined;
2. sequence level: corrections `δ = (ω_cam, dC_world)` of consecutive frames are strongly
   correlated (constant boresight error, slow GNSS drift). A robust, time-weighted median of the
   accepted corrections predicts each frame's correction. Accepted frames that disagree with
   their neighbours' prediction by more than a gate (pixels on the building) are treated as
   failures. Failures are fitted again from the predicted pose with a tight prior (the
   neighbours' scatter). A frame that still fails **inherits** the prediction, with status
   `"refined"` only when the prediction is well supported: at least `inherit_min_neighbours`
   accepted frames within the window, on both sides in time (interpolation, not extrapolation),
   and their scatter projected onto the building below `inherit_max_scatter_px`. Otherwise the
   frame keeps its prior pose with status `"prior"`.

`matches` counts inlier corner matches plus edges with at least half of their visible samples
matched; `rms_px` is the RMS of inlier residuals (edge-normal distances and corner distances).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from workers.pipeline.camera import Camera
from workers.pipeline.citymodel import Building
from workers.pipeline.coregister_frame import (
    FrameFit,
    FrameFitOptions,
    apply_delta,
    fit_frame,
    pose_delta,
)
from workers.pipeline.features import FeatureError, FeatureOptions, extract_features
from workers.pipeline.model_edges import (
    EdgeOptions,
    Wireframe,
    WireframeError,
    building_wireframe,
    visible_wireframe,
)
from workers.pipeline.pose import Pose
from workers.pipeline.raycast import RayCaster
from workers.pipeline.sequence import Accuracy, FrameSource

__all__ = ["CoregisterOptions", "RefinedPose", "prior_information", "refine_building"]


@dataclass(frozen=True)
class CoregisterOptions:
    """All parameters of the per-building orientation."""

    # image features (Förstner, LSD, intersections, edge distance pyramid)
    features: FeatureOptions = field(default_factory=FeatureOptions)
    # model wireframe and its visibility
    edges: EdgeOptions = field(default_factory=EdgeOptions)
    # per-frame adjustment and acceptance
    fit: FrameFitOptions = field(default_factory=FrameFitOptions)
    # a-priori standard deviations when the manifest has no `accuracy` (metres, degrees)
    default_position_sigma_m: float = 2.0
    default_attitude_sigma_deg: float = 1.0
    # the prior's standard deviations are multiplied by this and floored (the manifest's accuracy
    # does not cover the unknown boresight misalignment of several degrees)
    prior_sigma_scale: float = 2.0
    position_sigma_floor_m: float = 1.0
    attitude_sigma_floor_deg: float = 2.0
    # sequence level: time window (seconds) and Gaussian time scale of the neighbour prediction;
    # without times, frame indices are used as seconds
    window_s: float = 4.0
    time_sigma_s: float = 1.5
    # an accepted frame deviating from its neighbours' prediction by more than
    # max(outlier_gate_px, outlier_gate_sigma × their scatter) on the building is refitted
    outlier_gate_px: float = 4.0
    outlier_gate_sigma: float = 3.0
    # second pass: standard deviation floors of the neighbour prediction (metres, degrees)
    predict_sigma_floor_m: float = 0.3
    predict_sigma_floor_deg: float = 0.3
    # inheritance of the neighbours' correction (see the module docstring)
    inherit_min_neighbours: int = 3
    inherit_max_scatter_px: float = 2.0
    # run the second pass and inheritance at all
    sequence: bool = True


@dataclass(frozen=True, eq=False)
class RefinedPose:
    """The orientation of one frame against one building (`status` "refined" or "prior")."""

    frame: int
    pose: Pose
    status: str
    rms_px: float
    matches: int


def prior_information(prior: Pose, accuracy: Accuracy | None, options: CoregisterOptions) -> np.ndarray:
    """Information matrix `(6, 6)` of the prior on `δ = (ω_cam [rad], dC_world [m])`.

    Position σ east, north, up from `accuracy.position_m`; attitude σ roll, pitch, heading
    taken about the world's horizontal axes (roll, pitch, the larger of the two) and the vertical
    (heading), rotated into the camera frame. Both scaled by `prior_sigma_scale` and floored.
    """
    if accuracy is None:
        sp = np.full(3, options.default_position_sigma_m)
        sa = np.full(3, options.default_attitude_sigma_deg)
    else:
        sp = np.broadcast_to(np.asarray(accuracy.position_m, dtype=np.float64), (3,))
        sa = np.broadcast_to(np.asarray(accuracy.attitude_deg, dtype=np.float64), (3,))
    sp = np.maximum(sp * options.prior_sigma_scale, options.position_sigma_floor_m)
    sa = np.maximum(sa * options.prior_sigma_scale, options.attitude_sigma_floor_deg)
    h = max(sa[0], sa[1])
    cov_w = np.diag(np.radians([h, h, sa[2]]) ** 2)
    R = prior.R_world_from_cam
    info = np.zeros((6, 6))
    info[:3, :3] = np.linalg.inv(R.T @ cov_w @ R)
    info[3:, 3:] = np.diag(1.0 / sp**2)
    return info


def _diag_information(sigma_rad: float, sigma_m: float) -> np.ndarray:
    return np.diag([sigma_rad**-2] * 3 + [sigma_m**-2] * 3)


def _roi(camera: Camera, pose: Pose, wireframe: Wireframe, raycaster: RayCaster, margin: float,
         options: CoregisterOptions) -> tuple[int, int, int, int] | None:
    """Pixel box around the visible wireframe at `pose`, grown by `margin` px; None when nothing is seen."""
    vis = visible_wireframe(wireframe, camera, pose, raycaster, options.edges)
    if len(vis.points) < options.fit.min_samples:
        return None
    uv, _ = pose.project(camera, vis.points)
    lo = np.floor(uv.min(axis=0) - margin)
    hi = np.ceil(uv.max(axis=0) + margin) + 1
    u0, v0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
    u1, v1 = min(int(hi[0]), camera.width), min(int(hi[1]), camera.height)
    if u1 - u0 < 16 or v1 - v0 < 16:
        return None
    return u0, v0, u1, v1


def _fit(camera: Camera, wireframe: Wireframe, raycaster: RayCaster, image: np.ndarray, prior: Pose,
         info: np.ndarray, start: Pose, coarse: bool, options: CoregisterOptions) -> FrameFit:
    fo = options.fit
    margin = (fo.coarse_radius_px if coarse else fo.edge_radius_start_px) + fo.roi_margin_px
    roi = _roi(camera, start, wireframe, raycaster, margin, options)
    if roi is None:
        return FrameFit(pose=start, accepted=False, reason="building not visible")
    try:
        feats = extract_features(image, options.features, roi)
    except FeatureError as exc:
        return FrameFit(pose=start, accepted=False, reason=str(exc))
    return fit_frame(
        camera, wireframe, raycaster, feats, prior, info, start, fo, options.edges, coarse=coarse
    )


def _reprojection_px(camera: Camera, a: Pose, b: Pose, X: np.ndarray) -> float:
    """RMS pixel distance of points `X` `(N, 3)` projected with poses `a` and `b` (in front of both)."""
    ua, za = a.project(camera, X)
    ub, zb = b.project(camera, X)
    ok = (za > 0.5) & (zb > 0.5) & np.isfinite(ua).all(axis=1) & np.isfinite(ub).all(axis=1)
    if not ok.any():
        return float("inf")
    return float(np.sqrt(np.mean(np.sum((ua[ok] - ub[ok]) ** 2, axis=1))))


def _predict(
    j: int, times: np.ndarray, deltas: np.ndarray, accepted: np.ndarray, options: CoregisterOptions
) -> tuple[np.ndarray, np.ndarray, int, bool] | None:
    """Robust time-weighted median of the accepted corrections around frame `j`, leaving `j` out.

    Returns (prediction `(6,)`, robust scatter `(6,)`, number of neighbours, neighbours on both
    sides) or None when no accepted neighbour lies within the window.
    """
    dt = times - times[j]
    nb = accepted & (np.abs(dt) <= options.window_s)
    nb[j] = False
    k = np.nonzero(nb)[0]
    if len(k) == 0:
        return None
    w = np.exp(-0.5 * (dt[k] / options.time_sigma_s) ** 2)
    pred = np.array([_weighted_median(deltas[k, c], w) for c in range(6)])
    dev = np.abs(deltas[k] - pred)
    scatter = 1.4826 * np.array([_weighted_median(dev[:, c], w) for c in range(6)])
    both = bool(np.any(dt[k] < 0) and np.any(dt[k] > 0))
    return pred, scatter, len(k), both


def _weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    order = np.argsort(x)
    cw = np.cumsum(w[order])
    return float(x[order][np.searchsorted(cw, 0.5 * cw[-1])])


def refine_building(
    camera: Camera,
    building: Building,
    raycaster: RayCaster,
    frames: Sequence[int],
    frame_source: FrameSource,
    prior: Mapping[int, Pose],
    accuracy: Accuracy | None,
    options: CoregisterOptions = CoregisterOptions(),
    times: Mapping[int, float] | None = None,
) -> dict[int, RefinedPose]:
    """Refine the pose of every frame in `frames` against `building` (see the module docstring).

    Args:
        camera: interior orientation.
        building: the top-level building being oriented (parts included).
        raycaster: built over the building and its neighbours (hidden-edge removal).
        frames: frame indices that see the building, in recording order.
        frame_source: `load(i) -> (H, W)` float32 physical values.
        prior: GNSS/INS camera pose per frame (world = model CRS).
        accuracy: a-priori standard deviations of the GNSS/INS solution (None: option defaults).
        options: all parameters.
        times: frame times in seconds for the sequence level (default: the frame index).

    Returns:
        frame index -> `RefinedPose`; `pose` is the prior when `status` is `"prior"`.
    """
    frames = list(frames)
    out: dict[int, RefinedPose] = {}
    if not frames:
        return out
    try:
        wf = building_wireframe(building, options.edges)
    except WireframeError:
        return {i: RefinedPose(i, prior[i], "prior", float("nan"), 0) for i in frames}
    images: dict[int, np.ndarray] = {}
    fits: list[FrameFit] = []
    for i in frames:
        img = frame_source.load(i)
        info = prior_information(prior[i], accuracy, options)
        fits.append(_fit(camera, wf, raycaster, img, prior[i], info, prior[i], True, options))
        if not fits[-1].accepted and options.sequence:
            images[i] = img  # kept for the second pass (failures only)
    accepted = np.array([f.accepted for f in fits])
    t = np.array([float(times[i]) if times is not None else float(i) for i in frames])
    deltas = np.array([pose_delta(prior[i], f.pose) for i, f in zip(frames, fits, strict=True)])
    X = wf.vertices
    final: list[tuple[Pose, str, float, int]] = []
    for j, i in enumerate(frames):
        f = fits[j]
        pred = _predict(j, t, deltas, accepted, options) if options.sequence else None
        if f.accepted:
            if pred is None:
                final.append((f.pose, "refined", f.rms_px, f.matches))
                continue
            p_pose = apply_delta(prior[i], pred[0])
            spread = _reprojection_px(camera, p_pose, apply_delta(p_pose, pred[1]), X)
            gap = _reprojection_px(camera, f.pose, p_pose, X)
            if gap <= max(options.outlier_gate_px, options.outlier_gate_sigma * spread):
                final.append((f.pose, "refined", f.rms_px, f.matches))
                continue
            if i not in images:
                images[i] = frame_source.load(i)
        if pred is None:
            final.append((prior[i], "prior", f.rms_px, f.matches))
            continue
        delta, scatter, n_nb, both = pred
        start = apply_delta(prior[i], delta)
        s_rot = max(float(np.max(scatter[:3])), np.radians(options.predict_sigma_floor_deg))
        s_pos = max(float(np.max(scatter[3:])), options.predict_sigma_floor_m)
        info = _diag_information(2 * s_rot, 2 * s_pos)
        f2 = _fit(camera, wf, raycaster, images[i], start, info, start, False, options)
        if f2.accepted:
            final.append((f2.pose, "refined", f2.rms_px, f2.matches))
            continue
        spread = _reprojection_px(camera, start, apply_delta(start, scatter), X)
        if n_nb >= options.inherit_min_neighbours and both and spread <= options.inherit_max_scatter_px:
            final.append((start, "refined", float("nan"), 0))
        else:
            final.append((prior[i], "prior", f.rms_px, f.matches))
    for i, (pose, status, rms, matches) in zip(frames, final, strict=True):
        out[i] = RefinedPose(frame=i, pose=pose, status=status, rms_px=float(rms), matches=int(matches))
    return out

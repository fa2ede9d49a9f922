"""Per-building orientation: coregister every frame that sees a building to the building model.

In: `Camera`, the top-level `Building` (parts included), a `RayCaster` over the building and its
neighbours (whole-scene hidden-edge removal), frame indices, a `FrameSource`, the GNSS/INS prior
pose per frame with the manifest's `Accuracy`, options, optional frame times (seconds).
Out: `{frame: RefinedPose}` with status `"refined"` or `"prior"`.

Method (after Avbelj, Iwaszczuk, Stilla & Oštir 2012, extended):

0b. when the sequence orientation ran (`orient_sequence`: tracks and a bundle adjustment of the
   whole sequence in blocks against every building near the cameras, drives), the building's
   frames take its poses where the building's own edges confirm them and their covariance,
   projected onto the building, is small enough (`coregister_block.refine_from_sequence`); when
   the building's edges confirm them nowhere, the steps below run from the priors.

0. when the priors come from an accepted sequence calibration (`calibrate`; options from
   `calibrated_options`), the common error is already removed: a probe of frames decides whether
   frames orient alone (flights: step 1 per frame, then 3 and 4) or not (close-range drives: the
   block orientation 2c from the calibrated priors); steps 2 and the wide searches are skipped.

1. per frame (`coregister_frame`): the building's wireframe with hidden edges removed by ray
   casting through the whole scene (`model_edges`); Förstner points, LSD segments and their
   intersections, gradients and an edge-distance pyramid (`features`); iterative robust least
   squares (Tukey) of the six exterior-orientation parameters from edge-normal distances (1-D
   gradient search along each projected edge sample) and corner-to-point matches within a
   shrinking search radius R, the prior pose a weighted observation; accepted only when well
   determined (edge support, inlier RMS, inliers and edges, predicted reprojection uncertainty
   of the building ≤ `fit.max_sigma_px`, correction in a plausible range).
2. **joint coarse search** (`coregister_sequence`, `coregister_coarse`): the correspondence-free
   edge-distance score maps (image shift × roll × depth) of up to `joint_coarse_max_frames`
   frames are averaged, using the wireframe of the whole scene of the ray caster (building and
   neighbours: a row of similar houses is not ambiguous); when the minimum is distinct, the
   common correction (a rotation plus a translation across the optical axis, split by their
   a-priori sizes) is applied to every prior and pass 1 is centred on it. Else each frame runs
   its own coarse search (kept only when distinct, too).
2b. **joint fine adjustment** (`coregister_joint`, when the joint coarse search finds no
   distinct minimum, as on close-range drives): ONE common correction of all frames plus small
   per-frame deviations, adjusted from the stacked edge observations of every frame against the
   scene wireframe (an oriented-gradient search over common image shifts first). When accepted,
   the block orientation 2c starts from each frame's jointly corrected pose; if the block is
   rejected, pass 1 is centred on those poses, and a frame still at its prior after steps 3 and
   4 takes its jointly corrected pose with status `"refined"` when it lies in time between frames
   whose edge support confirms the correction and the common correction's uncertainty projected
   onto the building is ≤ `joint_max_sigma_px`.
2c. **block orientation** (`coregister_block`, close-range drives): feature tracks over the
   facades (`tracks`) and a bundle adjustment of all the building's frames with the track points
   on the model's planes, the scene's model edges and the priors (`bundle`; Hoegner & Stilla,
   method 2). A frame is `"refined"` when the block found the model and the frame's own
   uncertainty, projected onto the building, is ≤ `block.max_sigma_px`.
3. sequence level: corrections `δ = (ω_cam, dC_world)` of consecutive frames are strongly
   correlated (constant boresight error, slow GNSS drift). Frames that converged (found the
   building, whether or not alone they determine the pose) give each frame a **prediction**: the
   information-weighted, time-weighted mean of its neighbours' corrections (outliers gated). A
   frame accepted in pass 1 and consistent with its prediction keeps its fit; every other frame
   is fitted again (pass 2) with the prediction as its prior (covariance: the mean's plus the
   per-frame noise `frame_sigma_*`), which determines frames that see only one or two edges.
   **Inheritance rule**: a frame that still fails takes the predicted pose with status
   `"refined"` only when at least `inherit_min_neighbours` converged neighbours lie within the
   window on both sides in time (interpolation, never extrapolation) and the prediction's own
   uncertainty projected onto the building is ≤ `inherit_max_sigma_px`; otherwise it keeps its
   prior with status `"prior"`. `rms_px` is NaN and `matches` 0 for an inherited pose.
4. **scene fallback**: the pose error belongs to the frame, not to a building, so frames the
   building alone cannot orient (occluded, tiny, few edges) go through steps 1 and 3 again with
   the wireframe of the whole scene of the unit; the result is taken when accepted.

All frames of the building are held in memory during the call (`frame_source.load` once each).

`matches` counts inlier corner matches plus edges with at least half of their visible samples
matched; `rms_px` is the RMS of inlier residuals (edge-normal distances and corner distances).
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.manifest import Accuracy, FrameSource
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import apply_delta, pose_delta
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.block import (
    BlockOptions,
    UnitSequence,
    refine_block,
    refine_from_sequence,
    sigma_px,
)
from workers.pipeline.orientation.coarse import apply_coarse, joint_coarse
from workers.pipeline.orientation.common_correction import JointOptions, joint_fit
from workers.pipeline.orientation.features import FeatureError, FeatureOptions, extract_features
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.frame_fit import FrameFit, fit_frame
from workers.pipeline.orientation.neighbours import predict
from workers.pipeline.orientation.priors import PriorOptions, frame_noise_covariance, prior_information
from workers.pipeline.orientation.wireframe import (
    EdgeOptions,
    Wireframe,
    WireframeError,
    building_wireframe,
    mesh_wireframe,
    visible_wireframe,
)
from workers.pipeline.results import RefinedPose

__all__ = ["CoregisterOptions", "RefinedPose", "calibrated_options", "prior_information", "refine_building"]


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
    # joint coarse search over all frames of the building (common boresight/position error) ...
    joint_coarse: bool = True
    # ... at most this many frames (evenly spread) take part ...
    joint_coarse_max_frames: int = 16
    # ... on this pyramid level (full-resolution pixels per level pixel; the frames are first
    # downsampled by `joint_coarse_downsample`), over image shifts up to this radius (pixels;
    # model samples up to this far outside the frame take part) and these depth offsets (shares
    # of the median depth)
    joint_coarse_level: int = 8
    joint_coarse_downsample: int = 2
    joint_coarse_radius_px: float = 320.0
    joint_coarse_depth_steps: tuple[float, ...] = (0.0,)
    # ... with the wireframe of the whole scene of the ray caster (the building and its
    # neighbours: a row of similar houses is no longer ambiguous) or of the building alone ...
    joint_coarse_scene: bool = True
    # ... the minimum must lower the typical mean edge distance by this share, else no joint
    # correction is applied and every frame searches on its own ...
    joint_coarse_min_gain: float = 0.35
    # ... up to this many distinct minima, verified by the fine stage on `verify_frames` frames
    # with the scene wireframe (the best confirmed one is applied) ...
    joint_coarse_candidates: int = 3
    verify_frames: int = 3
    # ... and rolls about the optical axis (degrees; boresight errors of several degrees)
    joint_coarse_rolls_deg: tuple[float, ...] = (-8.0, -6.0, -4.0, -2.0, 0.0, 2.0, 4.0, 6.0, 8.0)
    # per-frame coarse search radius after the joint one, pixels (0: none; the per-frame search
    # sees one building only and may jump to a similar neighbour)
    frame_coarse_radius_px: float = 0.0
    # when the joint coarse search finds no distinct minimum (close-range drives: vertical
    # corners, window rows), ONE common correction of all frames is adjusted from the stacked
    # edge observations of every frame against the scene wireframe (`coregister_joint`); when
    # accepted, pass 1 is centred on it, and a frame still at its prior takes the jointly
    # corrected pose with status "refined" when its own edge support there reaches
    # `fit.min_support` and the joint uncertainty projected onto the building is
    # ≤ `joint_max_sigma_px` (the common part of the error is then known; what a frame alone
    # cannot observe of its own white noise stays, e.g. the height of a frame that sees only
    # vertical corners)
    joint_fine: bool = True
    joint_max_sigma_px: float = 3.0
    joint: JointOptions = field(default_factory=JointOptions)
    # close-range drives: the building's frames oriented as one block (feature tracks and a
    # bundle adjustment with the model: `coregister_block`) from the calibrated priors or from
    # the joint correction, or taken from the sequence orientation when it ran (step 0b); when
    # the block is rejected, the frames go on one by one. Off: neither
    block_orientation: bool = True
    block: BlockOptions = field(default_factory=BlockOptions)
    # per-frame deviation of a frame's correction from its neighbours' and from the common
    # correction (white noise, vibration), and the null shift of the edge-support test: one
    # `PriorOptions` for the frames, the joint fit and the block orientation
    prior: PriorOptions = field(default_factory=PriorOptions)
    # neighbours further than this (Mahalanobis², per degree of freedom) from the prediction are
    # outliers; an accepted frame this far from its prediction is refitted
    outlier_gate: float = 9.0
    # the regulariser of the prediction: this share of the prior's information
    prediction_regulariser: float = 0.05
    # inheritance of the neighbours' correction (see the module docstring)
    inherit_min_neighbours: int = 3
    inherit_max_sigma_px: float = 1.0
    # run the sequence level (second pass, inheritance) at all ...
    sequence: bool = True
    # ... and only when at least this many frames converged in pass 1 (else there is nothing
    # to predict from)
    min_converged_frames: int = 2
    # frames still at their prior are oriented (passes 1, 2, inheritance) against the whole
    # scene of the ray caster, the building and its neighbours
    scene_fallback: bool = True
    # the priors come from an accepted sequence calibration (`calibrate`): the common error is
    # already removed, so no joint coarse search and no coarse search of the joint fine stage
    calibrated: bool = False
    # ... then the joint adjustment runs only when fewer than this share of a probe of frames
    # (evenly spread) is refined on its own
    calibrated_joint_below: float = 0.5
    calibrated_probe_frames: int = 5


def calibrated_options(options: CoregisterOptions, accuracy_floor_m: float = PriorOptions.frame_sigma_m,
                       accuracy_floor_deg: float = PriorOptions.frame_sigma_deg) -> CoregisterOptions:
    """`options` for priors from an accepted sequence calibration: no joint coarse search and a
    narrow one in the joint fine stage, the prior's σ floors lowered to the per-frame deviations
    (metres, degrees; default: those of `PriorOptions`)."""
    # a narrow joint search stays: a calibration from a short sequence can leave a degree of pan
    # (drives: pan and a lateral offset are nearly interchangeable along one street)
    joint = replace(options.joint, coarse_radius_px=64.0, translation_max_m=1.0, translation_step_m=0.5,
                    candidates=1, translation_candidates=1)
    return replace(options, calibrated=True, joint_coarse=False, joint=joint,
                   prior_sigma_scale=1.0, position_sigma_floor_m=accuracy_floor_m,
                   attitude_sigma_floor_deg=accuracy_floor_deg)


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
    sequence: UnitSequence | None = None,
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
        sequence: the sequence orientation's poses, covariances and tracks for `frames`
            (`orient_sequence`): the building's own refinement starts from them (step 0b).

    Returns:
        frame index -> `RefinedPose`; `pose` is the prior when `status` is `"prior"`.
    """
    frames = list(frames)
    if not frames:
        return {}
    try:
        wf = building_wireframe(building, options.edges)
    except WireframeError:
        return {i: RefinedPose(i, prior[i], "prior", float("nan"), 0) for i in frames}
    images = {i: frame_source.load(i) for i in frames}
    if sequence is not None and options.block_orientation:
        got, reason = refine_from_sequence(camera, wf, raycaster, frames, images, prior, sequence,
                                           options.block, options.fit, options.edges, options.features,
                                           options.prior)
        if not reason:
            return got
    infos = {i: prior_information(prior[i], accuracy, options) for i in frames}
    starts = dict(prior)
    fo = options.fit
    scene_wf = None
    has_mesh = getattr(raycaster, "mesh", None) is not None
    if (options.joint_coarse_scene or options.scene_fallback) and has_mesh:
        with contextlib.suppress(WireframeError):
            scene_wf = mesh_wireframe(raycaster.mesh, options.edges)
    coarse = True
    common = None
    if options.joint_coarse:
        coarse_wf = scene_wf if (options.joint_coarse_scene and scene_wf is not None) else wf
        found = _joint_coarse(camera, coarse_wf, raycaster, frames, images, prior, options)
        if found:
            fo_v = replace(fo, coarse_radius_px=options.frame_coarse_radius_px)
            common = _verify(camera, coarse_wf, raycaster, frames, images, prior, infos, found, fo_v, options)
            # the common correction is a sequence-level estimate: pass 1 is centred on it
            starts = {i: apply_coarse(camera, prior[i], common, options.fit) for i in frames}
            fo = replace(fo, coarse_radius_px=options.frame_coarse_radius_px)
            coarse = options.frame_coarse_radius_px > 0
    t = {i: float(times[i]) if times is not None else float(i) for i in frames}
    block = options.block_orientation and scene_wf is not None
    if options.calibrated:
        # calibrated priors: every frame on its own (flights), unless most frames of a probe do not
        # determine their pose alone (close drives): then the block orientation
        n = min(len(frames), options.calibrated_probe_frames)
        probe = [frames[k] for k in np.unique(np.linspace(0, len(frames) - 1, n).round().astype(int))]
        ok = [fit_frame(camera, wf, raycaster, images[i], starts[i], infos[i], starts[i], fo, options.edges,
                        options.features, coarse=False).accepted for i in probe]
        if np.mean(ok) >= options.calibrated_joint_below:
            out = _orient(camera, wf, raycaster, frames, images, prior, starts, infos, t, fo, False, options)
            rest = [i for i in frames if out[i].status == "prior"]
            if options.scene_fallback and scene_wf is not None and rest:
                scene = _orient(camera, scene_wf, raycaster, rest, images, prior, starts, infos, t, fo, False,
                                options)
                out.update({i: r for i, r in scene.items() if r.status == "refined"})
            return out
        if block:
            got = _block(camera, wf, scene_wf, raycaster, frames, images, prior, starts, infos, options)
            if got is not None:
                return got
    joint = None
    if options.joint_fine and common is None and scene_wf is not None:
        jf = joint_fit(camera, scene_wf, raycaster, frames, images, prior, infos[frames[len(frames) // 2]],
                       options.joint, options.fit, options.edges, options.features, options.prior)
        if jf.accepted:
            joint = jf
            starts = {i: apply_delta(prior[i], jf.frame_delta.get(i, jf.delta)) for i in frames}
            fo = replace(fo, coarse_radius_px=0.0)
            coarse = False
            if block:
                got = _block(camera, wf, scene_wf, raycaster, frames, images, prior, starts, infos, options)
                if got is not None:
                    return got
    out = _orient(camera, wf, raycaster, frames, images, prior, starts, infos, t, fo, coarse, options)
    rest = [i for i in frames if out[i].status == "prior"]
    # the scene is tried when it showed a common signal (joint coarse) or the building some frames
    hope = common is not None or len(rest) < len(frames)
    if options.scene_fallback and scene_wf is not None and rest and hope:
        # the pose error belongs to the frame, not to a building: frames the building alone could
        # not orient are oriented against the whole scene of the unit (building and neighbours)
        scene = _orient(camera, scene_wf, raycaster, rest, images, prior, starts, infos, t, fo, coarse,
                        options)
        out.update({i: r for i, r in scene.items() if r.status == "refined"})
    if joint is not None:
        # the common correction holds for every frame between frames that confirm it in time
        ok_t = [t[i] for i in frames if joint.support.get(i, 0.0) >= options.fit.min_support]
        for i in frames:
            inside = bool(ok_t) and min(ok_t) <= t[i] <= max(ok_t)
            if out[i].status == "refined" or not inside:
                continue
            if sigma_px(camera, starts[i], wf.vertices, joint.covariance) <= options.joint_max_sigma_px:
                out[i] = RefinedPose(i, starts[i], "refined", float("nan"), 0)
    return out


def _orient(
    camera: Camera, wf: Wireframe, raycaster: RayCaster, frames: list[int], images: Mapping[int, np.ndarray],
    prior: Mapping[int, Pose], starts: Mapping[int, Pose], infos: Mapping[int, np.ndarray],
    times: Mapping[int, float], fo: FrameFitOptions, coarse: bool, options: CoregisterOptions,
) -> dict[int, RefinedPose]:
    """Pass 1, neighbour prediction, pass 2 and inheritance of `frames` against wireframe `wf`."""
    fits = [
        fit_frame(camera, wf, raycaster, images[i], starts[i], infos[i], starts[i], fo, options.edges,
                  options.features, coarse=coarse)
        for i in frames
    ]
    usable = np.array([f.converged for f in fits])
    if not options.sequence or usable.sum() < options.min_converged_frames:
        return {i: _result(i, f, prior[i]) for i, f in zip(frames, fits, strict=True)}
    t = np.array([times[i] for i in frames])
    deltas = np.array([pose_delta(prior[i], f.pose) for i, f in zip(frames, fits, strict=True)])
    frame_cov = frame_noise_covariance(options.prior.frame_sigma_deg, options.prior.frame_sigma_m)
    out: dict[int, RefinedPose] = {}
    for j, i in enumerate(frames):
        f = fits[j]
        reg_delta = pose_delta(prior[i], starts[i])
        pred = predict(j, t, deltas, fits, usable, frame_cov, options.prediction_regulariser * infos[i],
                       reg_delta, options.window_s, options.time_sigma_s, options.outlier_gate)
        if pred is None:
            out[i] = _result(i, f, prior[i])
            continue
        cov = pred.covariance + frame_cov
        r = deltas[j] - pred.delta
        consistent = float(r @ np.linalg.solve(cov, r)) / 6.0 <= options.outlier_gate
        if f.accepted and consistent:
            out[i] = _result(i, f, prior[i])
            continue
        centre = apply_delta(prior[i], pred.delta)
        start = f.pose if (f.converged and consistent) else centre
        f2 = fit_frame(camera, wf, raycaster, images[i], centre, np.linalg.inv(cov), start, fo, options.edges,
                       options.features, coarse=False)
        if f2.accepted:
            out[i] = _result(i, f2, prior[i])
            continue
        sigma = sigma_px(camera, centre, wf.vertices, pred.covariance)
        if pred.neighbours >= options.inherit_min_neighbours and pred.both_sides and \
                sigma <= options.inherit_max_sigma_px:
            out[i] = RefinedPose(i, centre, "refined", float("nan"), 0)
        else:
            out[i] = RefinedPose(i, prior[i], "prior", f.rms_px, f.matches)
    return out


def _result(i: int, fit: FrameFit, prior: Pose) -> RefinedPose:
    if fit.accepted:
        return RefinedPose(i, fit.pose, "refined", fit.rms_px, fit.matches)
    return RefinedPose(i, prior, "prior", fit.rms_px, fit.matches)


def _block(camera: Camera, wf: Wireframe, scene_wf: Wireframe, raycaster: RayCaster, frames: list[int],
           images: Mapping[int, np.ndarray], prior: Mapping[int, Pose], starts: Mapping[int, Pose],
           infos: Mapping[int, np.ndarray], options: CoregisterOptions) -> dict[int, RefinedPose] | None:
    """The block orientation of `frames` from `starts` (`coregister_block`), None when the block
    as a whole is rejected."""
    out, _, reason = refine_block(camera, wf, scene_wf, raycaster, frames, images, prior, starts,
                                  infos[frames[len(frames) // 2]], options.block, options.fit, options.edges,
                                  options.features, options.prior)
    return None if reason else out


def _joint_coarse(camera: Camera, wf: Wireframe, raycaster: RayCaster, frames: list[int],
                  images: Mapping[int, np.ndarray], prior: Mapping[int, Pose],
                  options: CoregisterOptions) -> list[tuple[np.ndarray, float, float, float]]:
    """Common coarse correction of (up to `joint_coarse_max_frames`) frames, see `joint_coarse`."""
    # the search runs on frames downsampled by `joint_coarse_downsample` (a scaled camera)
    ds = max(int(options.joint_coarse_downsample), 1)
    cam = camera.scaled(1.0 / ds) if ds > 1 else camera
    level = max(options.joint_coarse_level // ds, 1)
    radius = options.joint_coarse_radius_px / ds
    fo = replace(options.fit, coarse_level=level, coarse_radius_px=radius,
                 coarse_depth_steps=options.joint_coarse_depth_steps)
    eo = replace(options.edges, image_margin_px=-radius)
    fe = replace(options.features, dt_levels=(level,))
    pick = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), options.joint_coarse_max_frames))
                     .round().astype(int))
    poses, vis_list, feats_list = [], [], []
    for k in pick:
        i = frames[k]
        vis = visible_wireframe(wf, cam, prior[i], raycaster, eo)
        if len(vis.points) < fo.min_samples:
            continue
        img = images[i]
        if ds > 1:
            img = cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        try:
            feats = extract_features(img, fe, None, points=False)
        except FeatureError:
            continue
        poses.append(prior[i])
        vis_list.append(vis)
        feats_list.append(feats)
    if not poses:
        return []
    found = joint_coarse(cam, poses, vis_list, feats_list, fo, options.joint_coarse_rolls_deg,
                         options.joint_coarse_min_gain, options.joint_coarse_candidates)
    return [(c[0] * ds, *c[1:]) for c in found]


def _verify(camera: Camera, wf: Wireframe, raycaster: RayCaster, frames: list[int],
            images: Mapping[int, np.ndarray], prior: Mapping[int, Pose], infos: Mapping[int, np.ndarray],
            candidates: list[tuple[np.ndarray, float, float, float]], fo: FrameFitOptions,
            options: CoregisterOptions) -> tuple[np.ndarray, float, float, float]:
    """The candidate whose corrected priors the fine stage confirms best on a few frames (sum of
    edge support of the converged fits), the first on ties."""
    if len(candidates) == 1:
        return candidates[0]
    n = min(len(frames), options.verify_frames)
    pick = [frames[k] for k in np.unique(np.linspace(0, len(frames) - 1, n).round().astype(int))]
    scores = []
    for c in candidates:
        total = 0.0
        for i in pick:
            start = apply_coarse(camera, prior[i], c, options.fit)
            f = fit_frame(camera, wf, raycaster, images[i], start, infos[i], start, fo, options.edges,
                          options.features, coarse=False)
            total += f.support if f.converged else 0.0
        scores.append(total)
    return candidates[int(np.argmax(scores))]

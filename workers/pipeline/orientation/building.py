"""Per-building orientation: coregister every frame that sees a building to the building model.

In: `Camera`, the top-level `Building` (parts included), a `RayCaster` over the building and its
neighbours (whole-scene hidden-edge removal), frame indices, a `FrameSource`, the GNSS/INS prior
pose per frame with the manifest's `Accuracy`, options, optional frame times (seconds).
Out: `{frame: RefinedPose}` with status `"refined"` or `"prior"`.

Method (after Avbelj, Iwaszczuk, Stilla & Oštir 2012, extended):

0b. when the sequence orientation ran (`sequence.orient_sequence`: tracks and a bundle adjustment of the
   whole sequence in blocks against every building near the cameras, drives), the building's
   frames take its poses where the building's own edges confirm them and their covariance,
   projected onto the building, is small enough (`block.refine_from_sequence`); when
   the building's edges confirm them nowhere, the steps below run from the priors.

0. when the priors come from an accepted sequence calibration (`calibration`; options from
   `calibrated_options`, `building_options`), the common error is already removed: a probe of
   frames decides whether frames orient alone (flights: step 1 per frame, then 3 and 4) or not
   (close-range drives: the block orientation 2c from the calibrated priors); steps 2 and the
   wide searches are skipped.

1. per frame (`frame_fit`): the building's wireframe with hidden edges removed by ray
   casting through the whole scene (`wireframe`); Förstner points, LSD segments and their
   intersections, gradients and an edge-distance pyramid (`features`); iterative robust least
   squares (Tukey) of the six exterior-orientation parameters from edge-normal distances (1-D
   gradient search along each projected edge sample) and corner-to-point matches within a
   shrinking search radius R, the prior pose a weighted observation; accepted only when well
   determined (edge support, inlier RMS, inliers and edges, predicted reprojection uncertainty
   of the building ≤ `fit.max_sigma_px`, correction in a plausible range).
2. **joint coarse search** (`coarse.joint_coarse`): the correspondence-free
   edge-distance score maps (image shift × roll × depth) of up to `joint_coarse_max_frames`
   frames are averaged, using the wireframe of the whole scene of the ray caster (building and
   neighbours: a row of similar houses is not ambiguous); when the minimum is distinct, the
   common correction (a rotation plus a translation across the optical axis, split by their
   a-priori sizes) is applied to every prior and pass 1 is centred on it. Else each frame runs
   its own coarse search (kept only when distinct, too).
2b. **joint fine adjustment** (`common_correction`, when the joint coarse search finds no
   distinct minimum, as on close-range drives): ONE common correction of all frames plus small
   per-frame deviations, adjusted from the stacked edge observations of every frame against the
   scene wireframe (an oriented-gradient search over common image shifts first). When accepted,
   the block orientation 2c starts from each frame's jointly corrected pose; if the block is
   rejected, pass 1 is centred on those poses, and a frame still at its prior after steps 3 and
   4 takes its jointly corrected pose with status `"refined"` when it lies in time between frames
   whose edge support confirms the correction and the common correction's uncertainty projected
   onto the building is ≤ `joint_max_sigma_px`.
2c. **block orientation** (`block`, close-range drives): feature tracks over the
   facades (`tracks`) and a bundle adjustment of all the building's frames with the track points
   on the model's planes, the scene's model edges and the priors (`bundle`; Hoegner & Stilla,
   method 2). A frame is `"refined"` when the block found the model and the frame's own
   uncertainty, projected onto the building, is ≤ `block.max_sigma_px`.
3. sequence level: corrections `δ = (ω_cam, dC_world)` of consecutive frames are strongly
   correlated (constant boresight error, slow GNSS drift). Frames that converged (found the
   building, whether or not alone they determine the pose) give each frame a **prediction**: the
   information-weighted, time-weighted mean of its neighbours' corrections (outliers gated;
   `neighbours.predict`). A
   frame accepted in pass 1 and consistent with its prediction keeps its fit; every other frame
   is fitted again (pass 2) with the prediction as its prior (covariance: the mean's plus the
   per-frame noise `prior.frame_sigma_*`, `priors.PriorOptions`), which determines frames that
   see only one or two edges.
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
from dataclasses import dataclass, replace

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.manifest import Accuracy, FrameSource
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import apply_delta, pose_delta
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.block import (
    UnitSequence,
    refine_block,
    refine_from_sequence,
    sigma_px,
)
from workers.pipeline.orientation.building_options import CoregisterOptions, calibrated_options
from workers.pipeline.orientation.coarse import apply_coarse, joint_coarse
from workers.pipeline.orientation.common_correction import JointFit, joint_fit
from workers.pipeline.orientation.features import FeatureError, extract_features
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.frame_fit import FrameFit, fit_frame
from workers.pipeline.orientation.neighbours import predict
from workers.pipeline.orientation.priors import frame_noise_covariance, prior_information
from workers.pipeline.orientation.wireframe import (
    Wireframe,
    WireframeError,
    building_wireframe,
    mesh_wireframe,
    visible_wireframe,
)
from workers.pipeline.results import RefinedPose

__all__ = ["CoregisterOptions", "RefinedPose", "calibrated_options", "prior_information", "refine_building"]


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
        rest = [i for i in frames if got[i].status == "prior"] if options.sequence_fallback else []
        if not reason and rest:
            # the building's own edges did not confirm the sequence's pose of these frames: they
            # are oriented on their own from their priors (steps 0-4), taken where refined
            again = refine_building(camera, building, raycaster, rest, frame_source, prior, accuracy, options,
                                    times, None)
            got.update({i: r for i, r in again.items() if r.status == "refined"})
        if not reason:
            return got
    infos = {i: prior_information(prior[i], accuracy, options) for i in frames}
    t = {i: float(times[i]) if times is not None else float(i) for i in frames}
    u = _Unit(camera, wf, _scene_wireframe(raycaster, options), raycaster, frames, images, prior, infos, t,
              options)
    start = _Start(dict(prior), options.fit, True)
    common = _common_coarse(u) if options.joint_coarse else None
    if common is not None:
        # the common correction is a sequence-level estimate: pass 1 is centred on it
        start = _Start({i: apply_coarse(camera, prior[i], common, options.fit) for i in frames},
                       replace(options.fit, coarse_radius_px=options.frame_coarse_radius_px),
                       options.frame_coarse_radius_px > 0)
    if options.calibrated:
        got = _from_calibrated(u, start)
        if got is not None:
            return got
    joint = None
    if options.joint_fine and common is None and u.scene_wf is not None:
        jf = joint_fit(camera, u.scene_wf, raycaster, frames, images, prior, infos[frames[len(frames) // 2]],
                       options.joint, options.fit, options.edges, options.features, options.prior)
        if jf.accepted:
            joint = jf
            start = _Start({i: apply_delta(prior[i], jf.frame_delta.get(i, jf.delta)) for i in frames},
                           replace(start.fit, coarse_radius_px=0.0), False)
            got = _block(u, start.poses)
            if got is not None:
                return got
    out = _orient_building_then_scene(u, start, scene_always=common is not None)
    if joint is not None:
        _inherit_joint(u, joint, start.poses, out)
    return out


@dataclass(frozen=True, eq=False)
class _Unit:
    """What the steps of one building's orientation share (`refine_building`)."""

    camera: Camera
    # the building's wireframe, and the wireframe of the ray caster's whole scene (None: no mesh)
    wf: Wireframe
    scene_wf: Wireframe | None
    raycaster: RayCaster
    # the building's frames in recording order, their images, priors, prior information, times (s)
    frames: list[int]
    images: Mapping[int, np.ndarray]
    prior: Mapping[int, Pose]
    infos: Mapping[int, np.ndarray]
    times: Mapping[int, float]
    options: CoregisterOptions


@dataclass(frozen=True, eq=False)
class _Start:
    """Where pass 1 starts: a pose per frame, the frame fit's options, and whether each frame runs
    its own coarse search."""

    poses: Mapping[int, Pose]
    fit: FrameFitOptions
    coarse: bool


def _scene_wireframe(raycaster: RayCaster, options: CoregisterOptions) -> Wireframe | None:
    """The wireframe of the ray caster's whole scene (building and neighbours) when a step needs it
    (joint coarse search on the scene, scene fallback) and the ray caster has a mesh; else None."""
    has_mesh = getattr(raycaster, "mesh", None) is not None
    if (options.joint_coarse_scene or options.scene_fallback) and has_mesh:
        with contextlib.suppress(WireframeError):
            return mesh_wireframe(raycaster.mesh, options.edges)
    return None


def _from_calibrated(u: _Unit, start: _Start) -> dict[int, RefinedPose] | None:
    """Step 0, calibrated priors: every frame on its own (flights), unless most frames of a probe do
    not determine their pose alone (close drives): then the block orientation. None when neither
    applies (the block rejected) and the steps for uncalibrated priors go on."""
    o = u.options
    n = min(len(u.frames), o.calibrated_probe_frames)
    probe = [u.frames[k] for k in np.unique(np.linspace(0, len(u.frames) - 1, n).round().astype(int))]
    ok = [fit_frame(u.camera, u.wf, u.raycaster, u.images[i], start.poses[i], u.infos[i], start.poses[i],
                    start.fit, o.edges, o.features, coarse=False).accepted for i in probe]
    if np.mean(ok) >= o.calibrated_joint_below:
        return _orient_building_then_scene(u, _Start(start.poses, start.fit, False), scene_always=True)
    return _block(u, start.poses)


def _orient_building_then_scene(u: _Unit, start: _Start, scene_always: bool) -> dict[int, RefinedPose]:
    """Steps 1 and 3 against the building (`_orient`), then step 4 for the frames still at their
    prior against the whole scene, when there is hope: `scene_always`, or the building oriented
    some frames."""
    out = _orient(u, u.wf, u.frames, start)
    rest = [i for i in u.frames if out[i].status == "prior"]
    # the scene is tried when it showed a common signal (joint coarse) or the building some frames
    hope = scene_always or len(rest) < len(u.frames)
    if u.options.scene_fallback and u.scene_wf is not None and rest and hope:
        # the pose error belongs to the frame, not to a building: frames the building alone could
        # not orient are oriented against the whole scene of the unit (building and neighbours)
        scene = _orient(u, u.scene_wf, rest, start)
        out.update({i: r for i, r in scene.items() if r.status == "refined"})
    return out


def _inherit_joint(u: _Unit, joint: JointFit, starts: Mapping[int, Pose],
                   out: dict[int, RefinedPose]) -> None:
    """Step 2b's inheritance, in `out`: a frame still at its prior takes its jointly corrected pose
    `starts[i]` when it lies in time between frames whose edge support confirms the correction
    and the correction's uncertainty projected onto the building is ≤ `joint_max_sigma_px`."""
    o = u.options
    ok_t = [u.times[i] for i in u.frames if joint.support.get(i, 0.0) >= o.fit.min_support]
    for i in u.frames:
        inside = bool(ok_t) and min(ok_t) <= u.times[i] <= max(ok_t)
        if out[i].status == "refined" or not inside:
            continue
        if sigma_px(u.camera, starts[i], u.wf.vertices, joint.covariance) <= o.joint_max_sigma_px:
            out[i] = RefinedPose(i, starts[i], "refined", float("nan"), 0)


def _orient(u: _Unit, wf: Wireframe, frames: list[int], start: _Start) -> dict[int, RefinedPose]:
    """Pass 1, neighbour prediction, pass 2 and inheritance of `frames` against wireframe `wf`."""
    camera, raycaster, images, prior, infos = u.camera, u.raycaster, u.images, u.prior, u.infos
    options, starts, fo = u.options, start.poses, start.fit
    fits = [
        fit_frame(camera, wf, raycaster, images[i], starts[i], infos[i], starts[i], fo, options.edges,
                  options.features, coarse=start.coarse)
        for i in frames
    ]
    usable = np.array([f.converged for f in fits])
    if not options.sequence or usable.sum() < options.min_converged_frames:
        return {i: _result(i, f, prior[i]) for i, f in zip(frames, fits, strict=True)}
    t = np.array([u.times[i] for i in frames])
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
        again = f.pose if (f.converged and consistent) else centre
        f2 = fit_frame(camera, wf, raycaster, images[i], centre, np.linalg.inv(cov), again, fo, options.edges,
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


def _block(u: _Unit, starts: Mapping[int, Pose]) -> dict[int, RefinedPose] | None:
    """The block orientation of the unit's frames from `starts` (`block.refine_block`, step 2c);
    None when it does not run (off, or no scene wireframe) or the block as a whole is rejected."""
    o = u.options
    if not (o.block_orientation and u.scene_wf is not None):
        return None
    mid = u.frames[len(u.frames) // 2]
    out, _, reason = refine_block(u.camera, u.wf, u.scene_wf, u.raycaster, u.frames, u.images, u.prior,
                                  starts, u.infos[mid], o.block, o.fit, o.edges, o.features, o.prior)
    return None if reason else out


def _common_coarse(u: _Unit) -> tuple[np.ndarray, float, float, float] | None:
    """Step 2: the common coarse correction of the unit's frames (`coarse.joint_coarse`), on the
    scene wireframe (`joint_coarse_scene`) or the building's; of several candidates the one the
    fine stage confirms best (`_verify`); None without a distinct minimum."""
    o = u.options
    coarse_wf = u.scene_wf if (o.joint_coarse_scene and u.scene_wf is not None) else u.wf
    found = _joint_coarse(u.camera, coarse_wf, u.raycaster, u.frames, u.images, u.prior, o)
    if not found:
        return None
    fo_v = replace(o.fit, coarse_radius_px=o.frame_coarse_radius_px)
    return _verify(u, coarse_wf, found, fo_v)


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


def _verify(u: _Unit, wf: Wireframe, candidates: list[tuple[np.ndarray, float, float, float]],
            fo: FrameFitOptions) -> tuple[np.ndarray, float, float, float]:
    """The candidate whose corrected priors the fine stage confirms best on a few frames (sum of
    edge support of the converged fits), the first on ties."""
    if len(candidates) == 1:
        return candidates[0]
    options, frames = u.options, u.frames
    n = min(len(frames), options.verify_frames)
    pick = [frames[k] for k in np.unique(np.linspace(0, len(frames) - 1, n).round().astype(int))]
    scores = []
    for c in candidates:
        total = 0.0
        for i in pick:
            start = apply_coarse(u.camera, u.prior[i], c, options.fit)
            f = fit_frame(u.camera, wf, u.raycaster, u.images[i], start, u.infos[i], start, fo, options.edges,
                          options.features, coarse=False)
            total += f.support if f.converged else 0.0
        scores.append(total)
    return candidates[int(np.argmax(scores))]

"""Sequence calibration: the systematic part of the GNSS/INS pose error, once per sequence.

In: `Camera`, a `RayCaster` over the buildings the sequence sees (its mesh gives the scene
wireframe), the frames in recording order with their times (seconds), a `FrameSource`, the
GNSS/INS prior camera pose per frame (world = model CRS), the manifest's `Accuracy`, options.
Out: `SequenceCalibration`: a boresight correction `ω` (camera frame, radians), a GNSS position
offset `b` (world, metres), a lever-arm correction `l` (camera frame, metres) and a camera-to-INS
time delay `τ` (seconds), their covariance, acceptance; `apply_calibration` gives the calibrated
prior of every frame.

Why (Kolecki, Iwaszczuk & Stilla 2010; README.md, Commands: "calibrates the sequence once"): the
boresight misalignment, the lever arm the manifest does not know, the GNSS bias and the time
delay are constant over a sequence, while a single close-range frame of a drive (vertical
building corners only) does not determine its pose, and a single building seen along a straight
street cannot tell a lever arm from a GNSS offset. Over the whole sequence and all its buildings,
with the headings changing at every turn, all of them are observable.

Model (`calibration_model`): frame i's correction `δ_i = (ω_i, dC_i)`
(`geometry.pose_increments.apply_delta`) is

    ω_i  = ω − τ · Ω_i            (Ω_i: angular rate of the prior, camera frame, rad/s)
    dC_i = b + R_i · l − τ · v_i  (v_i: velocity of the prior centre, world, m/s)
    x_i  = A_i θ + ε_i,           θ = (ω, b, l, τ) (10,)

(exposure at `time − τ`, linearised), with per-frame deviations `ε_i` (white GNSS noise,
vibration) of a-priori σ `prior.frame_sigma_*` (`priors.PriorOptions`), eliminated by a Schur complement.

Method:
1. a bounded sample of frames (`calibration_frames`): at most `look_frames` evenly spread frames
   are looked at (their visible samples come from their part of the scene wireframe,
   `edge_observations.FrameWireframes`), and of those whose prior view shows scene edges the
   `max_frames` best-seeing, one per stretch of the sequence, take part: the cost does not grow
   with the sequence length;
2. start: the common correction `(ω, b)` from `common_correction.joint_fit` against the scene
   wireframe (oriented-gradient search over common image shifts, also with the cameras rolled
   about their optical axes, and over common world translations, coarse to fine within the
   correction's plausible range; then a robust adjustment) on at most
   `start_frames` frames of the first frame set where one fits: the picked frames, then
   `start_segments` consecutive stretches, when the camera turns less than `start_turn_deg`
   over the sequence; else the first `start_segments` stretches of consecutive frames that turn
   less than that (a lever-arm error turns with the camera; one common correction does not fit
   across a drive's turns), filled up by the longest shorter stretches when fewer are that long
   (a drive that turns often); `l = 0`, `τ = 0`;
3. Gauss-Newton of θ and the `ε_i` from every frame's edge-normal distances (1-D gradient search
   along each projected edge sample, Tukey weights; `edge_observations.normal_equations`) with a
   shrinking search radius; θ has a weighted prior of zero (`Accuracy` for `ω` and `b`,
   `lever_arm_sigma_m`, `time_delay_sigma_s`); τ is then searched on a grid (oriented-gradient
   score, all candidate delays of a frame projected at once; not when no frame turns or moves
   enough to tell the delays apart) and, when it moved, θ adjusted again from there;
4. accepted when the mean edge support of the frames reaches `min_mean_support`, at least
   `min_supported_frames` frames are supported, and the correction is plausible; otherwise the
   priors are kept (`accepted` False, `reason` says why).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.manifest import Accuracy, FrameSource
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import apply_delta
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.bundle_edges import edge_equations
from workers.pipeline.orientation.calibration_delay import delay_search
from workers.pipeline.orientation.calibration_frames import SampleOptions, sample_frames, start_sets
from workers.pipeline.orientation.calibration_model import N_PARAMS, design, frame_designs, frame_motion
from workers.pipeline.orientation.common_correction import JointOptions, joint_fit
from workers.pipeline.orientation.edge_observations import (
    FrameWireframes,
    edge_support,
    frame_edges,
)
from workers.pipeline.orientation.features import FeatureOptions, ImageFeatures
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.priors import PriorOptions, frame_noise_information
from workers.pipeline.orientation.wireframe import (
    EdgeOptions,
    VisibleWireframe,
    Wireframe,
    WireframeError,
    mesh_wireframe,
)

__all__ = [
    "CalibrationOptions",
    "SequenceCalibration",
    "apply_calibration",
    "calibrate_sequence",
    "calibrated_accuracy",
]


@dataclass(frozen=True)
class CalibrationOptions:
    """Parameters of the sequence calibration (metres, degrees, seconds, pixels)."""

    # at most this many frames take part (each the best-seeing of its stretch of the sequence),
    # chosen among at most `look_frames` (evenly spread) whose prior view shows scene edges: the
    # cost does not grow with the sequence length (`calibration_frames`)
    max_frames: int = 24
    look_frames: int = 48
    # the start (one common correction, `joint`) is searched on frame sets in turn, each of at most
    # `start_frames` frames: the picked frames, then `start_segments` consecutive stretches of the
    # looked-at frames, when their camera rotation stays within `start_turn_deg` (one common
    # correction cannot fit a lever-arm error across turns); else the `start_segments` stretches
    # within that rotation of at least `min_start_frames` frames that see the most scene edges
    # (the 300-frame NRW drive: none over the whole drive, mean edge support 0.07; its first
    # third gives one, and the calibration from there leaves 0.17° / 0.2 m σ over all 300 frames)
    start_segments: int = 3
    start_frames: int = 20
    start_turn_deg: float = 45.0
    min_start_frames: int = 10
    # ... and when fewer than `start_segments` stretches are that long (a drive that turns often:
    # the NRW drive of seed 2, stretches of 2-9 looked-at frames, had no start at all), the longest
    # of those of at least `min_short_frames` fill up the sets (seed 2: pairs < 1 px 0.0 -> 0.953,
    # median 47.1 -> 0.10 px; seeds 1 and 3 and the flight unchanged, their first set fits)
    min_short_frames: int = 5
    # the start: `joint_fit` over the frames (its support test is loose: one common correction
    # does not align frames with white noise; the final test below, after the per-frame
    # deviations are adjusted, decides)
    joint: JointOptions = field(default_factory=lambda: JointOptions(
        max_frames=40, coarse_frames=10, verify_frames=6, coarse_rolls_deg=(-8.0, -4.0, 0.0, 4.0, 8.0),
        max_correction_m=12.0, max_correction_deg=10.0,
        min_mean_support=0.2, visibility_reuse_px=3.0))
    edges: EdgeOptions = field(default_factory=EdgeOptions)
    fit: FrameFitOptions = field(default_factory=FrameFitOptions)
    features: FeatureOptions = field(default_factory=FeatureOptions)
    # a-priori σ when the manifest has no `accuracy`, and a floor (the accuracy does not cover the
    # boresight misalignment): position offset (m), boresight (deg)
    default_position_sigma_m: float = 3.0
    default_attitude_sigma_deg: float = 3.0
    position_sigma_floor_m: float = 3.0
    attitude_sigma_floor_deg: float = 3.0
    # a-priori σ of the lever-arm correction (m) and of the time delay (s); 0 fixes the term
    lever_arm_sigma_m: float = 1.0
    time_delay_sigma_s: float = 0.1
    # the time delay is first searched on a grid up to ± this (s) with this step: its effect is
    # large at turns only, often beyond the fine stage's search radius
    delay_search_s: float = 0.1
    delay_step_s: float = 0.0025
    # per-frame deviations from the systematic model (white noise, vibration), and the null shift
    # of the acceptance's edge-support test below
    prior: PriorOptions = field(default_factory=PriorOptions)
    # Gauss-Newton: edge search radius at the start (shrinks by `radius_decay`), iterations
    radius_start_px: float = 12.0
    radius_decay: float = 0.8
    iterations: int = 12
    # a frame's visible samples are computed again (every 4 iterations) only when its pose moved
    # some of them more than this many pixels since they were (0: always)
    visibility_reuse_px: float = 3.0
    # acceptance (edge support as in `common_correction`)
    # (0.3: tall facades at close range show few model edges, the Berlin drive calibrates right
    # at 0.35; noise is told apart by the null support below, 0.4 against 0.39)
    min_mean_support: float = 0.3
    min_supported_frames: int = 3
    # ... and the support must exceed the null support (samples moved `prior.null_shift_px` off
    # their edges) by this much
    min_support_gain: float = 0.2
    max_correction_m: float = 12.0
    max_correction_deg: float = 10.0


@dataclass(frozen=True, eq=False)
class SequenceCalibration:
    """The systematic correction of a sequence's priors (see the module docstring).

    Attributes:
        theta: `(10,)` = boresight correction `ω` (camera frame, rad), GNSS offset `b` (world, m),
            lever-arm correction `l` (camera frame, m), time delay `τ` (s).
        covariance: `(10, 10)` of `theta` (a-posteriori variance factor applied, ≥ 1).
        accepted: the acceptance tests passed (else `theta` must not be applied).
        reason: why not ("" when accepted).
        frames: frames that took part.
        support: `{frame: share of visible edge samples with an image edge within support_px}`.
        mean_support: mean of `support`.
        mean_null_support: the same share with the samples moved `prior.null_shift_px` off their edges
            along the image normal (edge clutter and noise; `mean_support` must exceed it by
            `min_support_gain`).
    """

    theta: np.ndarray
    covariance: np.ndarray = field(default_factory=lambda: np.full((N_PARAMS, N_PARAMS), np.nan))
    accepted: bool = False
    reason: str = ""
    frames: tuple[int, ...] = ()
    support: dict[int, float] = field(default_factory=dict)
    mean_support: float = 0.0
    mean_null_support: float = 0.0

    @property
    def boresight_rad(self) -> np.ndarray:
        """`(3,)` boresight correction, camera frame, radians."""
        return self.theta[0:3]

    @property
    def offset_m(self) -> np.ndarray:
        """`(3,)` GNSS position offset, world metres."""
        return self.theta[3:6]

    @property
    def lever_arm_m(self) -> np.ndarray:
        """`(3,)` lever-arm correction, camera frame, metres."""
        return self.theta[6:9]

    @property
    def time_delay_s(self) -> float:
        """Camera-to-INS delay τ (exposure at `time − τ`), seconds."""
        return float(self.theta[9])

    def to_dict(self) -> dict[str, object]:
        """JSON-ready summary (degrees, metres, seconds; standard deviations alongside)."""
        sd = np.sqrt(np.clip(np.diag(self.covariance), 0, None))
        return {
            "accepted": self.accepted,
            "reason": self.reason,
            "frames": len(self.frames),
            "mean_edge_support": round(self.mean_support, 3),
            "mean_null_support": round(self.mean_null_support, 3),
            "boresight_correction_deg": np.degrees(self.boresight_rad).round(4).tolist(),
            "offset_m": self.offset_m.round(4).tolist(),
            "lever_arm_correction_cam_m": self.lever_arm_m.round(4).tolist(),
            "time_delay_s": round(self.time_delay_s, 5),
            "sigma": {
                "boresight_deg": np.degrees(sd[0:3]).round(4).tolist(),
                "offset_m": sd[3:6].round(4).tolist(),
                "lever_arm_m": sd[6:9].round(4).tolist(),
                "time_delay_s": round(float(sd[9]), 5),
            },
        }


def apply_calibration(
    priors: Sequence[Pose], times: Sequence[float], calibration: SequenceCalibration
) -> list[Pose]:
    """Calibrated prior of every frame (recording order, `times` in seconds); the priors unchanged
    when the calibration was not accepted."""
    if not calibration.accepted:
        return list(priors)
    v, w = frame_motion(priors, times)
    return [apply_delta(p, design(p, v[i], w[i]) @ calibration.theta) for i, p in enumerate(priors)]


def calibrated_accuracy(calibration: SequenceCalibration, options: CalibrationOptions = CalibrationOptions(),
                        prior: Accuracy | None = None) -> Accuracy | None:
    """A-priori σ of a calibrated prior for the building units: the per-frame deviation σ and the
    calibration's own uncertainty (the manifest's accuracy when the calibration was rejected)."""
    if not calibration.accepted:
        return prior
    var = np.diag(calibration.covariance)
    pos = np.sqrt(options.prior.frame_sigma_m**2 + var[3:6] + np.sum(var[6:9]) / 3.0)
    att = np.degrees(np.sqrt(np.radians(options.prior.frame_sigma_deg) ** 2 + var[0:3]))
    return Accuracy(position_m=pos, attitude_deg=att)


def _prior_information(accuracy: Accuracy | None, options: CalibrationOptions) -> np.ndarray:
    """`(10, 10)` information of the zero prior on θ."""
    if accuracy is None:
        sp = np.full(3, options.default_position_sigma_m)
        sa = np.full(3, options.default_attitude_sigma_deg)
    else:
        sp = np.asarray(accuracy.position_m, dtype=np.float64).reshape(3)
        sa = np.asarray(accuracy.attitude_deg, dtype=np.float64).reshape(3)
    sp = np.maximum(sp, options.position_sigma_floor_m)
    sa = np.maximum(sa, options.attitude_sigma_floor_deg)
    d = np.concatenate([np.radians(sa) ** -2, sp**-2,
                        [options.lever_arm_sigma_m**-2 if options.lever_arm_sigma_m > 0 else 1e12] * 3,
                        [options.time_delay_sigma_s**-2 if options.time_delay_sigma_s > 0 else 1e12]])
    return np.diag(d)


@dataclass(frozen=True, eq=False)
class _Frame:
    index: int
    prior: Pose
    A: np.ndarray
    feats: ImageFeatures


def calibrate_sequence(
    camera: Camera,
    raycaster: RayCaster,
    frames: Sequence[int],
    frame_source: FrameSource,
    priors: Mapping[int, Pose],
    times: Mapping[int, float],
    accuracy: Accuracy | None,
    options: CalibrationOptions = CalibrationOptions(),
    wireframe: Wireframe | None = None,
) -> SequenceCalibration:
    """Calibrate the sequence (see the module docstring).

    Args:
        camera: interior orientation.
        raycaster: over the buildings the sequence sees (hidden-edge removal); its mesh gives the
            scene wireframe unless `wireframe` is given.
        frames: all frame indices of the sequence, in recording order.
        frame_source: `load(i) -> (H, W)` float32 physical values.
        priors: GNSS/INS camera pose per frame (world = model CRS).
        times: frame time per frame, seconds.
        accuracy: a-priori σ of the GNSS/INS solution (None: option defaults).
        options: all parameters.
        wireframe: the scene wireframe (default: `mesh_wireframe` of the ray caster's mesh).
    """
    frames = list(frames)
    zero = SequenceCalibration(theta=np.zeros(N_PARAMS))
    if wireframe is None:
        mesh = getattr(raycaster, "mesh", None)
        if mesh is None:
            return replace(zero, reason="no scene mesh")
        try:
            wireframe = mesh_wireframe(mesh, options.edges)
        except WireframeError as e:
            return replace(zero, reason=f"no scene wireframe: {e}")
    if len(frames) < options.min_supported_frames:
        return replace(zero, reason="too few frames")
    # a bounded sample of frames that see the model, spread over the sequence (`calibration_frames`)
    fo = options.fit
    wfs = FrameWireframes(wireframe, camera)
    so = _sample_options(options)
    sample = sample_frames(frames, priors, wfs, raycaster, options.edges, so)
    if len(sample.usable) < options.min_supported_frames:
        return replace(zero, reason="too few frames see the model")
    pick = list(sample.pick)
    images = {i: frame_source.load(i) for i in pick}
    P = _prior_information(accuracy, options)
    start = None
    for part in start_sets(sample, priors, so):
        # the first set of frames one common correction fits (the adjustment below models what
        # varies along the drive: lever arm with the heading, delay at the turns)
        images.update({i: frame_source.load(i) for i in part if i not in images})
        start = joint_fit(camera, wfs, raycaster, part, images, {i: priors[i] for i in part}, P[:6, :6],
                          replace(options.joint, max_frames=options.start_frames), fo, options.edges,
                          options.features, options.prior)
        if start.accepted:
            break
    if start is None or not start.accepted:
        reason = start.reason if start is not None else "no frame set"
        return replace(zero, reason=f"no common correction: {reason}", frames=tuple(pick))
    A = frame_designs(frames, priors, times, pick)
    corrected = {i: apply_delta(priors[i], start.delta) for i in pick}
    margin = options.radius_start_px + fo.roi_margin_px
    found = frame_edges(camera, wfs, raycaster, pick, images, corrected, margin, fo, options.edges,
                        options.features)
    data = [_Frame(i, priors[i], A[i], found[i].feats) for i in pick if i in found]
    theta0 = np.zeros(N_PARAMS)
    theta0[:6] = start.delta
    cal = _adjust(camera, wfs, raycaster, data, theta0, P, options)
    if options.time_delay_sigma_s > 0 and options.delay_search_s > 0:
        # the delay shows at turns only, often beyond the fine stage's search radius: searched on
        # a grid at the adjusted parameters, then adjusted again from there when it moved (not
        # when no frame turns or moves enough to tell the delays apart: a flight's straight lines)
        tau = delay_search(camera, wfs, raycaster, data, images, cal.theta, options.delay_search_s,
                           options.delay_step_s, options.edges, fo)
        theta1 = cal.theta.copy()
        theta1[9] = cal.theta[9] if tau is None else tau
        if abs(theta1[9] - cal.theta[9]) > options.delay_step_s:
            again = _adjust(camera, wfs, raycaster, data, theta1, P, options)
            if again.mean_support >= cal.mean_support:
                cal = again
    return _accept(replace(cal, frames=tuple(f.index for f in data)), options)


def _sample_options(options: CalibrationOptions) -> SampleOptions:
    """The frame sample's options (`calibration_frames`) of the calibration's."""
    return SampleOptions(look_frames=options.look_frames, max_frames=options.max_frames,
                         start_frames=options.start_frames, start_segments=options.start_segments,
                         start_turn_deg=options.start_turn_deg, min_start_frames=options.min_start_frames,
                         min_short_frames=options.min_short_frames,
                         min_samples=options.fit.min_samples)


def _adjust(
    camera: Camera, wireframe: FrameWireframes, raycaster: RayCaster, data: list[_Frame], theta0: np.ndarray,
    P: np.ndarray, options: CalibrationOptions,
) -> SequenceCalibration:
    """Gauss-Newton of θ `(10,)` and the per-frame deviations `ε_i` `(6,)` from `theta0` (Schur
    complement; module docstring) -> the calibration, not yet tested for acceptance."""
    fo = options.fit
    theta = theta0.copy()
    eps = {f.index: np.zeros(6) for f in data}
    F = frame_noise_information(options.prior)
    vis: dict[int, VisibleWireframe] = {}
    S = P.copy()
    for it in range(options.iterations):
        poses = {f.index: apply_delta(f.prior, f.A @ theta + eps[f.index]) for f in data}
        if it % 4 == 0:
            vis = {f.index: wireframe.visible(f.index, poses[f.index], raycaster, options.edges,
                                              fo.max_samples, options.visibility_reuse_px) for f in data}
        R_e = max(fo.edge_radius_min_px, options.radius_start_px * options.radius_decay**it)
        fo_it = replace(fo, tukey_min_px=max(fo.tukey_min_px, R_e / 3))
        S = P.copy()
        rhs = -P @ theta
        parts = {}
        Hs, gs = edge_equations(camera, [poses[f.index] for f in data], [vis[f.index] for f in data],
                                [f.feats for f in data], R_e, fo_it)  # all frames at once
        for f, Hi, gi in zip(data, Hs, gs, strict=True):
            B = np.linalg.inv(Hi + F)
            c = gi - F @ eps[f.index]
            HB = Hi @ B
            S += f.A.T @ (Hi - HB @ Hi) @ f.A
            rhs += f.A.T @ (gi - HB @ c)
            parts[f.index] = (B, c, Hi)
        try:
            dt = np.linalg.solve(S, rhs)
        except np.linalg.LinAlgError:
            break
        dt = _bounded(dt)
        theta = theta + dt
        big = 0.0
        for f in data:
            B, c, Hi = parts[f.index]
            de = B @ (c - Hi @ f.A @ dt)
            eps[f.index] = eps[f.index] + de
            big = max(big, float(np.linalg.norm(de[3:])))
        small = np.linalg.norm(dt[:3]) < 5e-5 and np.linalg.norm(dt[3:9]) < 5e-3 and abs(dt[9]) < 1e-3
        if R_e <= fo.edge_radius_min_px + 1e-9 and small and big < 5e-3:
            break
    support: dict[int, float] = {}
    null: dict[int, float] = {}
    chi2, n = 0.0, 0
    for f in data:
        # the null support: how often clutter or noise alone gives "support" (white noise ~0.4)
        pose = apply_delta(f.prior, f.A @ theta + eps[f.index])
        got = edge_support(camera, wireframe.wireframe, raycaster, pose, f.feats,
                           options.edges, fo, options.prior.null_shift_px,
                           visible=wireframe.visible(f.index, pose, raycaster, options.edges, fo.max_samples,
                                                     options.visibility_reuse_px))
        if got is None:
            continue
        support[f.index], null[f.index], inl, _ = got
        chi2 += float(np.sum(inl**2))
        n += len(inl)
    s0 = max(1.0, chi2 / max(n - N_PARAMS, 1) / fo.sigma_edge_px**2)
    try:
        cov = np.linalg.inv(S) * s0
    except np.linalg.LinAlgError:
        cov = np.full((N_PARAMS, N_PARAMS), np.nan)
    mean = float(np.mean(list(support.values()))) if support else 0.0
    mean_null = float(np.mean(list(null.values()))) if null else 0.0
    return SequenceCalibration(theta=theta, covariance=cov, support=support, mean_support=mean,
                               mean_null_support=mean_null)


def _bounded(d: np.ndarray) -> np.ndarray:
    """A Gauss-Newton step `(10,)` bounded to 3°, 2 m (offset and lever arm each) and 0.05 s."""
    d = d.copy()
    d[0:3] *= min(1.0, np.radians(3.0) / max(np.linalg.norm(d[0:3]), 1e-12))
    d[3:6] *= min(1.0, 2.0 / max(np.linalg.norm(d[3:6]), 1e-12))
    d[6:9] *= min(1.0, 2.0 / max(np.linalg.norm(d[6:9]), 1e-12))
    d[9] = float(np.clip(d[9], -0.05, 0.05))
    return d


def _accept(cal: SequenceCalibration, options: CalibrationOptions) -> SequenceCalibration:
    """Acceptance tests (module docstring)."""
    fo = options.fit
    supported = sum(s >= fo.min_support for s in cal.support.values())
    th = cal.theta
    reason = ""
    if cal.mean_support < options.min_mean_support:
        reason = f"mean edge support {cal.mean_support:.2f} < {options.min_mean_support}"
    elif supported < options.min_supported_frames:
        reason = f"only {supported} frames with edge support"
    elif cal.mean_support - cal.mean_null_support < options.min_support_gain:
        reason = (f"edge support {cal.mean_support:.2f} not above the null support "
                  f"{cal.mean_null_support:.2f} by {options.min_support_gain}")
    elif not np.all(np.isfinite(cal.covariance)):
        reason = "calibration not determined"
    elif np.linalg.norm(th[3:6]) + np.linalg.norm(th[6:9]) > options.max_correction_m or \
            np.degrees(np.linalg.norm(th[0:3])) > options.max_correction_deg:
        reason = "correction beyond the plausible range"
    return replace(cal, accepted=not reason, reason=reason)

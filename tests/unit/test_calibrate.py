"""Sequence calibration (`workers.pipeline.orientation.calibration`) on a synthetic drive, and its
conversion to the manifest's mounting terms (`workers.pipeline.orientation.mounting`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import pytest

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.georef import prior_poses
from workers.pipeline.geometry.manifest import (
    FrameRecord,
    MemoryFrames,
    Mounting,
    Radiometry,
    SequenceManifest,
)
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import apply_delta, pose_delta, so3_exp
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation import edge_observations
from workers.pipeline.orientation.calibration import (
    CalibrationOptions,
    SequenceCalibration,
    apply_calibration,
    calibrate_sequence,
    calibrated_accuracy,
)
from workers.pipeline.orientation.calibration_model import design, frame_motion
from workers.pipeline.orientation.common_correction import JointOptions, _translation_levels
from workers.pipeline.orientation.edge_observations import FrameWireframes, visible_samples
from workers.pipeline.orientation.mounting import (
    calibrated_mounting,
    calibration_report,
    mounting_document,
    wrap_deg,
)
from workers.pipeline.orientation.wireframe import EdgeOptions, mesh_wireframe
from workers.pipeline.synth import ErrorOptions, SynthOptions, SynthResult, procedural_block, synthesize

N_FRAMES = 40  # 30 frames leave too few frames seeing edges for the +5 m start (bench: 40)


Drive = tuple[SynthResult, list[np.ndarray], RayCaster, dict[int, float]]


@pytest.fixture(scope="module")
def drive() -> Drive:
    """The bench's error-free drive (`bench/orientation.py` `scene`): result, frames, caster, times."""
    res = synthesize(
        procedural_block(6, seed=1),
        SynthOptions(platform="drive", n_frames=N_FRAMES, seed=1, buildings=3,
                     errors=ErrorOptions(enabled=False)),
    )
    imgs = [res.frames.load(i) for i in range(N_FRAMES)]
    times = {i: f.time for i, f in enumerate(res.manifest.frames)}
    return res, imgs, RayCaster(res.mesh), times


def offset_pose(pose: Pose, d_m: float, d_deg: float) -> Pose:
    """`pose` moved by `d_m` along world x, y, z and rotated by `d_deg` about each camera axis."""
    return Pose(pose.R_world_from_cam @ so3_exp(np.radians([d_deg] * 3)), pose.center + d_m)


def calibrate(
    drive: Drive, priors: list[Pose], frames: list[np.ndarray] | None = None
) -> tuple[SequenceCalibration, list[Pose]]:
    """Calibrate `priors` over all frames (`frames` replace the rendered ones); calibrated priors."""
    res, imgs, caster, times = drive
    n = len(priors)
    cal = calibrate_sequence(res.manifest.camera, caster, list(range(n)), MemoryFrames(frames or imgs),
                             dict(enumerate(priors)), times, res.manifest.accuracy)
    return cal, apply_calibration(priors, [times[i] for i in range(n)], cal)


def errors(truth: list[Pose], poses: list[Pose]) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and rotation (deg) error `(N,)` of `poses` against `truth`."""
    d = np.array([pose_delta(t, p) for t, p in zip(truth, poses, strict=True)])
    return np.linalg.norm(d[:, 3:], axis=1), np.degrees(np.linalg.norm(d[:, :3], axis=1))


def test_a_5m_position_offset_is_calibrated_away(drive: Drive) -> None:
    truth = list(drive[0].truth.poses)
    priors = [offset_pose(p, 5.0, 0.0) for p in truth]
    cal, out = calibrate(drive, priors)
    assert cal.accepted, cal.reason
    pos, rot = errors(truth, out)
    # measured (seed 1): max 0.06 m, 0.13 deg; before: 8.7 m
    assert pos.max() < 0.5 and rot.max() < 0.5, (pos.max(), rot.max())
    # the offset goes mostly into b (the lever arm takes the rest)
    assert np.linalg.norm(cal.offset_m - (-5.0)) < 1.5, cal.offset_m
    acc = calibrated_accuracy(cal, prior=drive[0].manifest.accuracy)
    assert acc is not None and np.all(acc.position_m < 3.0) and np.all(np.isfinite(acc.attitude_deg))
    rep = calibration_report(cal)
    assert rep["run"] is True and rep["accepted"] is True and len(rep["gnss_offset_m"]) == 3


def test_a_2deg_attitude_offset_is_recovered(drive: Drive) -> None:
    truth = list(drive[0].truth.poses)
    priors = [offset_pose(p, 0.0, 2.0) for p in truth]
    cal, out = calibrate(drive, priors)
    assert cal.accepted, cal.reason
    pos, rot = errors(truth, out)
    # measured (seed 1): max 0.10 deg, 0.02 m; before: 3.5 deg
    assert rot.max() < 0.3 and pos.max() < 0.3, (rot.max(), pos.max())
    assert np.allclose(np.degrees(cal.boresight_rad), -2.0, atol=0.2)


@pytest.mark.parametrize("kind", ["noise", "white", "blank"])
def test_frames_without_the_scene_are_not_accepted_and_the_priors_stay(drive: Drive, kind: str) -> None:
    res, imgs, _, _ = drive
    rng = np.random.default_rng(3)
    if kind == "noise":
        # smoothed noise: mean edge support ~0.25
        frames = [cv2.GaussianBlur(rng.normal(290, 2, imgs[0].shape).astype(np.float32), (0, 0), 3.0)
                  for _ in imgs]
    elif kind == "white":
        # white noise reaches a mean edge support of ~0.42 (near the 0.45 bar); the null support
        # (samples moved off their edges) is as high, which rejects it
        frames = [rng.normal(290, 2, imgs[0].shape).astype(np.float32) for _ in imgs]
    else:
        frames = [np.full(imgs[0].shape, 290.0, np.float32) for _ in imgs]
    priors = [offset_pose(p, 5.0, 0.0) for p in res.truth.poses]
    cal, out = calibrate(drive, priors, frames)
    assert not cal.accepted and cal.reason
    assert all(a is b for a, b in zip(out, priors, strict=True))
    assert calibrated_accuracy(cal, prior=res.manifest.accuracy) is res.manifest.accuracy
    assert mounting_document(res.manifest.mounting, cal)["time_delay_s"] == 0.0


def test_frame_motion_on_a_constant_rate_circle() -> None:
    r, rate, dt = 20.0, np.radians(10.0), 0.1  # 20 m radius, 10 deg/s: 3.5 m/s
    R0 = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # camera looking along +x, level
    t = 5.0 + dt * np.arange(30)
    poses = []
    for tk in t:
        a = rate * tk
        Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        poses.append(Pose(Rz @ R0, np.array([r * np.cos(a), r * np.sin(a), 2.0])))
    v, w = frame_motion(poses, t)
    a = rate * t
    v_true = r * rate * np.c_[-np.sin(a), np.cos(a), np.zeros_like(a)]
    w_cam = R0.T @ np.array([0.0, 0.0, rate])  # the world z rate in camera axes (constant)
    # central differences: the chord, relative error (rate·dt)²/6 ~ 5e-5
    assert np.allclose(v[1:-1], v_true[1:-1], atol=1e-3 * r * rate)
    # one-sided at the ends: direction off by rate·dt/2
    assert np.allclose(v[[0, -1]], v_true[[0, -1]], atol=0.01 * r * rate)
    assert np.allclose(w, w_cam, atol=1e-9)
    v1, w1 = frame_motion(poses[:1], t[:1])
    assert not v1.any() and not w1.any()


def test_design_maps_a_pure_time_delay_to_minus_tau_times_the_motion() -> None:
    pose = Pose(so3_exp(np.array([0.3, -0.2, 1.1])), np.array([10.0, 20.0, 3.0]))
    v, w = np.array([8.0, -3.0, 0.2]), np.array([0.01, -0.02, 0.15])
    tau = 0.04
    theta = np.zeros(10)
    theta[9] = tau
    d = design(pose, v, w) @ theta
    assert np.allclose(d[:3], -tau * w) and np.allclose(d[3:], -tau * v)
    theta = np.zeros(10)
    theta[6:9] = [1.0, 2.0, 3.0]  # a lever-arm correction is rotated into world axes
    assert np.allclose((design(pose, v, w) @ theta)[3:], pose.R_world_from_cam @ [1.0, 2.0, 3.0])


# -- mounting conversion -------------------------------------------------------------------------
def curved_manifest(n: int = 30, mounting: Mounting | None = None) -> SequenceManifest:
    """A drive turning left at 10 deg/s, 10 m/s, rolling and pitching a little, 10 Hz; a side-
    looking camera (view = body right) with a boresight and lever arm; `crs` "model", grid
    headings."""
    M = np.array([[-1.0, 0, 0], [0, 0, 1], [0, 1, 0]])
    mnt = mounting or Mounting(M, np.array([0.8, -1.5, 2.5]), np.array([0.4, -0.3, -1.2]))
    frames = []
    for i in range(n):
        t = 100.0 + 0.1 * i
        heading = 30.0 - 10.0 * (t - 100.0)
        h = np.radians(heading)
        pos = np.array([50.0 * np.sin(h), 50.0 * np.cos(h), 40.0 + 0.2 * i])
        att = np.array([1.5 * np.sin(t), 2.0 + 0.5 * np.cos(0.7 * t), heading % 360.0])
        frames.append(FrameRecord(i, f"frames/{i:06d}.png", t, pos, att))
    return SequenceManifest(
        platform="drive", crs="model", camera=Camera(640, 512, 600.0, 600.0, 319.5, 255.5),
        radiometry=Radiometry(), mounting=mnt, frames=tuple(frames),
    )


def compare(manifest: SequenceManifest, theta: np.ndarray) -> tuple[float, float]:
    """Max rotation (rad) and centre (m) difference between `apply_calibration` of the manifest's
    priors and `prior_poses` with the converted mounting and delay (plus the GNSS offset)."""
    cal = SequenceCalibration(theta=theta, covariance=np.eye(10) * 1e-6, accepted=True)
    priors = prior_poses(manifest, None)
    times = [f.time for f in manifest.frames]
    linear = apply_calibration(priors, times, cal)
    doc = mounting_document(manifest.mounting, cal)
    mnt = Mounting(manifest.mounting.camera_to_body, np.array(doc["boresight_deg"]),
                   np.array(doc["lever_arm_m"]))
    exact = prior_poses(manifest, None, time_delay_s=doc["time_delay_s"], mounting=mnt)
    pairs = list(zip(linear, exact, strict=True))
    rot = max(float(np.linalg.norm(pose_delta(a, b)[:3])) for a, b in pairs)
    pos = max(float(np.linalg.norm(a.center - (b.center + cal.offset_m))) for a, b in pairs)
    return rot, pos


def test_the_mounting_round_trips_exactly_without_a_delay() -> None:
    theta = np.r_[0.01, -0.02, 0.015, 0.3, -0.2, 0.5, 0.2, -0.1, 0.3, 0.0]
    rot, pos = compare(curved_manifest(), theta)
    assert rot < 1e-6 and pos < 1e-3, (rot, pos)
    # a zero calibration gives back the manifest's mounting
    m = curved_manifest().mounting
    same = calibrated_mounting(m, SequenceCalibration(theta=np.zeros(10), accepted=True))
    assert np.allclose(same.boresight_deg, m.boresight_deg) and np.allclose(same.lever_arm_m, m.lever_arm_m)


def test_the_mounting_round_trips_to_first_order_with_a_delay() -> None:
    theta = np.r_[0.01, -0.02, 0.015, 0.3, -0.2, 0.5, 0.2, -0.1, 0.3, 0.03]
    rot, pos = compare(curved_manifest(), theta)
    # apply_calibration linearises the delay (30 ms at 10 m/s and 10 deg/s: 0.3 m, 0.3 deg)
    assert rot < 2e-4 and pos < 0.02, (rot, pos)


def test_boresight_angles_are_wrapped_near_180() -> None:
    M = np.eye(3)
    m = Mounting(M, np.array([0.0, 0.0, 179.5]), np.zeros(3))
    cal = SequenceCalibration(theta=np.r_[0, 0, np.radians(1.0), np.zeros(7)], accepted=True)
    assert np.allclose(calibrated_mounting(m, cal).boresight_deg, [0, 0, -179.5], atol=1e-9)
    assert np.allclose(wrap_deg(np.array([180.0, -180.0, 540.0, -190.0])), [180, 180, 180, 170])
    assert calibration_report(None) == {"run": False}


def test_frame_parts_see_what_the_whole_scene_wireframe_sees(drive: Drive) -> None:
    """`FrameWireframes.visible` (a frame's part of the scene wireframe) gives exactly the samples of
    `visible_samples` on the whole wireframe: near the pose a part was cut for, beyond its margins
    (cut again), and with samples asked for outside the frame."""
    res, _, caster, _ = drive
    wf = mesh_wireframe(caster.mesh, EdgeOptions())
    cam = res.manifest.camera
    parts = FrameWireframes(wf, cam)
    wide = replace(EdgeOptions(), image_margin_px=-200.0)
    rng = np.random.default_rng(5)
    seen = 0
    for i, pose in enumerate(res.truth.poses[::4]):
        for size in (0.0, 1.0, 1.9, 5.0):  # degrees and metres; margins 2 m, 2 deg
            d = rng.normal(size=6)
            d[:3] *= np.radians(size) / np.linalg.norm(d[:3])
            d[3:] *= size / np.linalg.norm(d[3:])
            p = apply_delta(pose, d)
            for eo in (EdgeOptions(), wide):
                whole = visible_samples(wf, cam, p, caster, eo, 10**6)
                part = parts.visible(i, p, caster, eo, 10**6)
                for name in ("points", "edge", "direction", "weight", "corners", "corner_points"):
                    assert np.array_equal(getattr(whole, name), getattr(part, name)), (i, size, name)
                seen += len(whole.points)
    assert seen > 1000


def test_the_translation_search_is_coarse_to_fine() -> None:
    """The whole range of common world translations is searched on about a thousand nodes, not on
    the 13³ = 2,197 of a 1 m grid over ±6 m, then refined to a quarter step around the best; the
    units' narrow search (±1 m, 0.5 m) stays the plain two-level one."""
    jo = JointOptions()
    levels = _translation_levels(jo)
    first = (2 * round(levels[0][0] / levels[0][1]) + 1) ** 3
    # later whole-range levels: the nodes within two steps of the previous level's best
    whole = first + sum(2 * jo.translation_candidates * 5**3 for *_, w in levels[1:] if w)
    assert first <= 7**3 and whole < 2197 / 2, (first, whole)
    assert np.isclose(levels[-1][1], jo.translation_step_m / 4) and not levels[-1][4]
    narrow = _translation_levels(replace(jo, translation_max_m=1.0, translation_step_m=0.5))
    assert [(h, s) for h, s, *_ in narrow] == [(1.0, 0.5), (0.5, 0.125)]


@dataclass
class RepeatedFrames:
    """A `FrameSource` repeating `imgs` (frame i is `imgs[i % len(imgs)]`) that counts its loads."""

    imgs: list[np.ndarray]
    loads: list[int] = field(default_factory=list)

    def load(self, index: int) -> np.ndarray:
        """Frame `index` `(H, W)` float32."""
        self.loads.append(index)
        return self.imgs[index % len(self.imgs)]


def test_the_calibration_cost_does_not_grow_with_the_sequence_length(drive: Drive,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A 3× longer sequence (the drive's frames repeated) loads as many frames and computes about
    as many visible wireframes: a bounded sample of frames takes part."""
    res, imgs, caster, _ = drive
    truth = list(res.truth.poses)
    calls = [0]
    counted = edge_observations.visible_wireframe

    def counting(*args: object, **kwargs: object) -> object:
        calls[0] += 1
        return counted(*args, **kwargs)

    monkeypatch.setattr(edge_observations, "visible_wireframe", counting)
    cost = {}
    for n in (120, 360):
        frames = RepeatedFrames(imgs)
        calls[0] = 0
        priors = {i: offset_pose(truth[i % N_FRAMES], 1.0, 0.0) for i in range(n)}
        times = {i: 0.1 * i for i in range(n)}
        calibrate_sequence(res.manifest.camera, caster, list(range(n)), frames, priors, times,
                           res.manifest.accuracy)
        cost[n] = (len(frames.loads), calls[0])
    assert cost[360][0] <= CalibrationOptions().max_frames and cost[360][0] <= cost[120][0] + 2, cost
    assert cost[360][1] <= 1.3 * cost[120][1], cost


def test_the_start_comes_from_a_stretch_when_no_correction_fits_the_whole_drive(
        drive: Drive, monkeypatch: pytest.MonkeyPatch) -> None:
    """Where one common correction of the frames spread over the whole drive is not found (a long
    drive's turns turn its lever arm; the NRW 300-frame drive), the start is searched on
    consecutive stretches in turn and the calibration goes on from the first one found. Here the
    search is refused whenever it sees frames of the drive's last third."""
    from workers.pipeline.orientation import calibration as calibration_module

    real = calibration_module.joint_fit
    seen: list[list[int]] = []

    def no_fit_over_the_last_third(camera, wf, caster, frames, *args, **kwargs):  # type: ignore[no-untyped-def]
        seen.append(list(frames))
        fit = real(camera, wf, caster, frames, *args, **kwargs)
        if max(frames) >= 2 * N_FRAMES // 3:
            return replace(fit, accepted=False, reason="refused by the test")
        return fit

    monkeypatch.setattr(calibration_module, "joint_fit", no_fit_over_the_last_third)
    truth = list(drive[0].truth.poses)
    priors = [offset_pose(p, 2.0, 1.0) for p in truth]
    cal, out = calibrate(drive, priors)
    assert cal.accepted, cal.reason
    assert len(seen) == 2 and max(seen[1]) < 2 * N_FRAMES // 3 <= max(seen[0]), seen
    pos, rot = errors(truth, out)
    # every frame, the last third included, is calibrated (before: rejected, 3.5 m / 1.7° off)
    assert pos.max() < 0.3 and rot.max() < 0.3, (pos.max(), rot.max())
    # with one stretch (the whole drive) there is no start
    one = replace(CalibrationOptions(), start_segments=1)
    res, imgs, caster, times = drive
    rejected = calibrate_sequence(res.manifest.camera, caster, list(range(N_FRAMES)), MemoryFrames(imgs),
                                  dict(enumerate(priors)), times, res.manifest.accuracy, one)
    assert not rejected.accepted and "no common correction" in rejected.reason


@dataclass(frozen=True)
class DelayTestFrame:
    """A frame for `calibration_delay.delay_search`: index, prior and design `(6, 10)`."""

    index: int
    prior: Pose
    A: np.ndarray


def test_the_delay_search_says_when_no_frame_tells_delays_apart(drive: Drive) -> None:
    """At the drive's 0.1 s frame spacing the delay moves the samples and is searched (a delay);
    with the same poses 10 s apart (100 times slower) a delay step moves no sample half a pixel:
    None, not 0 s."""
    from workers.pipeline.orientation.calibration_delay import delay_search
    from workers.pipeline.orientation.calibration_model import frame_designs

    res, imgs, caster, _ = drive
    truth = list(res.truth.poses)
    o = CalibrationOptions()
    wfs = FrameWireframes(mesh_wireframe(res.mesh, o.edges), res.manifest.camera)
    frames = list(range(N_FRAMES))
    picked = frames[::4]
    found = {}
    for spacing in (0.1, 10.0):
        A = frame_designs(frames, dict(enumerate(truth)), {i: spacing * i for i in frames}, picked)
        data = [DelayTestFrame(i, truth[i], A[i]) for i in picked]
        found[spacing] = delay_search(res.manifest.camera, wfs, caster, data, dict(enumerate(imgs)),
                                      np.zeros(10), o.delay_search_s, o.delay_step_s, o.edges, o.fit)
    assert found[0.1] is not None and abs(found[0.1]) <= o.delay_step_s, found  # the truth: no delay
    assert found[10.0] is None, found


def test_a_delay_the_frames_cannot_tell_apart_keeps_the_adjusted_one(drive: Drive,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """When the delay search cannot tell delays apart (None: a flight's straight lines), the
    adjusted parameters stand, τ included: the adjustment is not run again from τ = 0."""
    from workers.pipeline.orientation import calibration as calibration_module

    real = calibration_module._adjust
    starts: list[np.ndarray] = []

    def counted(*args, **kwargs):  # type: ignore[no-untyped-def]
        starts.append(np.array(args[4]))
        return real(*args, **kwargs)

    monkeypatch.setattr(calibration_module, "_adjust", counted)
    monkeypatch.setattr(calibration_module, "delay_search", lambda *args, **kwargs: None)
    truth = list(drive[0].truth.poses)
    cal, _ = calibrate(drive, [offset_pose(p, 2.0, 0.0) for p in truth])
    assert cal.accepted, cal.reason
    assert len(starts) == 1 and starts[0][9] == 0.0, starts

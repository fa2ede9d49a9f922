"""Sequence orientation without an accepted calibration (issue 19, item 0): a synthetic
close-range sequence of one facade (a one-wall model, a camera walking 10 m in front of it) with
priors off by a common error and per-frame noise of 0.5 m / 1°, oriented by the orient stage
of `citytherm run` after a rejected calibration; and the acceptance rules of
`orientation.sequence_acceptance` on small hand-made blocks."""

from __future__ import annotations

import doctest
from pathlib import Path

import numpy as np
import pytest

import workers.pipeline.orientation.smoothing as smoothing_module
from tests.unit.orientation_scenes import perturb
from workers import job
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building, ModelHeader, Polygon, Ring
from workers.pipeline.geometry.manifest import Accuracy, MemoryFrames
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.orientation.building import CoregisterOptions
from workers.pipeline.orientation.bundle import BundleResult
from workers.pipeline.orientation.calibration import SequenceCalibration
from workers.pipeline.orientation.quality import reprojection_rms
from workers.pipeline.orientation.sequence_acceptance import ConfirmOptions, confirm_block
from workers.pipeline.orientation.smoothing import smooth_poses
from workers.pipeline.orientation.tracks import Tracks
from workers.pipeline.units import UnitOptions

N = 40
ACC = Accuracy(position_m=np.full(3, 0.5), attitude_deg=np.full(3, 1.0))


def one_wall(width: float = 20.0, height: float = 12.0) -> Building:
    """A one-wall model: a single vertical WallSurface in the plane y = 0, its normal along −y."""
    c = np.array([(0, 0, 0), (width, 0, 0), (width, 0, height), (0, 0, height), (0, 0, 0)], float)
    ring = Ring(id="W1_r", coords=c)
    return Building(id="W1", polygons=(Polygon(id="W1_w", exterior=ring, surface_class="WallSurface"),))


def wall_points(width: float = 20.0, height: float = 12.0) -> np.ndarray:
    """`(273, 3)` points every metre on the wall (its corners included)."""
    gx, gz = np.meshgrid(np.linspace(0, width, 21), np.linspace(0, height, 13))
    return np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], axis=1)


@pytest.fixture(scope="module")
def facade():
    from workers.pipeline.synth import SynthOptions, synthesize

    res = synthesize(
        [one_wall()],
        SynthOptions(platform="terrestrial", n_frames=N, seed=3, buildings=1, frame_interval_s=0.4),
    )
    rng = np.random.default_rng(7)
    common_m, common_deg = np.array([0.3, -0.2, 0.25]), np.array([0.5, -0.6, 0.4])
    prior = [
        perturb(T, common_m + rng.normal(0, 0.5, 3), common_deg + rng.normal(0, 1.0, 3))
        for T in res.truth.poses
    ]
    return res, {i: res.frames.load(i) for i in range(N)}, prior


def _errors(res, poses) -> np.ndarray:
    """Per frame: RMS reprojection error (px) of the wall's points that the true pose sees."""
    cam, T = res.manifest.camera, res.truth.poses
    return np.array([reprojection_rms(cam, wall_points(), poses[i], T[i]) for i in range(N)])


def test_the_walk_faces_the_wall(facade) -> None:
    res, _, _ = facade
    C = np.array([p.center for p in res.truth.poses])
    assert np.all(np.abs(C[:, 1] + 10.0) < 0.5) and C[0, 0] - C[-1, 0] > 15.0  # 10 m in front, walking
    assert np.all(np.isfinite(_errors(res, res.truth.poses)))  # every frame sees the wall


def test_the_orient_stage_orients_a_facade_after_a_rejected_calibration(facade) -> None:
    res, images, prior = facade
    m = res.manifest
    ingested = job.Ingested(
        city_gml=Path("<wall>"),
        package_dir=Path("<memory>"),
        header=ModelHeader("2.0"),
        manifest=m,
        frames=MemoryFrames(images),
        priors=tuple(prior),
        buildings=res.buildings,
        n_model_buildings=1,
        radiometry=m.radiometry,
    )
    rejected = SequenceCalibration(theta=np.zeros(10), reason="too few frames see the model")
    calibrated = job.Calibrated(rejected, tuple(prior), ACC)
    options = job.RunOptions(unit=UnitOptions(refine=CoregisterOptions()))
    assert job.orients(options, calibrated, m.platform) and m.platform == "terrestrial"
    oriented = job.orient(ingested, calibrated, options)
    assert oriented.report["run"] and oriented.report["priors"] == "manifest", oriented.report
    noise = oriented.report["prior_noise"]  # the per-frame noise measured from the priors
    assert noise["smoothed_start"] and 0.6 < noise["attitude_deg"] < 1.6 and 0.3 < noise["position_m"] < 0.8
    before, after = _errors(res, prior), _errors(res, oriented.orientation.poses)
    assert np.mean(before > 5.0) >= 0.8
    assert np.mean(after < 1.0) >= 0.9 and np.median(after) < 0.5, np.round(after, 2)
    assert all(b["accepted"] for b in oriented.report["blocks"])
    # without refinement the stage does not run; flights are oriented by it too (issue 18)
    assert not job.orients(job.RunOptions.build(refine=False), calibrated, "terrestrial")
    assert job.orients(options, calibrated, "flight")


def test_smoothing_keeps_a_steady_motion_and_removes_white_noise() -> None:
    assert doctest.testmod(smoothing_module).failed == 0
    rng = np.random.default_rng(2)
    t = {k: 0.4 * k for k in range(40)}
    truth = {k: Pose(np.eye(3), np.array([1.2 * t[k], -10.0, 1.6])) for k in t}
    noisy = {k: perturb(p, rng.normal(0, 0.5, 3), rng.normal(0, 1.0, 3)) for k, p in truth.items()}
    smooth = smooth_poses(noisy, range(40), t, 1.0)
    e0 = np.array([np.linalg.norm(noisy[k].center - truth[k].center) for k in t])
    e1 = np.array([np.linalg.norm(smooth[k].center - truth[k].center) for k in t])
    step = np.array([np.linalg.norm(smooth[k + 1].center - smooth[k].center) for k in range(39)])
    assert np.median(e1) < 0.5 * np.median(e0)
    assert np.all(np.abs(step - 0.48) < 0.15)  # consecutive start poses move as the camera did
    assert smooth_poses(noisy, range(40), t, 0.0)[3] is noisy[3]


# --- the acceptance rules on a hand-made block: 6 frames 10 m in front of the wall y = 0 ---

CAM = Camera(width=640, height=512, fx=780.0, fy=780.0, cx=319.5, cy=255.5)


def _block(
    spread: float = 1.0,
    off_plane_m: float = 0.0,
    moved: int | None = None,
    edges: dict[int, float] | None = None,
    variance: float = 1e-6,
):
    """Frames 0..5 looking at the wall from y = −10, 40 points on it seen by all of them; the
    adjusted poses are the priors except frame `moved` (3 m along x); `off_plane_m` moves the
    adjusted points off their plane; `spread` scales the points' extent on the wall; `variance`:
    of every pose parameter in the adjustment's covariance (rad², m²)."""
    frames = list(range(6))
    R = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # camera x east, y down, z north
    prior = {f: Pose(R, np.array([10.0 + 0.5 * f, -10.0, 1.6])) for f in frames}
    rng = np.random.default_rng(0)
    X = np.stack(
        [11.2 + spread * rng.uniform(-3, 3, 40), np.zeros(40), 1.6 + spread * rng.uniform(-2, 2, 40)], axis=1
    )
    track, frame, uv = [], [], []
    for f in frames:
        p, _ = prior[f].project(CAM, X)
        track += list(range(40))
        frame += [f] * 40
        uv.append(p)
    normal = np.tile([0.0, -1.0, 0.0], (40, 1))
    tracks = Tracks(np.array(track), np.array(frame), np.concatenate(uv), X, normal, np.zeros(40))
    poses = dict(prior)
    if moved is not None:
        poses[moved] = Pose(R, prior[moved].center + np.array([3.0, 0.0, 0.0]))
    points = X + np.array([0.0, off_plane_m, 0.0])
    sup = edges or {}
    res = BundleResult(
        poses=poses,
        covariance={f: np.eye(6) * variance for f in frames},
        ties={f: 40 for f in frames},
        tie_rms_px={f: 0.1 for f in frames},
        edge_rms_px={},
        edge_support=sup,
        null_support=dict.fromkeys(sup, 0.0),
        matched_edges={},
        points=points,
        inlier=np.ones(len(track), bool),
        sigma0=0.4,
    )
    info = np.diag([np.radians(1.0) ** -2] * 3 + [0.5**-2] * 3)
    return frames, prior, res, tracks, info


def test_a_block_without_edges_is_confirmed_by_its_planes_and_tracks() -> None:
    frames, prior, res, tracks, info = _block()
    c = confirm_block(CAM, frames, prior, res, tracks, info)
    assert c.reason == "" and c.by_planes == frames and all(c.taken.values())
    assert all(a is None for a in c.anchor.values()) and c.plane_rms_m < 1e-6


@pytest.mark.parametrize("case", ["off_plane", "on_a_line", "torn", "undetermined"])
def test_a_block_that_is_not_confirmed_is_rejected(case: str) -> None:
    kw = {
        "off_plane": {"off_plane_m": 0.8},
        "on_a_line": {"spread": 0.02},
        "torn": {"moved": 2},
        "undetermined": {"variance": 1.0},
    }[case]
    frames, prior, res, tracks, info = _block(**kw)
    c = confirm_block(
        CAM, frames, prior, res, tracks, info, options=ConfirmOptions(max_inconsistent_share=0.1)
    )
    assert c.reason and not any(c.taken.values()), c
    if case == "torn":
        assert c.inconsistent == [2]
    if case == "undetermined":  # a pose known to a metre is no orientation, whatever the edges say
        assert c.undetermined == list(range(6))


def test_edges_decide_where_they_exist() -> None:
    # edges seen and confirming: taken; edges seen and contradicting everywhere: rejected
    frames, prior, res, tracks, info = _block(edges=dict.fromkeys(range(6), 0.9))
    c = confirm_block(CAM, frames, prior, res, tracks, info)
    assert c.reason == "" and all(c.anchor.values()) and c.by_planes == [] and all(c.taken.values())
    frames, prior, res, tracks, info = _block(edges=dict.fromkeys(range(6), 0.05))
    c = confirm_block(CAM, frames, prior, res, tracks, info)
    assert c.reason and not any(c.taken.values())

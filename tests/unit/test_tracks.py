"""Feature tracks on the model's surfaces (`workers.pipeline.orientation.tracks`) on a synthetic drive with
known true poses: every tracked position is compared with the true correspondence (the first
view's ray onto the model, projected with the true pose of the later frame)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.unit.orientation_scenes import CAMERA, look_at, perturb
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.quality import tie_errors
from workers.pipeline.orientation.tracks import TrackOptions, plane_affine, texture_strength, track_sequence


@pytest.fixture(scope="module")
def drive():
    from workers.pipeline.synth import ErrorOptions, SynthOptions, procedural_block, synthesize

    opts = SynthOptions(platform="drive", n_frames=16, seed=1, buildings=2,
                        errors=ErrorOptions(enabled=False))
    res = synthesize(procedural_block(6, seed=1), opts)
    images = {i: res.frames.load(i) for i in range(16)}
    return res, images, RayCaster(res.mesh)


def test_texture_strength_is_high_at_corners_low_on_edges_and_flat() -> None:
    img = np.zeros((64, 64), np.float32)
    img[32:, 32:] = 1.0  # a corner at (32, 32); straight edges along row 32 and column 32
    s = texture_strength(img, 2.5)
    assert s[32, 32] > 20 * s[50, 32]  # the corner against a point on the vertical edge
    assert s[50, 32] < 1e-3 and s[10, 10] < 1e-9


def test_plane_affine_of_a_fronto_parallel_plane_is_the_depth_ratio() -> None:
    cam = Camera(width=640, height=512, fx=800.0, fy=800.0, cx=319.5, cy=255.5)
    pa = look_at([0.0, -10.0, 0.0], [0.0, 0.0, 0.0])
    pb = look_at([0.0, -5.0, 0.0], [0.0, 5.0, 0.0])  # half the distance to the plane y = 0
    A = plane_affine(cam, pa, pb, np.array([[319.5, 255.5], [400.0, 300.0]]), np.zeros((2, 3)),
                     np.array([[0.0, -1.0, 0.0]] * 2))
    np.testing.assert_allclose(A, np.broadcast_to(2.0 * np.eye(2), A.shape), atol=1e-6)


def test_tracks_from_the_true_poses_are_a_tenth_of_a_pixel_accurate(drive) -> None:
    res, images, caster = drive
    truth = res.truth.poses
    tr = track_sequence(res.manifest.camera, list(range(16)), images, dict(enumerate(truth)), caster)
    assert tr.n_tracks > 100 and np.median(tr.lengths()) >= 3
    assert tr.lengths().min() >= 2
    e = tie_errors(tr, res.manifest.camera, truth, caster)
    assert len(e) > 300
    # a few per cent drift along the epipolar line onto the next window of a regular grid (the
    # bundle adjustment drops them against their point and its plane)
    assert np.median(e) < 0.1 and np.percentile(e, 95) < 0.3 and np.mean(e > 1.0) < 0.02
    # every track lies on a model wall, as the ray cast from its first view says
    assert np.all(np.abs(tr.normal[:, 2]) < 0.2)


def test_tracks_from_poses_with_a_common_error_stay_accurate(drive) -> None:
    # 0.5 m and 0.5° common error, 0.1 m and 0.1° per frame (calibrated GNSS/INS): the predictions
    # are pixels off, the tracking is not
    res, images, caster = drive
    truth = res.truth.poses
    rng = np.random.default_rng(3)
    wrong = {i: perturb(T, np.array([0.5, -0.3, 0.2]) + rng.normal(0, 0.1, 3),
                        np.full(3, 0.5) + rng.normal(0, 0.1, 3)) for i, T in enumerate(truth)}
    tr = track_sequence(res.manifest.camera, list(range(16)), images, wrong, caster)
    e = tie_errors(tr, res.manifest.camera, truth, caster)
    assert len(e) > 300
    assert np.median(e) < 0.2 and np.mean(e > 1.0) < 0.02


def test_frames_without_texture_give_no_tracks(drive) -> None:
    res, _, caster = drive
    blank = {i: np.full((CAMERA.height, CAMERA.width), 280.0, np.float32) for i in range(4)}
    rng = np.random.default_rng(0)
    shape = (CAMERA.height, CAMERA.width)
    noise = {i: (280.0 + rng.normal(0, 0.05, shape)).astype(np.float32) for i in range(4)}
    for imgs in (blank, noise):
        tr = track_sequence(res.manifest.camera, list(range(4)), imgs, dict(enumerate(res.truth.poses)),
                            caster)
        assert tr.n_tracks == 0 or len(tr.track) < 10


def test_no_border_still_detects(drive) -> None:
    # a border of 0 px must not clear the whole detection map (a slice [-0:] is everything)
    res, images, caster = drive
    tr = track_sequence(res.manifest.camera, [0, 1], images, dict(enumerate(res.truth.poses)), caster,
                        TrackOptions(border_px=0))
    assert tr.n_tracks > 20

"""Tie points of consecutive frames: tracking, epipolar and model-transfer residuals against truth."""

from __future__ import annotations

import numpy as np
import pytest

from tests.unit.orientation_scenes import CAMERA, Renderer, box_building, drive_poses, perturb
from workers.pipeline.coregister_geometry import apply_delta
from workers.pipeline.tiepoints import (
    model_points,
    sampson_jacobian,
    sampson_px,
    stretch8,
    tie_pairs,
    transfer_jacobian,
    transfer_px,
)

B1 = box_building("B1", 0, 0, 20, 12, 9, ridge=4)
B2 = box_building("B2", 24, 2, 10, 10, 6)


@pytest.fixture(scope="module")
def drive():
    scene = Renderer([B1, B2], seed=4)
    truth = drive_poses(np.array([16.0, -11.0, 1.8]), np.array([-1.0, 0.0, 0.0]), 5, step_m=0.8)
    frames = {i: scene.render(p, i) for i, p in enumerate(truth)}
    return scene, dict(enumerate(truth)), frames


def test_stretch8_uses_the_box_and_returns_uint8():
    img = np.zeros((40, 50), np.float32)
    img[10:30, 10:40] = np.linspace(270.0, 272.0, 30)[None]
    img[:10] = 250.0  # cold sky outside the box
    u8 = stretch8(img, (10, 10, 40, 30))
    assert u8.dtype == np.uint8 and u8.shape == img.shape
    assert int(u8[20, 39]) - int(u8[20, 10]) > 150  # the building's range fills the 8 bits


def test_tie_points_fit_the_true_relative_poses(drive):
    scene, truth, frames = drive
    rng = np.random.default_rng(3)
    wrong = {i: perturb(p, rng.normal(0, 0.3, 3), rng.normal(0, 0.3, 3)) for i, p in truth.items()}
    # tracking starts from the prediction over the model with the (wrong) priors: along a row of
    # windows a plain tracker can lock onto the neighbouring window, on the epipolar line
    pairs = tie_pairs(CAMERA, frames, list(frames), raycaster=scene.caster, poses=wrong)
    assert len(pairs) >= 4  # gaps 1 and 2 over 5 frames: 7 possible
    for tp in pairs:
        assert len(tp.xa) >= 20
        r_true = np.abs(sampson_px(CAMERA, truth[tp.a], truth[tp.b], tp.xa, tp.xb))
        r_wrong = np.abs(sampson_px(CAMERA, wrong[tp.a], wrong[tp.b], tp.xa, tp.xb))
        assert np.median(r_true) < 0.3
        assert np.median(r_wrong) > 3 * np.median(r_true) + 0.5
        # through the model: the rays of frame a meet the facade, projected into b
        X0, nrm, ok = model_points(scene.caster, truth[tp.a], tp.xa)
        assert ok.sum() >= 10  # the others lie on the ground (not in the model)
        t_true = np.linalg.norm(transfer_px(CAMERA, truth[tp.a], truth[tp.b], tp.xa[ok], tp.xb[ok], X0[ok],
                                            nrm[ok]), axis=1)
        assert np.median(t_true) < 0.8
        t_wrong = np.linalg.norm(transfer_px(CAMERA, wrong[tp.a], wrong[tp.b], tp.xa[ok], tp.xb[ok], X0[ok],
                                             nrm[ok]), axis=1)
        assert np.median(t_wrong) > 5 * np.median(t_true)


def test_large_image_motion_is_tracked_from_the_model_prediction(drive):
    scene, truth, frames = drive
    # the second frame turned by 6 degrees (~80 px): plain pyramidal tracking loses most points,
    # the prediction over the model with poses within a few tenths of the truth does not
    turned = perturb(truth[1], np.zeros(3), np.array([0.0, 6.0, 0.0]))
    imgs = {0: frames[0], 1: scene.render(turned, 1)}
    guess = {0: perturb(truth[0], np.array([0.2, -0.1, 0.1]), np.array([0.2, 0.0, 0.1])),
             1: perturb(turned, np.array([-0.1, 0.2, 0.0]), np.array([0.0, -0.2, 0.2]))}
    got = tie_pairs(CAMERA, imgs, [0, 1], raycaster=scene.caster, poses=guess)
    assert len(got) == 1 and len(got[0].xa) >= 30
    r = np.abs(sampson_px(CAMERA, truth[0], turned, got[0].xa, got[0].xb))
    assert np.median(r) < 0.3


def test_jacobians_match_finite_differences_of_the_residuals(drive):
    scene, truth, frames = drive
    tp = tie_pairs(CAMERA, frames, [0, 1])[0]
    pa, pb = truth[0], truth[1]
    d = np.array([2e-3, -1e-3, 1.5e-3, 0.02, -0.03, 0.01])
    r, J = sampson_jacobian(CAMERA, pa, pb, tp.xa, tp.xb)
    lin = r + J[:, 6:] @ d
    assert np.allclose(sampson_px(CAMERA, pa, apply_delta(pb, d), tp.xa, tp.xb), lin, atol=0.05)
    X0, nrm, ok = model_points(scene.caster, pa, tp.xa)
    r2, J2 = transfer_jacobian(CAMERA, pa, pb, tp.xa[ok], tp.xb[ok], X0[ok], nrm[ok])
    lin2 = r2 + J2[:, :, :6] @ d
    moved = transfer_px(CAMERA, apply_delta(pa, d), pb, tp.xa[ok], tp.xb[ok], X0[ok], nrm[ok])
    assert np.allclose(moved, lin2, atol=0.05)
    assert np.abs(moved - r2).max() > 1.0  # the step is not negligible

"""Camera model: round trips over the whole image and agreement with OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from workers.pipeline.geometry.camera import Camera

SPEC_CAMERA = Camera(640, 512, 880.0, 880.0, 319.5, 255.5, k1=-0.12, k2=0.05)
SPEC_K1_STRONG = Camera(640, 512, 880.0, 880.0, 319.5, 255.5, k1=-0.3)
# wide angle: the image corner (r ≈ 0.68) lies close to the fold of the model at r_d ≈ 0.70
STRONG = Camera(640, 512, 600.0, 600.0, 319.5, 255.5, k1=-0.3)
TANGENTIAL = Camera(640, 512, 700.0, 705.0, 322.0, 250.0, k1=-0.2, k2=0.08, p1=0.002, p2=-0.0015, k3=-0.01)
CAMERAS = [SPEC_CAMERA, SPEC_K1_STRONG, STRONG, TANGENTIAL]
IDS = ["spec", "spec-k1=-0.3", "wide-k1=-0.3", "tangential"]


def dense_grid(cam: Camera, step: float = 4.0) -> np.ndarray:
    """Pixel grid `(N, 2)` over the image, including the four corner pixel centres and edges."""
    us = np.unique(np.r_[np.arange(0.0, cam.width - 1, step), cam.width - 1.0, -0.5, cam.width - 0.5])
    vs = np.unique(np.r_[np.arange(0.0, cam.height - 1, step), cam.height - 1.0, -0.5, cam.height - 0.5])
    u, v = np.meshgrid(us, vs)
    return np.column_stack([u.ravel(), v.ravel()])


@pytest.mark.parametrize("cam", CAMERAS, ids=IDS)
def test_round_trip_dense_grid_with_corners(cam: Camera) -> None:
    uv = dense_grid(cam)
    corners = np.array([[0, 0], [cam.width - 1, 0], [0, cam.height - 1], [cam.width - 1, cam.height - 1]])
    assert (np.abs(uv[:, None, :] - corners[None]).sum(-1) == 0).any(axis=0).all()
    rays = cam.bearing(uv)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    assert np.all(rays[:, 2] > 0)
    back = cam.project(rays * 7.3)  # any depth along the ray
    err = np.abs(back - uv).max()
    assert err < 1e-6, f"round trip error {err} px"


@pytest.mark.parametrize("cam", CAMERAS, ids=IDS)
def test_project_agrees_with_cv2_projectPoints(cam: Camera) -> None:
    rng = np.random.default_rng(1)
    # random points inside the field of view (undistorted normalised coordinates within the image)
    ab = cam.normalized_from_pixel(rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (500, 2)))
    z = rng.uniform(2.0, 80.0, 500)
    X = np.column_stack([ab * z[:, None], z])
    ours = cam.project(X)
    ref, _ = cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist_coeffs)
    assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-9


@pytest.mark.parametrize("cam", CAMERAS, ids=IDS)
def test_bearing_agrees_with_cv2_undistortPoints(cam: Camera) -> None:
    rng = np.random.default_rng(2)
    uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (500, 2))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    ref = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), cam.K, cam.dist_coeffs, None, None, crit)
    ref = ref.reshape(-1, 2)
    ours = cam.normalized_from_pixel(uv)
    # OpenCV's fixed-point iteration is less exact than Newton for strong distortion: compare
    # both against the forward model, and against each other to the pixel scale of 1e-3 px.
    assert np.abs(cam.pixel_from_normalized(ours) - uv).max() < 1e-6
    assert np.abs((ours - ref) * cam.fx).max() < 1e-3
    rays = cam.bearing(uv)
    np.testing.assert_allclose(rays[:, :2] / rays[:, 2:], ours, atol=1e-12)


def test_no_distortion_is_pinhole() -> None:
    cam = Camera(100, 80, 50.0, 60.0, 49.5, 39.5)
    X = np.array([[1.0, -2.0, 4.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(cam.project(X), [[49.5 + 12.5, 39.5 - 30.0], [49.5, 39.5]])
    np.testing.assert_allclose(cam.bearing(np.array([[49.5, 39.5]])), [[0.0, 0.0, 1.0]])


def test_points_behind_camera_are_nan() -> None:
    uv = SPEC_CAMERA.project(np.array([[0.0, 0.0, -5.0], [0.1, 0.2, 0.0]]))
    assert np.isnan(uv).all()


def test_pixel_centre_convention_and_in_image() -> None:
    cam = SPEC_CAMERA
    # the principal point of the spec camera is the image centre with pixel centres at integers
    np.testing.assert_allclose(cam.project(np.array([[0.0, 0.0, 1.0]])), [[319.5, 255.5]])
    m = cam.in_image(np.array([[0, 0], [639, 511], [-0.01, 3], [639.01, 3], [np.nan, 1]]))
    assert m.tolist() == [True, True, False, False, False]


def test_scaled_camera_keeps_rays() -> None:
    cam = SPEC_CAMERA
    half = cam.scaled(0.5)
    X = np.array([[1.0, 0.5, 10.0], [-2.0, 1.0, 9.0]])
    uv_full, uv_half = cam.project(X), half.project(X)
    np.testing.assert_allclose((uv_full + 0.5) * 0.5 - 0.5, uv_half, atol=1e-9)


def test_dict_round_trip() -> None:
    assert Camera.from_dict(TANGENTIAL.to_dict()) == TANGENTIAL


def test_points_beyond_the_distortion_fold_do_not_enter_the_image() -> None:
    # k1 = -0.3: r_d = r (1 - 0.3 r²) folds at r² = 1/0.9; a point ~60° off-axis would come back
    # to u ≈ 518 px, inside the image, if the model were applied blindly
    cam = SPEC_K1_STRONG
    assert cam.max_radius2 == pytest.approx(1 / 0.9)
    uv = cam.project(np.array([[1.7, 0.0, 1.0], [1.2, 0.9, 1.0], [1.0, 0.0, 1.0]]))
    assert np.isnan(uv[:2]).all()
    assert np.isfinite(uv[2]).all() and not cam.in_image(uv[2:]).any()
    # a pixel whose distorted radius exceeds the model's maximum has no ray
    assert np.isnan(cam.bearing(np.array([[1100.0, 255.5]]))).all()
    # monotonic models have no fold
    assert SPEC_CAMERA.max_radius2 == float("inf")
    assert Camera(10, 10, 5.0, 5.0, 4.5, 4.5).max_radius2 == float("inf")
    assert Camera(10, 10, 5.0, 5.0, 4.5, 4.5, k1=0.1, k2=-0.01).max_radius2 > 0


def test_every_image_pixel_of_a_wide_strong_lens_has_a_ray() -> None:
    uv = dense_grid(STRONG, step=8.0)
    rays = STRONG.bearing(uv)
    assert np.isfinite(rays).all()

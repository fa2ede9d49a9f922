"""Image features on synthetic frames with known geometry: an antialiased, blurred rectangle."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from workers.pipeline.orientation.features import (
    FeatureError,
    FeatureOptions,
    extract_features,
    normalize_contrast,
    segment_intersections,
)

CORNERS = np.array([[60.3, 50.7], [170.6, 50.7], [170.6, 140.2], [60.3, 140.2]])


def _rectangle_frame(seed: int = 0, ss: int = 4) -> np.ndarray:
    """240x200 kelvin frame: a 10 K warmer axis-aligned rectangle with sub-pixel corners."""
    H, W = 200, 240
    vv, uu = np.mgrid[0 : H * ss, 0 : W * ss] / ss - (ss - 1) / (2 * ss)
    (u0, v0), (u1, v1) = CORNERS[0], CORNERS[2]
    inside = (uu >= u0) & (uu <= u1) & (vv >= v0) & (vv <= v1)
    img = inside.reshape(H, ss, W, ss).mean(axis=(1, 3)) * 10.0 + 280.0
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.7)
    return img + np.random.default_rng(seed).normal(0, 0.05, img.shape).astype(np.float32)


def _nearest(points: np.ndarray, targets: np.ndarray) -> np.ndarray:
    return np.min(np.linalg.norm(points[:, None] - targets[None], axis=2), axis=0)


def test_forstner_points_find_every_corner_within_a_pixel():
    f = extract_features(_rectangle_frame())
    assert len(f.forstner) >= 4
    assert np.all(_nearest(f.forstner, CORNERS) < 1.2)
    # nothing but corners: every point is near one
    assert np.all(_nearest(CORNERS, f.forstner) < 1.2)


def test_segments_lie_on_the_rectangle_sides_and_intersect_at_corners():
    f = extract_features(_rectangle_frame())
    assert len(f.segments) >= 4
    # each segment is horizontal or vertical at one of the side coordinates
    for u0, v0, u1, v1 in f.segments:
        if abs(v1 - v0) < abs(u1 - u0):
            assert min(abs(0.5 * (v0 + v1) - 50.7), abs(0.5 * (v0 + v1) - 140.2)) < 0.5
        else:
            assert min(abs(0.5 * (u0 + u1) - 60.3), abs(0.5 * (u0 + u1) - 170.6)) < 0.5
    assert np.all(_nearest(f.intersections, CORNERS) < 0.7)


def test_intersections_respect_the_angle_and_gap_thresholds():
    segs = np.array([[0.0, 0.0, 10.0, 0.0], [10.5, 0.5, 10.5, 10.0], [0.0, 1.0, 10.0, 2.0], [30, 30, 40, 30]])
    pts = segment_intersections(segs, FeatureOptions(intersection_min_angle_deg=30.0))
    # the near-parallel pair (0, 2) gives nothing; the far segment 3 meets nothing
    assert len(pts) == 2
    assert np.allclose(pts[np.argmin(pts[:, 1])], [10.5, 0.0], atol=1e-9)


def test_distance_pyramid_is_zero_on_edges_and_grows_away():
    f = extract_features(_rectangle_frame(), FeatureOptions(dt_levels=(1, 4)))
    dt1 = f.dt[1]
    assert dt1[140, 120] <= 1.0  # bottom side, v = 140.2
    assert dt1[95, 115] > 10.0  # rectangle centre, far from every side
    assert set(f.dt) == {1, 4}
    assert f.dt[4].shape == (200 // 4, 240 // 4)
    assert f.dt[4][140 // 4, 120 // 4] <= 1.0


def test_roi_features_are_in_full_frame_coordinates():
    img = _rectangle_frame()
    f = extract_features(img, roi=(40, 30, 200, 170))
    assert f.roi == (40, 30, 200, 170)
    assert np.all(_nearest(f.intersections, CORNERS) < 0.7)


def test_normalize_contrast_keeps_order_and_range():
    img = np.random.default_rng(3).normal(280, 2, (50, 60)).astype(np.float32)
    n = normalize_contrast(img)
    assert n.dtype == np.float32 and n.min() >= 0 and n.max() <= 1
    i, j = np.unravel_index(np.argmax(img), img.shape)
    assert n[i, j] == 1.0


def test_bad_input_is_refused():
    with pytest.raises(FeatureError, match="2-D"):
        extract_features(np.zeros((10, 10, 3), np.float32))
    with pytest.raises(FeatureError, match="region of interest"):
        extract_features(np.zeros((100, 100), np.float32), roi=(95, 95, 120, 120))

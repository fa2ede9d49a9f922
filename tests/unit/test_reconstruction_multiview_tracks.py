"""Method 3's TIR tracks on repeated windows. `multiview.consistent_tracks`: a false match along
the epipolar line (the next window of a row) joins two points into one track; triangulated from
start poses a few pixels off, the track's observations do not fit one point and the false one is
dropped. Guided matching (`image_tracks.epipolar_band`): a window repeated up the facade is no
rival of the true match."""

from __future__ import annotations

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import apply_delta
from workers.pipeline.orientation.tracks import Tracks
from workers.pipeline.reconstruction.image_tracks import ImageTrackOptions, epipolar_band, verified_matches
from workers.pipeline.reconstruction.multiview import consistent_tracks
from workers.pipeline.reconstruction.options import ReconstructionOptions

CAMERA = Camera(width=640, height=512, fx=780.0, fy=780.0, cx=319.5, cy=255.5)
#: camera x along world x (the drive), camera z (view) along world y (the facade), y down
R_SIDE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _scene(seed: int) -> tuple[Tracks, dict[int, Pose], np.ndarray]:
    """Points on a facade 10-17 m away seen by 8 frames 1 m apart, 0.3 px of noise, each track
    in 4 consecutive frames; every 10th track's third observation replaced by the projection of
    the point 2 m further along the facade (a repeated window: still on the epipolar line).
    Returns the tracks, start poses (as smoothed priors: a common error of 0.5 m / 0.5°, each
    frame 0.03 m / 0.05° off it) and which observations are false."""
    rng = np.random.default_rng(seed)
    true = {f: Pose(R_SIDE, np.array([1.0 * f, 0.0, 0.0])) for f in range(8)}
    track, frame, uv, false = [], [], [], []
    t = 0
    for first in range(5):
        X = np.column_stack([rng.uniform(first - 1, first + 4, 60), rng.uniform(10, 17, 60),
                             rng.uniform(-2.5, 2.5, 60)])  # fmt: skip
        for x in X:
            for k, f in enumerate(range(first, first + 4)):
                y = x + np.array([2.0, 0.0, 0.0]) if (t % 10 == 0 and k == 2) else x
                q, _ = true[f].project(CAMERA, y[None])
                track.append(t), frame.append(f), uv.append(q[0] + rng.normal(0, 0.3, 2))
                false.append(t % 10 == 0 and k == 2)
            t += 1
    z = np.zeros((t, 3))
    tracks = Tracks(np.array(track), np.array(frame), np.array(uv), z, z.copy(), np.zeros(t))
    common = np.concatenate([rng.normal(0, np.radians(0.5), 3), rng.normal(0, 0.5, 3)])
    own = np.column_stack([rng.normal(0, np.radians(0.05), (8, 3)), rng.normal(0, 0.03, (8, 3))])
    start = {f: apply_delta(p, common + own[f]) for f, p in true.items()}
    return tracks, start, np.array(false)


def test_false_matches_along_the_epipolar_line_are_dropped() -> None:
    """With a 8 px limit, no false observation is left and at least 95 % of the true ones are."""
    tracks, start, false = _scene(3)
    opts = ReconstructionOptions(min_track_length=3, min_angle_deg=1.0, min_depth_m=2.0)
    kept = consistent_tracks(CAMERA, tracks, start, opts, max_px=8.0, rounds=3)
    key = {(int(f), round(u, 6), round(v, 6)) for f, (u, v) in zip(kept.frame, kept.uv, strict=True)}
    was_kept = np.array([(int(f), round(u, 6), round(v, 6)) in key
                         for f, (u, v) in zip(tracks.frame, tracks.uv, strict=True)])  # fmt: skip
    assert not np.any(was_kept[false])
    assert np.mean(was_kept[~false]) >= 0.95
    assert np.all(np.bincount(kept.track) >= 3)


def test_consistent_tracks_come_back_whole() -> None:
    """Tracks without a false match and start poses at the truth: nothing is dropped."""
    tracks, _, false = _scene(4)
    keep = ~np.isin(tracks.track, tracks.track[false])
    clean = tracks.subset(keep)
    true = {f: Pose(R_SIDE, np.array([1.0 * f, 0.0, 0.0])) for f in range(8)}
    opts = ReconstructionOptions(min_track_length=3, min_angle_deg=1.0, min_depth_m=2.0)
    kept = consistent_tracks(CAMERA, clean, true, opts, max_px=8.0, rounds=3)
    assert kept is clean


def test_guided_matching_keeps_a_window_repeated_up_the_facade() -> None:
    """Two frames 1 m apart along a facade; every point of frame a has its true match in frame b
    and a twin with an almost equal descriptor 150 px higher (a window of the next floor). Among
    all keypoints the ratio test drops every such match; within the epipolar band of the poses
    (0.1° off) the twin is no rival and each true match is found."""
    rng = np.random.default_rng(5)
    pa, pb = Pose(R_SIDE, np.zeros(3)), Pose(R_SIDE, np.array([1.0, 0.0, 0.0]))
    X = np.column_stack([rng.uniform(-2, 3, 80), rng.uniform(10, 17, 80), rng.uniform(-0.5, 1.5, 80)])
    ua, _ = pa.project(CAMERA, X)
    ub, _ = pb.project(CAMERA, X)
    desc = rng.uniform(0, 100, (80, 128)).astype(np.float32)
    twin = desc + rng.normal(0, 1.0, desc.shape).astype(np.float32)
    kb = np.concatenate([ub, ub - np.array([0.0, 150.0])])
    db = np.concatenate([desc + rng.normal(0, 1.0, desc.shape).astype(np.float32), twin])
    opts = ImageTrackOptions(min_inliers=8)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    ia, _ = verified_matches(ua, desc, kb, db, CAMERA, matcher, opts)
    assert len(ia) == 0
    off = apply_delta(pb, np.array([0.0, np.radians(0.1), 0.0, 0.0, 0.0, 0.0]))
    band = epipolar_band(ua, kb, CAMERA, pa, off, 15.0)
    ia, ib = verified_matches(ua, desc, kb, db, CAMERA, matcher, opts, band)
    assert len(ia) >= 76 and np.all(ib == ia)

"""Bundle adjustment of a block (`workers.pipeline.orientation.bundle`) on synthetic observations with known
ground truth: points on the planes of a box corner seen by a drive, no images (no edges)."""

from __future__ import annotations

import doctest

import numpy as np

import workers.pipeline.orientation.bundle as bundle_module
from tests.unit.orientation_scenes import CAMERA, drive_poses, perturb
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import pose_delta
from workers.pipeline.orientation.bundle import BundleOptions, bundle_adjust, track_pairs
from workers.pipeline.orientation.tracks import Tracks

# four planes: a facade y = 0 (facing -y), the side wall x = 20 of its building (facing +x), the
# facade y = 4 of the set-back neighbour (facing -y) and the ground z = 0 in front of them. (The
# planes must not all pass through one point: a scaling of the whole block about that point would
# keep every point on its plane and every observation, leaving the scale to the GNSS baselines.)


def _points(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Points `(N, 3)` on the four planes and their normals `(N, 3)`."""
    a = np.c_[rng.uniform(0, 20, 150), np.zeros(150), rng.uniform(0.5, 9, 150)]  # facade
    b = np.c_[np.full(60, 20.0), rng.uniform(0, 4, 60), rng.uniform(0.5, 9, 60)]  # side wall
    c = np.c_[rng.uniform(20, 34, 80), np.full(80, 4.0), rng.uniform(0.5, 9, 80)]  # set-back facade
    d = np.c_[rng.uniform(0, 34, 120), rng.uniform(-10, -2, 120), np.zeros(120)]  # ground
    X = np.vstack([a, b, c, d])
    n = np.vstack([np.tile([0.0, -1.0, 0.0], (150, 1)), np.tile([1.0, 0.0, 0.0], (60, 1)),
                   np.tile([0.0, -1.0, 0.0], (80, 1)), np.tile([0.0, 0.0, 1.0], (120, 1))])
    return X, n


def _block(seed: int, noise_px: float = 0.1, n_frames: int = 10, off_plane_m: float = 0.0):
    """True poses of a drive past the corner, observations of the points they see (with pixel
    noise; the true points `off_plane_m` (σ) off their model planes, as recessed windows are),
    the points' start positions on their model planes (0.2 m off)."""
    rng = np.random.default_rng(seed)
    # driving west past the corner at 12 m, looking north and 30° ahead, level
    truth = drive_poses(np.array([31.0, -12.0, 2.0]), np.array([-1.0, 0.0, 0.0]), n_frames, step_m=0.9,
                        forward_deg=30.0, up_deg=0.0)
    X, nrm = _points(np.random.default_rng(99))
    X_true = X + nrm * rng.normal(0, off_plane_m, (len(X), 1)) if off_plane_m > 0 else X
    track, frame, uv = [], [], []
    for f, pose in enumerate(truth):
        p, z = pose.project(CAMERA, X_true)
        ok = (z > 0.5) & CAMERA.in_image(p, 5.0)
        idx = np.flatnonzero(ok)
        track.append(idx)
        frame.append(np.full(len(idx), f))
        uv.append(p[idx] + rng.normal(0, noise_px, (len(idx), 2)))
    track, frame, uv = np.concatenate(track), np.concatenate(frame), np.concatenate(uv)
    # a point seen once ties nothing (the tracker drops such tracks too)
    many = (np.bincount(track, minlength=len(X)) >= 2)[track]
    track, frame, uv = track[many], frame[many], uv[many]
    # start points: off by 0.2 m along their planes (as a ray cast from a wrong pose gives them)
    d = rng.normal(0, 0.2, X.shape)
    d -= np.sum(d * nrm, axis=1, keepdims=True) * nrm
    tracks = Tracks(track=track, frame=frame, uv=uv, point=X + d, normal=nrm)
    return truth, tracks, X_true


def _info(sigma_deg: float, sigma_m: float) -> np.ndarray:
    return np.diag([np.radians(sigma_deg) ** -2] * 3 + [sigma_m**-2] * 3)


def _priors(truth: list[Pose], seed: int, common: tuple[float, float], white: tuple[float, float]) -> dict:
    """Priors: the truth with a common error (m, deg) and per-frame white noise (m, deg)."""
    rng = np.random.default_rng(seed)
    c_m = rng.normal(0, common[0], 3)
    c_deg = rng.normal(0, common[1], 3)
    return {f: perturb(T, c_m + rng.normal(0, white[0], 3), c_deg + rng.normal(0, white[1], 3))
            for f, T in enumerate(truth)}


def _errors(poses: dict, truth: list[Pose]) -> tuple[float, float]:
    """Largest position (m) and rotation (deg) error over the frames."""
    d = np.array([pose_delta(truth[f], poses[f]) for f in poses])
    pos = float(np.max(np.linalg.norm(d[:, 3:], axis=1)))
    return pos, float(np.degrees(np.max(np.linalg.norm(d[:, :3], axis=1))))


def _adjust(truth, tracks, prior, options: BundleOptions = BundleOptions(), common=_info(2.0, 1.0)):
    frames = list(range(len(truth)))
    return bundle_adjust(CAMERA, frames, {}, prior, prior, dict.fromkeys(frames, _info(0.3, 0.3)), common,
                         tracks, None, None, options)  # type: ignore[arg-type]


def test_doctests_and_pairs() -> None:
    assert doctest.testmod(bundle_module).failed == 0
    i, j = track_pairs(np.array([2, 0, 2, 1, 2]), 3)
    pairs = set(zip(i.tolist(), j.tolist(), strict=True))
    assert pairs == {(a, b) for a in (0, 2, 4) for b in (0, 2, 4)} | {(1, 1), (3, 3)}


def test_block_with_common_and_per_frame_errors_converges_to_the_truth() -> None:
    truth, tracks, X = _block(1)
    prior = _priors(truth, 2, common=(0.8, 1.0), white=(0.2, 0.2))
    before = _errors(prior, truth)
    res = _adjust(truth, tracks, prior)
    pos, rot = _errors(res.poses, truth)
    assert before[0] > 0.5 and before[1] > 0.5
    # the geometry (planes of σ 5 cm, weak priors) fixes the block to a centimetre and a tenth of
    # a degree here, and each frame's error is within 3 σ of its predicted covariance
    assert pos < 0.03 and rot < 0.1, (pos, rot)
    for f, pose in res.poses.items():
        z = pose_delta(truth[f], pose) / np.sqrt(np.diag(res.covariance[f]))
        assert np.all(np.abs(z) < 3.0), (f, z)
    assert res.sigma0 < 1.5  # the observations' σ (0.1 px noise against tie_sigma 0.15 px) fits
    # the points seen end at their true places
    seen = np.unique(tracks.track)
    err = np.linalg.norm(res.points[seen] - X[seen], axis=1)
    assert np.median(err) < 0.01 and np.percentile(err, 90) < 0.03
    assert all(res.ties[f] > 20 for f in res.ties)


def test_gross_tie_errors_are_dropped_and_do_not_bias_the_block() -> None:
    truth, tracks, _ = _block(3)
    rng = np.random.default_rng(4)
    bad = rng.choice(len(tracks.uv), size=len(tracks.uv) // 20, replace=False)
    uv = tracks.uv.copy()
    uv[bad] += rng.uniform(5, 20, (len(bad), 2)) * rng.choice([-1, 1], (len(bad), 2))
    tracks = Tracks(tracks.track, tracks.frame, uv, tracks.point, tracks.normal)
    prior = _priors(truth, 5, common=(0.5, 0.5), white=(0.2, 0.2))
    res = _adjust(truth, tracks, prior)
    pos, rot = _errors(res.poses, truth)
    assert pos < 0.03 and rot < 0.1, (pos, rot)
    assert not res.inlier[bad].any()
    good = np.setdiff1d(np.arange(len(uv)), bad)
    assert res.inlier[good].mean() > 0.99


def test_covariance_matches_the_scatter_of_repeated_adjustments() -> None:
    """Twelve draws of the same block with errors as the adjustment assumes them (tie noise
    0.15 px, points 5 cm off their model planes, prior errors of the assumed σ: common 1 m and 2°,
    per frame 0.3 m and 0.3°): the predicted standard deviations of the poses agree with the
    observed scatter within a factor of two."""
    errs, sds = [], []
    for k in range(12):
        truth, tracks, _ = _block(100 + k, noise_px=0.15, off_plane_m=0.05)
        prior = _priors(truth, 200 + k, common=(1.0 / np.sqrt(3), 2.0 / np.sqrt(3)), white=(0.3, 0.3))
        res = _adjust(truth, tracks, prior)
        errs.append(np.array([pose_delta(truth[f], res.poses[f]) for f in res.poses]))
        sds.append(np.array([np.sqrt(np.diag(res.covariance[f])) for f in res.poses]))
    scatter = np.std(np.array(errs), axis=0)  # (frames, 6) over the draws
    predicted = np.mean(np.array(sds), axis=0)
    ratio = scatter / predicted
    assert 0.5 < np.median(ratio) < 2.0, np.median(ratio)


def test_what_one_facade_cannot_fix_stays_with_the_prior_and_the_covariance_says_so() -> None:
    """A block seen against one facade only: its height is fixed by no plane, so a common height
    error of the priors stays and the covariance says so (σ of the size of the common prior),
    while the distance to the facade, which the plane fixes, stays within its predicted σ."""
    truth, tracks, _ = _block(7)
    facade = tracks.normal[:, 1] < -0.5
    keep = facade[tracks.track]
    sub = Tracks(tracks.track[keep], tracks.frame[keep], tracks.uv[keep], tracks.point, tracks.normal)
    shift = {f: Pose(T.R_world_from_cam, T.center + np.array([0.0, 0.0, 0.5])) for f, T in enumerate(truth)}
    res = _adjust(truth, sub, shift)
    assert np.sqrt(res.covariance[5][5, 5]) > 0.3
    assert abs(res.poses[5].center[2] - truth[5].center[2]) > 0.3
    for f, pose in res.poses.items():
        dy = pose.center[1] - truth[f].center[1]
        assert abs(dy) < 3.0 * np.sqrt(res.covariance[f][4, 4]) and abs(dy) < 0.1


def test_priors_with_a_common_error_hold_the_block_unless_the_error_is_modelled() -> None:
    """The same block and priors (a common error of 0.5 m and 0.5°, per-frame noise of 0.1 m):
    as independent per-frame observations the priors pull the block toward their common error;
    with a common error of the block in the model they do not."""
    truth, tracks, _ = _block(9)
    prior = _priors(truth, 10, common=(0.5, 0.5), white=(0.1, 0.1))
    frames = list(range(len(truth)))
    white = dict.fromkeys(frames, _info(0.3, 0.3))
    independent = bundle_adjust(CAMERA, frames, {}, prior, prior, white, None, tracks, None, None,  # type: ignore[arg-type]
                                BundleOptions())
    common = _adjust(truth, tracks, prior)
    pos_i = _errors(independent.poses, truth)[0]
    pos_c, rot_c = _errors(common.poses, truth)
    assert pos_c < 0.03 and rot_c < 0.1
    assert pos_i > 1.5 * pos_c
    assert all(c.shape == (6, 6) for c in independent.covariance.values())


def test_the_model_planes_hold_when_the_start_points_are_off_them() -> None:
    """Track points handed on from an earlier adjustment lie off their model planes by the
    facades' detail; the plane observations use the model planes (`Tracks.offset`), not planes
    through the start points: 0.3 m off along the normals, the block still ends on the truth."""
    truth, tracks, _ = _block(13)
    off = tracks.with_points(tracks.point + 0.3 * tracks.normal)
    assert np.allclose(off.offset, np.sum(tracks.normal * tracks.point, axis=1))
    prior = _priors(truth, 14, common=(0.3, 0.3), white=(0.1, 0.1))
    pos, rot = _errors(_adjust(truth, off, prior).poses, truth)
    assert pos < 0.03 and rot < 0.1, (pos, rot)
    # planes through the start points instead: the block follows them off by decimetres
    wrong = Tracks(off.track, off.frame, off.uv, off.point, off.normal)
    assert _errors(_adjust(truth, wrong, prior).poses, truth)[0] > 0.1


def test_observations_of_points_behind_a_camera_are_left_out() -> None:
    """A frame turned away from the scene with (mismatched) observations of points behind it: the
    projection's Jacobian there is huge and finite (depth clamped), and would swamp the system."""
    truth, tracks, _ = _block(15)
    n = len(truth)
    away = Pose(truth[0].R_world_from_cam @ np.diag([-1.0, 1.0, -1.0]), truth[0].center)  # looking back
    rng = np.random.default_rng(16)
    pick = rng.choice(tracks.n_tracks, 30, replace=False)
    t2 = Tracks(np.concatenate([tracks.track, pick]), np.concatenate([tracks.frame, np.full(30, n)]),
                np.concatenate([tracks.uv, rng.uniform(0, 400, (30, 2))]), tracks.point, tracks.normal)
    all_truth = [*truth, away]
    prior = _priors(all_truth, 17, common=(0.3, 0.3), white=(0.1, 0.1))
    res = _adjust(all_truth, t2, prior)
    pos, rot = _errors({f: res.poses[f] for f in range(n)}, truth)
    assert pos < 0.03 and rot < 0.1, (pos, rot)
    assert res.converged and res.ties[n] == 0


def test_far_points_seen_from_nearly_one_direction_neither_break_nor_hold_the_block() -> None:
    """Points kilometres away the model lacks (off every plane, so without plane weight), each seen
    by two frames 0.9 m apart: their depth is all but unobserved. The points' step damping
    (`point_step_sigma_m`) keeps their 3 × 3 systems invertible without holding them (σ 10 m
    held them: 0.27 m / 0.64° off here), and a tie of a single inlier observation is left out."""
    truth, tracks, _ = _block(1)
    rng = np.random.default_rng(7)
    t, f, uv, pts = [], [], [], []
    for k in range(len(truth) - 1):
        for _ in range(6):
            ray = truth[k].R_world_from_cam @ np.r_[rng.uniform(-0.3, 0.3, 2), 1.0]
            X = truth[k].center + ray / np.linalg.norm(ray) * rng.uniform(3000, 6000)
            obs = [truth[g].project(CAMERA, X[None])[0][0] for g in (k, k + 1)]
            if all(CAMERA.in_image(o[None])[0] for o in obs):
                t += [tracks.n_tracks + len(pts)] * 2
                f += [k, k + 1]
                uv += obs
                pts.append(X + rng.normal(0, 1.0, 3))
    assert len(pts) > 20
    normals = np.tile([0.0, -1.0, 0.0], (len(pts), 1))
    far = Tracks(np.r_[tracks.track, t], np.r_[tracks.frame, f], np.vstack([tracks.uv, uv]),
                 np.vstack([tracks.point, pts]), np.vstack([tracks.normal, normals]))
    prior = _priors(truth, 2, common=(0.8, 1.0), white=(0.2, 0.2))
    res = _adjust(truth, far, prior)
    pos, rot = _errors(res.poses, truth)
    assert res.converged and pos < 0.03 and rot < 0.1, (pos, rot)
    used = bundle_module._tied(np.array([True, True, False, True]), np.array([0, 1, 1, 2]), 3, 2)
    assert used.tolist() == [False, False, False, False]


def test_a_step_is_measured_in_each_frames_own_sigma() -> None:
    """`_largest_sigma_step`: a frame stepping one σ of its own block (the other frames and the
    common correction held) measures 1, whatever its neighbours' blocks and the coupling."""
    rng = np.random.default_rng(3)
    n = 4
    A = rng.normal(size=(6 * n + 6, 6 * n + 6))
    S = A @ A.T + 6 * n * np.eye(6 * n + 6)
    steps = np.zeros((n, 6))
    D = S[12:18, 12:18]  # frame 2's block
    w, V = np.linalg.eigh(D)
    steps[2] = V[:, 0] / np.sqrt(w[0])  # one σ along its weakest direction
    w1, V1 = np.linalg.eigh(S[6:12, 6:12])
    steps[1] = 0.5 * V1[:, -1] / np.sqrt(w1[-1])  # half a σ of frame 1, along its strongest direction
    assert abs(bundle_module._largest_sigma_step(S, steps) - 1.0) < 1e-9
    steps[2] *= 0.1
    assert abs(bundle_module._largest_sigma_step(S, steps) - 0.5) < 1e-9

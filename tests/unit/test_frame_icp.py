"""Per-frame ICP with relative-orientation ties (`reconstruction.frame_icp`): known truth."""

from __future__ import annotations

import numpy as np

from workers.pipeline.geometry.pose import Pose
from workers.pipeline.reconstruction.dense_stereo import _relative
from workers.pipeline.reconstruction.frame_icp import FrameIcpOptions, _exp, _log, register_frames

ORIGIN = np.array([691000.0, 5334000.0, 35.0])  # UTM-sized coordinates
#: the tests' relative orientations are exact: tied as tightly as the images would at best
EXACT = FrameIcpOptions(
    distances_m=(1.0, 0.5, 0.25, 0.1), relative_rotation_sigma_deg=0.05, relative_position_sigma_m=0.03
)
#: camera looking north (+y): x right = east, y down, z forward = north
R_NORTH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _street(rng: np.random.Generator, n: int) -> np.ndarray:
    """World points `(n, 3)`: a wall y = 0 (x 0…30, z 0…10), a side wall x = 0 (the corner,
    y −8…0), the street z = 0 (y −8…0) and a bay 0.6 m out of the wall (x 12…16, z 3…7)."""
    u = rng.uniform(0, 1, (n, 2))
    k = rng.integers(0, 4, n)
    P = np.zeros((n, 3))
    m = [k == i for i in range(4)]
    P[m[0]] = np.column_stack([u[m[0], 0] * 30, np.zeros(m[0].sum()), u[m[0], 1] * 10])
    P[m[1]] = np.column_stack([np.zeros(m[1].sum()), -u[m[1], 0] * 8, u[m[1], 1] * 10])
    P[m[2]] = np.column_stack([u[m[2], 0] * 30, -u[m[2], 1] * 8, np.zeros(m[2].sum())])
    P[m[3]] = np.column_stack([12 + 4 * u[m[3], 0], np.full(m[3].sum(), -0.6), 3 + 4 * u[m[3], 1]])
    return P + ORIGIN


def _block(seed: int, noise_m: float = 0.03) -> tuple:
    """True poses of 12 frames along the street, every frame's visible points in its camera
    frame (noise `noise_m`), the exact relative orientations of consecutive frames, the
    reference cloud, and priors: a common 0.4 m offset, per-frame 0.2 m / 0.15° noise."""
    rng = np.random.default_rng(seed)
    target = _street(rng, 120_000)
    true, pts = [], []
    for i in range(12):
        c = ORIGIN + np.array([2.0 + 2.0 * i, -8.0, 1.5])
        R = _exp(np.radians(rng.normal(0, 1.0, 3))) @ R_NORTH
        p = Pose(R, c)
        true.append(p)
        X = _street(rng, 20_000)
        X = X[np.abs(X[:, 0] - c[0]) < 7.0]
        pts.append(p.cam_from_world(X) + noise_m * rng.standard_normal(X.shape))
    rel = [(a, a + 1, *_relative(true[a], true[a + 1])) for a in range(11)]
    bias = np.array([0.3, -0.2, 0.2])
    priors = [
        Pose(_exp(np.radians(rng.normal(0, 0.15, 3))) @ p.R_world_from_cam,
             p.center + bias + rng.normal(0, 0.2, 3))
        for p in true
    ]  # fmt: skip
    return true, pts, rel, target, priors


def _errors(poses: list[Pose] | tuple[Pose, ...], true: list[Pose]) -> tuple[np.ndarray, np.ndarray]:
    dp = np.array([np.linalg.norm(p.center - t.center) for p, t in zip(poses, true, strict=True)])
    dr = np.array(
        [np.degrees(np.linalg.norm(_log(t.R_world_from_cam.T @ p.R_world_from_cam)))
         for p, t in zip(poses, true, strict=True)]
    )  # fmt: skip
    return dp, dr


def test_every_frame_is_corrected_with_the_chain() -> None:
    true, pts, rel, target, priors = _block(3)
    dp0, dr0 = _errors(priors, true)
    assert dp0.mean() > 0.3 and np.median(dr0) > 0.1  # the priors' errors: a few decimetres
    res = register_frames(pts, priors, rel, target, EXACT)
    dp, dr = _errors(res.poses, true)
    assert np.max(dp) < 0.05, dp  # every frame, also those seeing one wall only (held by the chain)
    assert np.median(dp) < 0.03
    assert np.max(dr) < 0.05, dr  # priors: 0.15° per angle
    assert np.all(res.points_used > 100)


def test_without_the_chain_a_frame_seeing_one_wall_keeps_its_sliding_error() -> None:
    true, pts, _, target, priors = _block(3)
    res = register_frames(pts, priors, [], target, EXACT)
    dp, _ = _errors(res.poses, true)
    assert dp[0] < 0.05  # the corner frame: fully observed
    assert np.max(dp[4:]) > 0.1  # frames seeing the wall and the street: x is unobserved


def test_block_registration_runs_per_frame_after_the_rigid_icp() -> None:
    from workers.pipeline.reconstruction.dense_stereo import DenseCloud
    from workers.pipeline.reconstruction.rgb_method import RgbRegistrationOptions, register_clouds_of_blocks

    true, pts, rel, target, priors = _block(4)
    P = np.concatenate([p.world_from_cam(x) for p, x in zip(priors, pts, strict=True)])
    F = np.concatenate([np.full(len(x), a, np.int32) for a, x in enumerate(pts)])
    pairs = tuple((a, b) for a, b, _, _ in rel)
    tir = DenseCloud(P, F, pairs, len(rel), (), tuple((R, t, True) for _, _, R, t in rel))
    rgb = DenseCloud(target, np.zeros(len(target), np.int32), (), 0, ())
    opts = RgbRegistrationOptions(per_frame=True, frames=EXACT)
    reg = register_clouds_of_blocks(tir, rgb, priors, opts)
    assert reg.accepted and reg.frame_icp is not None, reg.frame_reason
    dp, dr = _errors(reg.poses, true)
    assert np.median(dp) < 0.03 and np.max(dp) < 0.06, dp
    assert np.max(dr) < 0.05, dr
    f = reg.figures()
    # every TIR point counted: after the per-frame step the cloud lies on the reference
    assert f["mean_distance_after_m"] < 0.05 < 0.1 < f["rigid_mean_distance_after_m"]
    rigid = register_clouds_of_blocks(tir, rgb, priors, RgbRegistrationOptions(per_frame=False))
    dp_rigid, _ = _errors(rigid.poses, true)
    assert np.median(dp_rigid) > 0.1  # one transform per block keeps the per-frame noise


def test_orient_with_rgb_keeps_the_input_poses_when_nothing_matches() -> None:
    from workers.pipeline.geometry.camera import Camera
    from workers.pipeline.reconstruction.rgb_method import orient_with_rgb

    cam = Camera(64, 48, 60.0, 60.0, 31.5, 23.5)
    poses = [Pose(R_NORTH, ORIGIN + np.array([1.5 * i, -8.0, 1.5])) for i in range(6)]
    blank_tir = np.full((48, 64), 280.0, np.float32)
    blank_rgb = np.zeros((48, 64, 3), np.uint8)
    reg = orient_with_rgb(lambda i: blank_tir, cam, poses, lambda j: blank_rgb, cam, poses)
    assert not reg.accepted and "too few dense points" in reg.reason
    assert all(p is q for p, q in zip(reg.poses, poses, strict=True))

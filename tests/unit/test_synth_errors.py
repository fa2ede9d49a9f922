"""GNSS/INS error model: exact without errors, statistics matching the parameters with them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from workers.pipeline.geometry.georef import camera_pose, camera_poses, prior_poses
from workers.pipeline.synth import (
    ErrorOptions,
    PathTrajectory,
    SensorOptions,
    SynthOptions,
    procedural_block,
    simulate_ins,
    synthesize,
)
from workers.pipeline.synth.render import default_camera
from workers.pipeline.synth.trajectory import camera_to_body

SMALL = default_camera(64, 48)
OFF = ErrorOptions(
    position_bias_h_m=0, position_bias_v_m=0, position_random_walk_m=0, position_white_m=0,
    attitude_white_deg=0, vibration_deg=0, boresight_deg=(0, 0, 0), time_delay_s=0,
)  # fmt: skip


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


@pytest.fixture(scope="module")
def loop_traj():
    a = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
    loop = np.stack([500.0 + 60 * np.cos(-a), 800.0 + 40 * np.sin(-a)], axis=-1)
    return PathTrajectory(loop, 102.0, 8.0, t0=50.0, sway_deg=0.3, seed=1)


@pytest.mark.parametrize("platform", ["drive", "flight"])
def test_errors_off_manifest_reproduces_true_poses(platform):
    res = synthesize(
        procedural_block(6, seed=2),
        SynthOptions(platform=platform, n_frames=15, seed=2, buildings=2, camera=SMALL,
                     errors=ErrorOptions(enabled=False)),
    )  # fmt: skip
    m = res.manifest
    priors = prior_poses(m, "EPSG:25832")
    for f, true, prior in zip(m.frames, res.truth.poses, priors, strict=True):
        p = camera_pose(f.position, f.attitude_deg, m.mounting)
        assert np.abs(p.R_world_from_cam - true.R_world_from_cam).max() < 1e-9
        assert np.abs(p.center - true.center).max() < 1e-9
        assert np.abs(prior.center - true.center).max() < 1e-9
    assert res.truth.time_delay_s == 0.0


def test_errors_on_statistics(loop_traj):
    o = ErrorOptions()
    times = 50.0 + 0.1 * np.arange(3000)  # 300 s
    M = camera_to_body(25, 12)
    sim = simulate_ins(loop_traj.state, times, M, "drive", o, seed=7)
    e = sim.position_error
    # bias: 1.5 m horizontal, 2 m vertical (+ a slow random walk of 0.02 m/√s)
    assert abs(np.hypot(*e[:, :2].mean(axis=0)) - 1.5) < 0.3
    assert abs(abs(e[:, 2].mean()) - 2.0) < 0.3
    # white noise 0.2 m per axis: differences of consecutive frames have std √2 · 0.2
    sd = np.std(np.diff(e, axis=0), axis=0) / np.sqrt(2)
    assert np.all(np.abs(sd - 0.2) < 0.02)
    # random walk 0.02 m/√s: consecutive 10-s means differ by σ²·10·2/3 (+ the white noise's share)
    means = e.reshape(30, 100, 3).mean(axis=1)
    expect = np.sqrt(0.02**2 * 10 * 2 / 3 + 2 * 0.2**2 / 100)
    assert 0.75 * expect < np.std(np.diff(means, axis=0)) < 1.3 * expect
    # attitude white noise 0.05° per angle
    assert np.all(np.abs(np.std(sim.attitude_error, axis=0) - 0.05) < 0.006)
    # vibration: true minus smooth attitude at exposure, RMS = 0.2/√2 per angle
    _, A_smooth = loop_traj.state(times - o.time_delay_s)
    vib = (sim.true_attitudes - A_smooth + 180.0) % 360.0 - 180.0
    assert np.all(np.abs(np.sqrt(np.mean(vib**2, axis=0)) - 0.2 / np.sqrt(2)) < 0.02)
    # mounting: manifest says nominal, no boresight, no lever arm; the truth differs
    assert np.allclose(sim.manifest_mounting.boresight_deg, 0)
    assert np.allclose(sim.manifest_mounting.lever_arm_m, 0)
    assert np.allclose(sim.true_mounting.boresight_deg, (1.0, -2.0, 2.5))
    # imu.csv at 100 Hz, covering every exposure
    assert np.allclose(np.diff(sim.imu.time), 0.01)
    assert sim.imu.time[0] <= times[0] - o.time_delay_s and sim.imu.time[-1] >= times[-1]


def test_time_delay_and_boresight_define_the_true_pose(loop_traj):
    times = 50.0 + 0.1 * np.arange(50)
    M = camera_to_body(25, 12)
    o = replace(OFF, time_delay_s=0.02, boresight_deg=(0.0, 8.0, 0.0), lever_arm_m=(1.0, 0.5, -0.8))
    sim = simulate_ins(loop_traj.state, times, M, "flight", o, seed=3)
    # true pose = platform state at t − δ with the true mounting
    P, A = loop_traj.state(times - 0.02)
    expect = camera_poses(P, A, sim.true_mounting)
    for a, b in zip(sim.poses, expect, strict=True):
        assert np.abs(a.center - b.center).max() < 1e-9
        assert rotation_angle_deg(a.R_world_from_cam, b.R_world_from_cam) < 1e-7
    # the manifest's prior (no boresight, no lever arm, no delay) is 8° and ~1.4 m off + 0.16 m of motion
    for f, true in zip([sim.frame_positions[i] for i in range(3)], sim.poses[:3], strict=True):
        assert np.linalg.norm(f - true.center) > 1.0
    prior = camera_poses(sim.frame_positions, sim.frame_attitudes, sim.manifest_mounting)
    ang = [
        rotation_angle_deg(p.R_world_from_cam, t.R_world_from_cam)
        for p, t in zip(prior, sim.poses, strict=True)
    ]
    assert np.allclose(ang, 8.0, atol=0.3)


def test_recorded_frames_are_imu_samples(loop_traj):
    times = 50.0 + 0.1 * np.arange(40)
    sim = simulate_ins(loop_traj.state, times, camera_to_body(25, 12), "drive", ErrorOptions(), seed=4)
    k = np.searchsorted(sim.imu.time, times - 1e-9)
    assert np.allclose(sim.imu.time[k], times)
    assert np.allclose(sim.imu.position[k], sim.frame_positions)
    assert np.allclose(sim.imu.attitude_deg[k], sim.frame_attitudes)


def test_sensor_options_reach_the_truth():
    res = synthesize(
        procedural_block(3, seed=1),
        SynthOptions(n_frames=2, seed=1, buildings=1, camera=SMALL, sensor=SensorOptions(netd_k=0.1)),
    )
    assert res.truth.sensor.netd_k == 0.1
    assert res.truth.errors["time_delay_s"] == 0.02


def test_calibrated_priors_recover_the_truth():
    """With the true mounting and δ, `georef.prior_poses` (SLERP over imu.csv at t − δ) gives the
    true poses: the package and the truth agree on the delay's sign and the mounting formula."""
    o = replace(OFF, time_delay_s=0.05, boresight_deg=(1.0, -2.0, 2.5), lever_arm_m=(0.4, 0.6, -1.2))
    res = synthesize(
        procedural_block(6, seed=5), SynthOptions(n_frames=20, seed=5, buildings=2, camera=SMALL, errors=o)
    )
    t = res.truth
    calibrated = prior_poses(
        res.manifest, "EPSG:25832", time_delay_s=t.time_delay_s, mounting=t.true_mounting
    )
    naive = prior_poses(res.manifest, "EPSG:25832")
    for c, n, true in zip(calibrated, naive, t.poses, strict=True):
        assert np.linalg.norm(c.center - true.center) < 0.005
        assert rotation_angle_deg(c.R_world_from_cam, true.R_world_from_cam) < 0.01
        assert rotation_angle_deg(n.R_world_from_cam, true.R_world_from_cam) > 2.0

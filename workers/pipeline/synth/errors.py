"""GNSS/INS error model: from a true trajectory to what the manifest records, and the true poses.

In: a true platform trajectory (`PathTrajectory.state(t)`: IMU reference point `(N, 3)` world
metres, attitude `[roll, pitch, heading]` `(N, 3)` degrees), frame time stamps `(F,)` seconds
(camera clock = INS clock + δ), the nominal mounting `M` (`camera_to_body`), the platform, a
seed and `ErrorOptions`. Out: `InsSimulation`: the recorded INS solution at the frames and at
`imu_rate_hz` (for `imu.csv`), the mounting the manifest states, the true mounting and delay,
and the true camera poses (`Pose`, world) of every frame.

Model (each term a parameter; `enabled=False` switches all of them off):
- recorded position = true + bias (a fixed vector: `position_bias_h_m` horizontally in a random
  direction, ±`position_bias_v_m` vertically) + random walk (`position_random_walk_m` m/√s per
  axis) + white noise (`position_white_m` per axis);
- recorded attitude = true + white noise (`attitude_white_deg` per angle);
- platform vibration (`vibration_deg` amplitude at ~`vibration_hz`, a narrow band of three
  sinusoids per angle) moves the camera but is not in the INS solution;
- true mounting: boresight `boresight_deg` (default a few degrees for drives, 8° pitch for
  flights) and lever arm `lever_arm_m`; the manifest states the nominal `M` with zero boresight
  and zero lever arm (with errors off: the true lever arm, and no boresight);
- camera-to-INS delay δ = `time_delay_s`: a frame stamped `t` was exposed at `t − δ`, its true
  pose is the (true, vibrating) platform state at `t − δ` with the true mounting.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from workers.pipeline.geometry.georef import camera_poses
from workers.pipeline.geometry.manifest import Accuracy, ImuSamples, Mounting
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.synth.common import SynthError, rng_for

#: Platform defaults of the true mounting errors: boresight (deg, about body x, y, z), lever arm (m).
PLATFORM_DEFAULTS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "drive": ((1.0, -2.0, 2.5), (0.4, 0.6, -1.2)),
    "flight": ((0.0, 8.0, 0.0), (1.2, 0.5, 0.8)),
}

StateFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class ErrorOptions:
    """GNSS/INS and mounting error terms (see the module docstring). Metres, degrees, seconds."""

    enabled: bool = True
    position_bias_h_m: float = 1.5
    position_bias_v_m: float = 2.0
    position_random_walk_m: float = 0.02  # per axis, m/√s
    position_white_m: float = 0.2  # per axis, standard deviation
    attitude_white_deg: float = 0.05  # per angle, standard deviation
    vibration_deg: float = 0.2  # amplitude per angle
    vibration_hz: float = 10.0
    boresight_deg: tuple[float, float, float] | None = None  # true misalignment; None: platform default
    lever_arm_m: tuple[float, float, float] | None = None  # true lever arm; None: platform default
    time_delay_s: float = 0.02
    imu_rate_hz: float = 100.0


@dataclass(frozen=True, eq=False)
class InsSimulation:
    """What the error model produced (see the module docstring).

    Attributes:
        frame_times: `(F,)` frame stamps, seconds.
        frame_positions / frame_attitudes: `(F, 3)` recorded INS solution at the stamps.
        imu: recorded INS solution at `imu_rate_hz` over the frames (±1 s).
        true_positions / true_attitudes: `(F, 3)` true platform state at the exposure times
            (vibration included).
        position_error / attitude_error: `(F, 3)` recorded minus true smooth state at the stamps
            (metres east/north/up; degrees roll/pitch/heading, wrapped to ±180).
        poses: true camera pose of every frame.
        true_mounting: boresight and lever arm the platform really has.
        manifest_mounting: what the manifest states.
        time_delay_s: true camera-to-INS delay δ.
        accuracy: a-priori standard deviations for the manifest.
    """

    frame_times: np.ndarray
    frame_positions: np.ndarray
    frame_attitudes: np.ndarray
    imu: ImuSamples
    true_positions: np.ndarray
    true_attitudes: np.ndarray
    position_error: np.ndarray
    attitude_error: np.ndarray
    poses: tuple[Pose, ...]
    true_mounting: Mounting
    manifest_mounting: Mounting
    time_delay_s: float
    accuracy: Accuracy


def _vibration(times: np.ndarray, options: ErrorOptions, seed: int) -> np.ndarray:
    """Attitude vibration `(N, 3)` degrees: per angle three sinusoids at `vibration_hz · (1 ± 8%)`
    with random phases; RMS = amplitude/√2 like one sinusoid of that amplitude."""
    if options.vibration_deg <= 0:
        return np.zeros((len(times), 3))
    rng = rng_for(seed, "vibration")
    f = options.vibration_hz * rng.uniform(0.92, 1.08, size=(3, 3))
    ph = rng.uniform(0, 2 * np.pi, size=(3, 3))
    a = options.vibration_deg / np.sqrt(3.0)
    arg = 2 * np.pi * times[:, None, None] * f[None] + ph[None]
    return a * np.sin(arg).sum(axis=2)


def simulate_ins(
    state: StateFn,
    frame_times: np.ndarray,
    camera_to_body: np.ndarray,
    platform: str,
    options: ErrorOptions,
    seed: int,
) -> InsSimulation:
    """Run the error model (see the module docstring) for frames stamped `frame_times` `(F,)`."""
    o = options
    t_f = np.asarray(frame_times, dtype=np.float64).reshape(-1)
    if len(t_f) == 0 or np.any(np.diff(t_f) <= 0):
        raise SynthError("frame times must be non-empty and strictly increasing")
    if o.imu_rate_hz <= 0:
        raise SynthError(f"imu_rate_hz must be positive, got {o.imu_rate_hz}")
    bore_d, lever_d = PLATFORM_DEFAULTS.get(platform, PLATFORM_DEFAULTS["drive"])
    M = np.asarray(camera_to_body, dtype=np.float64).reshape(3, 3)
    lever = np.asarray(o.lever_arm_m if o.lever_arm_m is not None else lever_d, dtype=np.float64)
    if o.enabled:
        bore = np.asarray(o.boresight_deg if o.boresight_deg is not None else bore_d, dtype=np.float64)
        delay = float(o.time_delay_s)
        manifest_mounting = Mounting(M.copy(), np.zeros(3), np.zeros(3))
    else:
        bore, delay = np.zeros(3), 0.0
        manifest_mounting = Mounting(M.copy(), np.zeros(3), lever.copy())
    true_mounting = Mounting(M.copy(), bore, lever)

    # the INS clock: a regular grid covering the frames (and their exposures) by a second
    dt = 1.0 / o.imu_rate_hz
    n_imu = int(np.ceil((t_f[-1] - t_f[0] + 2.0) / dt)) + 1
    t_imu = t_f[0] - 1.0 + dt * np.arange(n_imu)
    rng = rng_for(seed, "ins")
    on = o.enabled
    direction = rng.uniform(0, 2 * np.pi)
    bias = np.array(
        [
            o.position_bias_h_m * np.cos(direction),
            o.position_bias_h_m * np.sin(direction),
            o.position_bias_v_m * (1.0 if rng.uniform() < 0.5 else -1.0),
        ]
    )
    steps = rng.standard_normal((n_imu, 3)) * o.position_random_walk_m * np.sqrt(dt)
    steps[0] = 0.0
    walk = np.cumsum(steps, axis=0)
    white_p = rng.standard_normal((n_imu, 3)) * o.position_white_m
    white_a = rng.standard_normal((n_imu, 3)) * o.attitude_white_deg
    if not on:
        bias, walk, white_p, white_a = np.zeros(3), walk * 0, white_p * 0, white_a * 0

    # frame stamps on the grid reuse its white noise; others get their own draws
    k = np.clip(np.rint((t_f - t_imu[0]) / dt).astype(np.int64), 0, n_imu - 1)
    on_grid = np.abs(t_imu[k] - t_f) < 1e-6
    fresh_p = rng.standard_normal((len(t_f), 3)) * o.position_white_m * on
    fresh_a = rng.standard_normal((len(t_f), 3)) * o.attitude_white_deg * on
    wp_f = np.where(on_grid[:, None], white_p[k], fresh_p)
    wa_f = np.where(on_grid[:, None], white_a[k], fresh_a)
    walk_f = np.stack([np.interp(t_f, t_imu, walk[:, j]) for j in range(3)], axis=-1)

    P_imu, A_imu = state(t_imu)
    P_f, A_f = state(t_f)
    pos_err = bias + walk_f + wp_f
    rec_P_f = P_f + pos_err
    rec_A_f = _wrap_attitude(A_f + wa_f)
    imu = ImuSamples(
        time=t_imu,
        position=P_imu + bias + walk + white_p,
        attitude_deg=_wrap_attitude(A_imu + white_a),
    )

    # the truth: platform state at exposure (vibrating), true mounting
    t_exp = t_f - delay
    P_true, A_true = state(t_exp)
    if on:
        A_true = A_true + _vibration(t_exp, o, seed)
    A_true = _wrap_attitude(A_true)
    poses = tuple(camera_poses(P_true, A_true, true_mounting))

    att_err = rec_A_f - A_f
    att_err = (att_err + 180.0) % 360.0 - 180.0
    sd_p = np.hypot([o.position_bias_h_m, o.position_bias_h_m, o.position_bias_v_m], o.position_white_m)
    sd_a = np.full(3, np.hypot(o.attitude_white_deg, o.vibration_deg / np.sqrt(2.0)))
    accuracy = Accuracy(np.maximum(sd_p, 0.01) if on else np.full(3, 0.01), sd_a if on else np.full(3, 0.01))
    return InsSimulation(
        frame_times=t_f,
        frame_positions=rec_P_f,
        frame_attitudes=rec_A_f,
        imu=imu,
        true_positions=P_true,
        true_attitudes=A_true,
        position_error=pos_err,
        attitude_error=att_err,
        poses=poses,
        true_mounting=true_mounting,
        manifest_mounting=manifest_mounting,
        time_delay_s=delay,
        accuracy=accuracy,
    )


def _wrap_attitude(att: np.ndarray) -> np.ndarray:
    """Attitudes `(N, 3)` degrees with the heading wrapped to [0, 360)."""
    out = np.array(att, dtype=np.float64)
    out[:, 2] = np.mod(out[:, 2], 360.0)
    out[:, 2] = np.where(out[:, 2] >= 360.0, 0.0, out[:, 2])
    return out

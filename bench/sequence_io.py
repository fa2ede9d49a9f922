"""Bench: sequence package I/O and georeferencing speed, SLERP accuracy. Prints JSON.

Writes a synthetic 640x512 package (200 frames, IMU at 100 Hz), opens it as a folder and as a
zip, loads every frame, computes prior poses with and without a time delay, and checks the
interpolated attitude against the analytic one of a constant yaw-rate turn across north.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

from db.sequence_package import open_package, write_package
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.georef import Trajectory, attitude_from_ned_from_body, prior_poses
from workers.pipeline.geometry.manifest import FrameRecord, ImuSamples, Mounting, Radiometry, SequenceManifest

N_FRAMES, W, H = 200, 640, 512


def manifest() -> SequenceManifest:
    t_imu = np.arange(0.0, N_FRAMES / 10 + 0.001, 0.01)  # 100 Hz over the whole drive
    heading = (350.0 + 1.5 * t_imu) % 360  # turns through north
    pos = np.column_stack([691000 + 8 * t_imu, 5334000 + 0.5 * t_imu**2, np.full_like(t_imu, 520.0)])
    att = np.column_stack([0.3 * np.sin(t_imu), -1.0 + 0.2 * np.cos(t_imu), heading])
    imu = ImuSamples(t_imu, pos, att)
    tf = np.arange(N_FRAMES) / 10 + 0.05
    idx = np.round(tf * 100).astype(int)
    frames = tuple(
        FrameRecord(i, f"frames/{i:06d}.png", float(t_imu[idx[i]]), pos[idx[i]], att[idx[i]])
        for i in range(N_FRAMES)
    )
    return SequenceManifest(
        platform="drive",
        crs="EPSG:25832",
        camera=Camera(W, H, 880.0, 880.0, 319.5, 255.5, k1=-0.12, k2=0.05),
        radiometry=Radiometry(),
        mounting=Mounting(
            np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]), np.zeros(3), np.array([1.0, 0, -0.5])
        ),
        frames=frames,
        imu=imu,
    )


def main() -> None:
    rng = np.random.default_rng(0)
    base = rng.integers(27000, 31000, (H, W)).astype(np.uint16)
    m = manifest()
    out: dict[str, float] = {}
    tmp = Path(tempfile.mkdtemp(prefix="citytherm-bench-"))
    try:
        t0 = time.perf_counter()
        write_package(tmp / "pkg", m, (np.roll(base, i, axis=1) for i in range(N_FRAMES)))
        out["write_frames_per_s"] = N_FRAMES / (time.perf_counter() - t0)
        with zipfile.ZipFile(tmp / "pkg.zip", "w", zipfile.ZIP_STORED) as zf:
            for f in sorted((tmp / "pkg").rglob("*")):
                zf.write(f, f.relative_to(tmp / "pkg").as_posix())
        t0 = time.perf_counter()
        with open_package(tmp / "pkg") as pkg:
            out["open_dir_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            for i in range(N_FRAMES):
                pkg.frames.load(i)
            out["load_frames_per_s"] = N_FRAMES / (time.perf_counter() - t0)
        t0 = time.perf_counter()
        with open_package(tmp / "pkg.zip") as pkg:
            out["open_zip_s"] = time.perf_counter() - t0
        out["package_mb"] = sum(f.stat().st_size for f in (tmp / "pkg").rglob("*")) / 1e6
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    t0 = time.perf_counter()
    prior_poses(m, "EPSG:25832")
    out["prior_poses_per_s"] = N_FRAMES / (time.perf_counter() - t0)
    t0 = time.perf_counter()
    prior_poses(m, "EPSG:25832", time_delay_s=0.0137)
    out["delayed_poses_per_s"] = N_FRAMES / (time.perf_counter() - t0)
    # SLERP between 100 Hz samples of a 1.5°/s turn through north: heading error at mid-points
    traj = Trajectory.from_imu(m.imu)
    tq = m.imu.time[:-1] + 0.005
    _, R = traj.at(tq)
    h = attitude_from_ned_from_body(R)[:, 2]
    dh = (h - (350.0 + 1.5 * tq) % 360 + 180) % 360 - 180
    out["slerp_heading_max_err_deg"] = float(np.abs(dh).max())
    print(json.dumps({k: float(f"{v:.4g}") for k, v in out.items()}, indent=1))


if __name__ == "__main__":
    main()

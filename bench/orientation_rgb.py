"""Method 3 bench: the TIR block registered onto an RGB block by ICP of dense clouds.

A synthetic drive (`citytherm synth` with its RGB camera: `SynthOptions(rgb=RgbOptions())`)
along real LoD2 geometry (the bundled Berlin model, `workers.pipeline.synth.BUNDLED_MODEL`) with
the default GNSS/INS error model on the TIR poses. The TIR priors are the package's poses with
the true mounting and delay (what an accepted calibration gives: method 3 corrects the GNSS/INS
errors, not the boresight), the RGB poses are the package's `rgb_camera` poses (a block adjusted
with ground control: 1 cm / 0.005° per frame). Prints JSON:

- `clouds`: points per cloud, stereo pairs, TIR pairs oriented from the images;
- `multiview`: the TIR frames' multi-view block (`multiview.multiview_block`: tracks, tie RMS,
  frames tied; off with `--no-multiview`: the pairs' two-view orientations from the priors);
- `distance`: mean / median TIR-RGB cloud distance (point to the RGB cloud's local plane, every
  TIR point of the dense cloud, none dropped for the figure) before, after the block's rigid ICP
  (`rigid_mean_distance_after_m`) and after the per-frame registration (`mean_distance_after_m`),
  and the mean over the overlap (distances < 1 m) (paper: 1.82 m -> 0.11 m; bar: mean after
  <= 0.10 m), ICP fitness and inlier RMSE, the transform;
- `tir_pose_error`: before / after the multi-view block / after the rigid ICP / after (per
  frame), position error (mean, median, metres), rotation error (median, degrees), share of
  frames whose reprojection error is below 1 px (RMS over the true view's surface points on a
  16 x 13 pixel grid);
- `cpu_s` / `wall_s` per step and the machine's load average.

Usage: `python bench/orientation_rgb.py [--frames 48] [--buildings 3] [--seed 1] [--interval 0.25]
[--look-up 10] [--per-frame] [--no-multiview] [--prior-direction] [--degeneracy-ratio R]
[--consistent-tracks PX] [--epipolar-band PX]` (a frame
every 2 m: the drive passes several facade directions; the flags switch on the options of the
same names).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from db.citygml.reader import read_model
from workers.pipeline.geometry.georef import prior_poses
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.reconstruction.dense_stereo import dense_cloud
from workers.pipeline.reconstruction.rgb_method import (
    RgbRegistrationOptions,
    corrected_poses,
    register_clouds_of_blocks,
    rgb_prior_poses,
    tir_cloud,
)
from workers.pipeline.synth import BUNDLED_MODEL, RgbOptions, SynthOptions, SynthResult, synthesize
from workers.pipeline.synth.trajectory import DriveOptions

T = TypeVar("T")


def reprojection_px(res: SynthResult, i: int, pose: Pose) -> float:
    """RMS pixel distance between the true and `pose`'s projections of the surface points the
    true view of frame `i` sees on a 16 x 13 grid of pixels."""
    cam, true = res.manifest.camera, res.truth.poses[i]
    label, t = res.renderer.labels(true)
    v, u = np.mgrid[20 : cam.height - 20 : 13j, 20 : cam.width - 20 : 16j]
    uv = np.stack([u.ravel(), v.ravel()], axis=-1)
    depth = t[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
    ok = np.isfinite(depth) & (label[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)] != -1)
    if not np.any(ok):
        return float("nan")
    X = true.world_from_cam(cam.bearing(uv[ok]) * depth[ok, None])
    q, _ = pose.project(cam, X)
    p, _ = true.project(cam, X)
    return float(np.sqrt(np.nanmean(np.sum((q - p) ** 2, axis=1))))


def pose_errors(res: SynthResult, poses: list[Pose]) -> dict:
    """Position / rotation errors of `poses` against the truth and the share of frames < 1 px."""
    dp, dr, px = [], [], []
    for i, (p, t) in enumerate(zip(poses, res.truth.poses, strict=True)):
        dp.append(float(np.linalg.norm(p.center - t.center)))
        c = (np.trace(t.R_world_from_cam.T @ p.R_world_from_cam) - 1) / 2
        dr.append(float(np.degrees(np.arccos(np.clip(c, -1, 1)))))
        px.append(reprojection_px(res, i, p))
    px_a = np.array(px)
    return {
        "position_mean_m": float(np.mean(dp)), "position_median_m": float(np.median(dp)),
        "rotation_median_deg": float(np.median(dr)), "reprojection_median_px": float(np.nanmedian(px_a)),
        "share_below_1px": float(np.mean(px_a < 1.0)),
    }  # fmt: skip


def timed(fn: Callable[..., T], *args: Any, **kw: Any) -> tuple[T, float, float]:
    """(result, cpu seconds, wall seconds) of `fn(*args, **kw)`."""
    c, w = time.process_time(), time.perf_counter()
    out = fn(*args, **kw)
    return out, time.process_time() - c, time.perf_counter() - w


def main() -> None:
    """Run the bench and print its JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--buildings", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--look-up", type=float, default=10.0, help="camera tilt up, degrees")
    ap.add_argument("--interval", type=float, default=0.25, help="seconds between frames (8 m/s)")
    ap.add_argument("--per-frame", action="store_true", help="RgbRegistrationOptions.per_frame")
    ap.add_argument("--prior-direction", action="store_true", help="TIR DenseOptions.prior_direction")
    ap.add_argument("--no-multiview", action="store_true", help="RgbRegistrationOptions.multiview = None")
    ap.add_argument("--degeneracy-ratio", type=float, default=None, help="IcpOptions.degeneracy_ratio")
    ap.add_argument("--consistent-tracks", type=float, default=None, help="MultiViewOptions.start_max_px")
    ap.add_argument("--epipolar-band", type=float, default=None, help="ImageTrackOptions.epipolar_band_px")
    a = ap.parse_args()
    _, blds = read_model(BUNDLED_MODEL)
    opts = SynthOptions(n_frames=a.frames, seed=a.seed, buildings=a.buildings, rgb=RgbOptions(),
                        frame_interval_s=a.interval,
                        drive=DriveOptions(look_up_deg=a.look_up))  # fmt: skip
    res = synthesize(blds, opts)
    m, tr = res.manifest, res.truth
    tir_priors = prior_poses(m, None, time_delay_s=tr.time_delay_s, mounting=tr.true_mounting)
    rgb_poses = rgb_prior_poses(m, None)
    (tir_imgs, c_tir_r, w_tir_r) = timed(lambda: [res.frames.load(i) for i in range(a.frames)])
    (rgb_imgs, c_rgb_r, w_rgb_r) = timed(lambda: [res.rgb.frames.load(i) for i in range(a.frames)])
    o = RgbRegistrationOptions(per_frame=a.per_frame)
    if a.no_multiview:
        o = replace(o, multiview=None)
    if a.prior_direction:
        o = replace(o, tir=replace(o.tir, prior_direction=True))
    if o.multiview is not None and a.consistent_tracks is not None:
        o = replace(o, multiview=replace(o.multiview, start_max_px=a.consistent_tracks))
    if o.multiview is not None and a.epipolar_band is not None:
        mv = o.multiview
        o = replace(o, multiview=replace(mv, tracks=replace(mv.tracks, epipolar_band_px=a.epipolar_band)))
    if a.degeneracy_ratio is not None:
        o = replace(o, icp=replace(o.icp, degeneracy_ratio=a.degeneracy_ratio))
    tir, c_tir, w_tir = timed(tir_cloud, tir_imgs.__getitem__, m.camera, tir_priors, o)
    rgb, c_rgb, w_rgb = timed(dense_cloud, rgb_imgs.__getitem__, m.rgb.camera, rgb_poses, o.rgb)
    placed = tir.placed  # as `register_tir_on_rgb`: the poses the cloud was placed with
    reg, c_icp, w_icp = timed(register_clouds_of_blocks, tir.cloud, rgb, placed, o)
    reg = replace(reg, block=tir.block)
    rigid = corrected_poses(placed, reg.world_from_tir_world)
    f = reg.figures()
    keys = ("fitness", "inlier_rmse_m", "translation_m", "rotation_deg", "accepted", "reason",
            "observed_directions", "per_frame", "per_frame_reason", "frames_with_points",
            "frame_rms_median_m")
    common = np.mean([p.center - t.center for p, t in zip(tir_priors, tr.poses, strict=True)], axis=0)
    out = {
        "options": {"per_frame": a.per_frame, "multiview": not a.no_multiview,
                    "consistent_tracks_px": a.consistent_tracks, "epipolar_band_px": a.epipolar_band,
                    "prior_direction": a.prior_direction, "degeneracy_ratio": o.icp.degeneracy_ratio},
        "scene": {"model": Path(BUNDLED_MODEL).name, "frames": a.frames, "buildings": list(tr.cluster),
                  "seed": a.seed, "look_up_deg": a.look_up, "interval_s": a.interval,
                  "tir": [m.camera.width, m.camera.height],
                  "rgb": [m.rgb.camera.width, m.rgb.camera.height]},
        "clouds": {k: f[k] for k in ("points_tir", "points_rgb", "pairs_tir", "pairs_rgb",
                                     "refined_pairs_tir")},
        "multiview": f.get("multiview"),
        "distance": {k: v for k, v in f.items() if "distance" in k or "trimmed" in k or k in keys},
        "bar_mean_after_le_0_10_m": bool(f.get("mean_distance_after_m", np.inf) <= 0.10),
        "tir_pose_error": {"before": pose_errors(res, tir_priors),
                           "block": pose_errors(res, list(tir.block.poses)) if tir.block else None,
                           "after_rigid": pose_errors(res, rigid),
                           "after": pose_errors(res, list(reg.poses))},
        "true_common_position_error_m": common.tolist(),
        "cpu_s": {"render_tir": c_tir_r, "render_rgb": c_rgb_r, "block_and_dense_tir": c_tir,
                  "dense_rgb": c_rgb, "icp": c_icp},
        "wall_s": {"render_tir": w_tir_r, "render_rgb": w_rgb_r, "block_and_dense_tir": w_tir,
                   "dense_rgb": w_rgb, "icp": w_icp},
        "load_average": list(os.getloadavg()),
    }  # fmt: skip
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

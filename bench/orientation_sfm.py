"""Reconstruction bench (issue 19, item 1, first measurement): pycolmap triangulation from the
GNSS/INS poses and pycolmap's bundle adjustment on the project's own LK tracks, on the
close-range sequence of one facade of `bench/orientation_sequence.py`.

Steps: the tracks of the sequence orientation (`tracks.track_sequence`, from the priors
smoothed over a second, as the orient stage starts) -> a `pycolmap.Reconstruction` (OPENCV
camera, one trivial rig and frame per image, pixel centres moved to COLMAP's +0.5) -> every
track triangulated linearly (DLT on the normalised rays) from the start poses (points behind
or within 0.5 m of a camera left out) -> pycolmap's
bundle adjustment (poses and points free, intrinsics fixed) -> the reconstruction placed in
the model CRS by a 7-parameter similarity, (a) from its points onto their true positions on the
wall (the reconstruction's own accuracy, unreachable in practice) and (b) from the GNSS/INS
(rotation: chordal mean of the prior attitudes against the reconstructed ones; scale and shift:
the camera centres, which on a straight walk leave the rotation about the walking line open).

Printed: tracks, their length and correctness against the truth; the features on TIR
(`features_on_tir`): the LK tracks' observations and those within 1 px of the truth, against
pycolmap SIFT on CLAHE-stretched 8-bit copies matched between consecutive frames (matches and
those within 1 px); per start (raw priors,
smoothed priors) registered frames, points, mean reprojection error before and after the
adjustment (px), CPU seconds; per placement the share of frames below 1 px (wall points every
metre against the true poses), median and 90th percentile.

Usage:
`python bench/orientation_sfm.py [--frames 40] [--seed 3]`.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.orientation_sequence import figures, frame_errors, noisy_priors, one_wall, wall_points
from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.quality import tie_errors
from workers.pipeline.orientation.smoothing import smooth_poses
from workers.pipeline.orientation.tracks import Tracks, track_sequence
from workers.pipeline.reconstruction.colmap import colmap_camera
from workers.pipeline.synth import SynthOptions, synthesize


def reconstruction(camera: Camera, tracks: Tracks, poses: Mapping[int, Pose], n: int):
    """A `pycolmap.Reconstruction` of frames `0..n-1` at `poses` with every track of two or more
    observations triangulated linearly from them (image ids = frame + 1)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(colmap_camera(camera))
    where: dict[int, tuple[int, int]] = {}
    for f in range(n):
        obs = np.flatnonzero(tracks.frame == f)
        img = pycolmap.Image(name=f"{f:06d}", keypoints=tracks.uv[obs] + 0.5, camera_id=1, image_id=f + 1)
        R = poses[f].R_world_from_cam.T
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ poses[f].center))
        where.update({int(o): (f + 1, k) for k, o in enumerate(obs)})
    for t in range(tracks.n_tracks):
        obs = np.flatnonzero(tracks.track == t)
        if len(obs) < 2:
            continue
        rows = []
        for o in obs:
            p = poses[int(tracks.frame[o])]
            b = camera.bearing(tracks.uv[o][None])[0]
            P = np.hstack([p.R_world_from_cam.T, (-p.R_world_from_cam.T @ p.center)[:, None]])
            rows += [b[0] / b[2] * P[2] - P[0], b[1] / b[2] * P[2] - P[1]]
        X = np.linalg.svd(np.array(rows))[2][-1]
        if abs(X[3]) < 1e-12:
            continue
        X = X[:3] / X[3]
        if min(float(poses[int(tracks.frame[o])].project(camera, X[None])[1][0]) for o in obs) < 0.5:
            continue  # behind or at a camera: an ill-conditioned intersection
        track = pycolmap.Track()
        for o in obs:
            track.add_element(*where[int(o)])
        rec.add_point3D(X, track)
    return rec


def poses_of(rec, n: int) -> dict[int, Pose]:
    """`{frame: Pose}` (world = the reconstruction's) of images `1..n`."""
    out = {}
    for f in range(n):
        M = rec.images[f + 1].cam_from_world().matrix()
        out[f] = Pose(M[:, :3].T, -M[:, :3].T @ M[:, 3])
    return out


def similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale, rotation `(3, 3)`, shift `(3,)` with `dst ≈ s R src + t` (Umeyama), points `(N, 3)`."""
    ms, md = src.mean(0), dst.mean(0)
    U, sv, Vt = np.linalg.svd((dst - md).T @ (src - ms) / len(src))
    E = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ E @ Vt
    s = float(np.trace(np.diag(sv) @ E) / np.mean(np.sum((src - ms) ** 2, axis=1)))
    return s, R, md - s * R @ ms


def moved(poses: Mapping[int, Pose], s: float, R: np.ndarray, t: np.ndarray) -> dict[int, Pose]:
    """The poses under `x -> s R x + t`."""
    return {f: Pose(R @ p.R_world_from_cam, s * R @ p.center + t) for f, p in poses.items()}


def true_points(rec, camera: Camera, truth: list[Pose], caster: RayCaster) -> tuple[np.ndarray, np.ndarray]:
    """Reconstructed points `(K, 3)` and their true positions `(K, 3)`: the first observation's
    ray from the true pose onto the model."""
    got, true = [], []
    for pt in rec.points3D.values():
        el = pt.track.elements[0]
        f = el.image_id - 1
        uv = np.asarray(rec.images[el.image_id].points2D[el.point2D_idx].xy) - 0.5
        d = camera.bearing(uv[None]) @ truth[f].R_world_from_cam.T
        hit = caster.cast(truth[f].center[None], d)
        if hit.hit[0]:
            got.append(pt.xyz)
            true.append(truth[f].center + hit.t[0] * d[0])
    return np.array(got), np.array(true)


def gnss_placement(
    poses: Mapping[int, Pose], prior: Mapping[int, Pose]
) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity from the GNSS/INS: rotation the chordal mean of `R_prior R_recᵀ`, scale and
    shift from the camera centres."""
    M = sum(prior[f].R_world_from_cam @ poses[f].R_world_from_cam.T for f in poses)
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    C = np.array([R @ poses[f].center for f in poses])
    Cp = np.array([prior[f].center for f in poses])
    s = float(np.sum((C - C.mean(0)) * (Cp - Cp.mean(0))) / np.sum((C - C.mean(0)) ** 2))
    return s, R, Cp.mean(0) - s * C.mean(0)


def clahe8(image: np.ndarray, clip: float = 3.0, tiles: int = 8) -> np.ndarray:
    """A float TIR frame `(H, W)` as a locally contrast-stretched 8-bit copy (2nd–98th percentile
    to 0–255, then OpenCV CLAHE with `clip` and `tiles` × `tiles` tiles)."""
    import cv2

    lo, hi = np.percentile(image, [2, 98])
    u8 = np.clip((image - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
    return cv2.createCLAHE(clipLimit=clip, tileGridSize=(tiles, tiles)).apply(u8)


def sift_pairs(
    camera: Camera, images: Mapping[int, np.ndarray], truth: list[Pose], caster: RayCaster
) -> dict:
    """pycolmap SIFT on `clahe8` copies, matched between consecutive frames (mutual nearest
    neighbours with Lowe's ratio 0.8, OpenCV): matches, and those within 1 px of the truth (the
    first keypoint's true ray on the model projected with the next true pose)."""
    import cv2
    import pycolmap

    sift = pycolmap.Sift()
    feats = {f: sift.extract(clahe8(img)) for f, img in images.items()}
    bf = cv2.BFMatcher(cv2.NORM_L2, crossCheck=False)
    n = correct = 0
    frames = sorted(images)
    for a, b in itertools.pairwise(frames):
        (ka, da), (kb, db) = feats[a], feats[b]
        if len(ka) < 2 or len(kb) < 2:
            continue
        ms = [
            m
            for m, m2 in bf.knnMatch(da.astype(np.float32), db.astype(np.float32), k=2)
            if m.distance < 0.8 * m2.distance
        ]
        if not ms:
            continue
        ua = ka[[m.queryIdx for m in ms], :2] - 0.5
        ub = kb[[m.trainIdx for m in ms], :2] - 0.5
        d = camera.bearing(ua) @ truth[a].R_world_from_cam.T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        hit = caster.cast(np.broadcast_to(truth[a].center, d.shape), d)
        X = truth[a].center + np.where(hit.hit, hit.t, 0.0)[:, None] * d
        uv, z = truth[b].project(camera, X)
        ok = hit.hit & (z > 0) & (np.linalg.norm(uv - ub, axis=1) < 1.0)
        n += len(ms)
        correct += int(ok.sum())
    return {"matches": n, "correct_within_1px": correct}


def lk_pairs(tracks: Tracks, camera: Camera, truth: list[Pose], caster: RayCaster) -> dict:
    """The LK tracks as consecutive correspondences: count, and those within 1 px of the truth."""
    e = tie_errors(tracks, camera, truth, caster)
    return {"observations": len(tracks.track), "correct_within_1px": int(np.sum(e < 1.0))}


def main() -> None:
    import pycolmap

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--seed", type=int, default=3)
    a = ap.parse_args()
    n = a.frames
    res = synthesize(
        [one_wall()],
        SynthOptions(platform="terrestrial", n_frames=n, seed=a.seed, buildings=1, frame_interval_s=0.4),
    )
    cam, truth = res.manifest.camera, list(res.truth.poses)
    images = {i: res.frames.load(i) for i in range(n)}
    prior = dict(enumerate(noisy_priors(truth, a.seed)))
    times = {i: f.time for i, f in enumerate(res.manifest.frames)}
    caster = RayCaster(res.mesh)
    c0 = time.process_time()
    start = smooth_poses(prior, range(n), times, 1.0)
    tracks = track_sequence(cam, list(range(n)), images, start, caster)
    e = tie_errors(tracks, cam, truth, caster)
    out: dict = {
        "bench": "orientation_sfm",
        "pycolmap": pycolmap.__version__,
        "frames": n,
        "tracks": int(tracks.n_tracks),
        "observations": len(tracks.track),
        "mean_track_length": round(float(tracks.lengths().mean()), 2),
        "ties_within_1px_of_truth": round(float(np.mean(e < 1.0)), 3),
        "tracking_cpu_s": round(time.process_time() - c0, 2),
        "priors": figures(frame_errors(res, wall_points(), prior)),
        "features_on_tir": {
            "lk_float": lk_pairs(tracks, cam, truth, caster),
            "sift_clahe8": sift_pairs(cam, images, truth, caster),
        },
    }
    for name, init in (("from_priors", prior), ("from_smoothed_priors", start)):
        c0 = time.process_time()
        rec = reconstruction(cam, tracks, init, n)
        rec.update_point_3d_errors()
        before = rec.compute_mean_reprojection_error()
        opts = pycolmap.BundleAdjustmentOptions()
        opts.refine_focal_length = opts.refine_principal_point = opts.refine_extra_params = False
        pycolmap.bundle_adjustment(rec, opts)
        rec.update_point_3d_errors()
        cpu = time.process_time() - c0
        P = poses_of(rec, n)
        got, true = true_points(rec, cam, truth, caster)
        out[name] = {
            "registered_frames": rec.num_reg_images(),
            "points": rec.num_points3D(),
            "mean_reprojection_px_before_adjustment": round(float(before), 3),
            "mean_reprojection_px_after_adjustment": round(float(rec.compute_mean_reprojection_error()), 3),
            "cpu_s": round(cpu, 2),
            "placed_on_true_points": figures(
                frame_errors(res, wall_points(), moved(P, *similarity(got, true)))
            ),
            "placed_by_gnss_ins": figures(
                frame_errors(res, wall_points(), moved(P, *gnss_placement(P, prior)))
            ),
        }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

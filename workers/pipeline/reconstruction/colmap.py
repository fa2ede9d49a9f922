"""The sequence's tracks as a `pycolmap.Reconstruction`: every track triangulated from the start
poses, then pycolmap's bundle adjustment (poses and points free, intrinsics fixed, Cauchy loss).

Coordinates: the reconstruction's world is the model CRS minus `origin` (a local origin near
the cameras keeps COLMAP's doubles well conditioned); image `k + 1` is the `k`-th frame given;
COLMAP's pixel centres sit at +0.5 of the project's (`Camera`: pixel centres at integers).

Why triangulation from the priors and not COLMAP's incremental mapper: the GNSS/INS poses
already give every frame's pose to decimetres and the LK tracks give the correspondences, so
the mapper's two-view initialisation and registration by PnP add nothing but the chance to
fail on the weak baselines of a drive along one facade; measured on the one-facade sequence
(`bench/orientation_sfm.py`), triangulation from the smoothed priors and one adjustment reach
0.09 px mean reprojection error with every frame registered.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.orientation.tracks import Tracks
from workers.pipeline.reconstruction.options import ReconstructionOptions
from workers.pipeline.reconstruction.similarity import umeyama


@dataclass(frozen=True, eq=False)
class Adjusted:
    """An adjusted reconstruction of a run of frames.

    Attributes:
        poses: `{frame: Pose}` of the registered frames, world = model CRS − `origin`.
        points: `(K, 3)` adjusted points (same world); `track_ids` `(K,)` their track indices.
        obs_track, obs_frame: `(M,)` track index and frame of each kept observation; `obs_uv`
            `(M, 2)` its pixel (project convention); `obs_error_px` `(M,)` its reprojection error.
        sigma0_px: RMS reprojection error of the kept observations (px).
        before_px: the same before the adjustment (triangulated from the start poses).
    """

    poses: dict[int, Pose]
    points: np.ndarray
    track_ids: np.ndarray
    obs_track: np.ndarray
    obs_frame: np.ndarray
    obs_uv: np.ndarray
    obs_error_px: np.ndarray
    sigma0_px: float
    before_px: float


def colmap_camera(camera: Camera) -> Any:  # pycolmap.Camera
    """The project's `Camera` (Brown k1, k2, p1, p2) as a COLMAP OPENCV camera, id 1."""
    import pycolmap

    params = [
        camera.fx,
        camera.fy,
        camera.cx + 0.5,
        camera.cy + 0.5,
        camera.k1,
        camera.k2,
        camera.p1,
        camera.p2,
    ]
    return pycolmap.Camera(
        model="OPENCV", width=camera.width, height=camera.height, params=params, camera_id=1
    )


def triangulate(
    camera: Camera, tracks: Tracks, poses: Mapping[int, Pose], options: ReconstructionOptions
) -> tuple[np.ndarray, np.ndarray]:
    """Linear (DLT on normalised rays) intersection of every track of `min_track_length` or more
    observations from `poses` (world as given). Returns `(track ids (K,), points (K, 3))`;
    tracks with a point behind or within `min_depth_m` of an observing camera, or whose rays
    span less than `min_angle_deg`, are left out."""
    bearings = camera.bearing(tracks.uv)
    ids, pts = [], []
    order = np.argsort(tracks.track, kind="stable")
    bounds = np.searchsorted(tracks.track[order], np.arange(tracks.n_tracks + 1))
    cos_min = np.cos(np.radians(options.min_angle_deg))
    for t in range(tracks.n_tracks):
        obs = order[bounds[t] : bounds[t + 1]]
        if len(obs) < options.min_track_length:
            continue
        Rs = np.array([poses[int(tracks.frame[o])].R_world_from_cam for o in obs])
        Cs = np.array([poses[int(tracks.frame[o])].center for o in obs])
        b = bearings[obs]
        rays = np.einsum("nij,nj->ni", Rs, b / np.linalg.norm(b, axis=1, keepdims=True))
        if np.min(rays @ rays.T) > cos_min:
            continue
        P = np.concatenate(
            [np.transpose(Rs, (0, 2, 1)), -np.einsum("nji,nj->ni", Rs, Cs)[:, :, None]], axis=2
        )
        x, y = b[:, 0] / b[:, 2], b[:, 1] / b[:, 2]
        A = np.concatenate([x[:, None] * P[:, 2] - P[:, 0], y[:, None] * P[:, 2] - P[:, 1]])
        X = np.linalg.svd(A)[2][-1]
        if abs(X[3]) < 1e-12:
            continue
        X = X[:3] / X[3]
        depth = np.einsum("ni,ni->n", X - Cs, Rs[:, :, 2])
        if np.min(depth) < options.min_depth_m:
            continue
        ids.append(t)
        pts.append(X)
    return np.asarray(ids, dtype=np.int64), np.asarray(pts, dtype=np.float64).reshape(-1, 3)


def reconstruct(
    camera: Camera,
    tracks: Tracks,
    frames: Sequence[int],
    start: Mapping[int, Pose],
    options: ReconstructionOptions,
) -> Adjusted | None:
    """Triangulate the tracks of `frames` from `start` (world = model CRS − origin) and adjust
    with pycolmap (`ba_rounds` rounds, observations beyond `max_reprojection_px` dropped between
    them). None when fewer than two frames keep `min_frame_points` points."""
    import pycolmap

    ids, X = triangulate(camera, tracks, start, options)
    if len(ids) < options.min_frame_points:
        return None
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(colmap_camera(camera))
    image_of = {f: k + 1 for k, f in enumerate(frames)}
    keep = np.isin(tracks.track, ids)
    where: dict[int, tuple[int, int]] = {}
    for f in frames:
        obs = np.flatnonzero(keep & (tracks.frame == f))
        img = pycolmap.Image(
            name=f"{f:08d}", keypoints=tracks.uv[obs] + 0.5, camera_id=1, image_id=image_of[f]
        )
        R = start[f].R_world_from_cam.T
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ start[f].center))
        where.update({int(o): (image_of[f], k) for k, o in enumerate(obs)})
    point_of_track: dict[int, int] = {}
    for t, x in zip(ids, X, strict=True):
        track = pycolmap.Track()
        for o in np.flatnonzero(tracks.track == t):
            track.add_element(*where[int(o)])
        point_of_track[int(t)] = rec.add_point3D(x, track)
    rec.update_point_3d_errors()
    before = float(rec.compute_mean_reprojection_error())
    for _ in range(options.ba_rounds):
        _adjust(rec, options)
        _drop_outliers(rec, options)
    return _collect(rec, camera, frames, image_of, point_of_track, tracks, before, options)


def _adjust(rec, options: ReconstructionOptions) -> None:  # noqa: ANN001 (pycolmap.Reconstruction)
    """One pycolmap bundle adjustment of `rec` in place (intrinsics fixed, Cauchy loss, 1 thread,
    its datum moved back onto the camera centres it started from)."""
    import pycolmap

    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = opts.refine_principal_point = opts.refine_extra_params = False
    opts.print_summary = False
    opts.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    opts.ceres.loss_function_scale = options.ba_loss_px
    opts.ceres.solver_options.max_num_iterations = options.ba_iterations
    opts.ceres.solver_options.num_threads = 1
    centers = {i: np.asarray(rec.images[i].projection_center()) for i in rec.reg_image_ids()}
    pycolmap.bundle_adjustment(rec, opts)
    # back onto the start poses' datum: the free gauge lets the scale drift (measured: × 0.002
    # and × 4.8 on a 24-frame facade walk; COLMAP's two-camera gauge on a 0.3 m first baseline
    # did no better), which the shape survives but the conditioning of what follows does not
    ids = sorted(centers)
    src = np.array([rec.images[i].projection_center() for i in ids])
    S = umeyama(src, np.array([centers[i] for i in ids]))
    rec.transform(pycolmap.Sim3d(S.scale, pycolmap.Rotation3d(S.R), S.t))
    rec.update_point_3d_errors()


def _drop_outliers(rec, options: ReconstructionOptions) -> None:  # noqa: ANN001
    """Drop observations of `rec` beyond `max_reprojection_px`, then points left with < 2."""
    for pid in list(rec.points3D):
        pt = rec.points3D[pid]
        for el in list(pt.track.elements):
            img = rec.images[el.image_id]
            if img.points2D[el.point2D_idx].point3D_id != pid:
                continue  # an element whose keypoint another point took over
            uv = img.project_point(pt.xyz)
            err = (
                np.inf
                if uv is None
                else float(np.linalg.norm(np.asarray(uv) - img.points2D[el.point2D_idx].xy))
            )
            if err > options.max_reprojection_px:
                if rec.points3D[pid].track.length() <= 2:
                    rec.delete_point3D(pid)
                    break
                rec.delete_observation(el.image_id, el.point2D_idx)
    rec.update_point_3d_errors()


def _collect(
    rec,  # noqa: ANN001 (pycolmap.Reconstruction)
    camera: Camera,
    frames: Sequence[int],
    image_of: Mapping[int, int],
    point_of_track: Mapping[int, int],
    tracks: Tracks,
    before: float,
    options: ReconstructionOptions,
) -> Adjusted | None:
    """`Adjusted` from the pycolmap reconstruction (frames with `min_frame_points` points)."""
    track_of_point = {p: t for t, p in point_of_track.items()}
    t_ids, pts, o_t, o_f, o_uv, o_e = [], [], [], [], [], []
    frame_of_image = {i: f for f, i in image_of.items()}
    for pid, pt in rec.points3D.items():
        t_ids.append(track_of_point[pid])
        pts.append(np.asarray(pt.xyz))
        for el in pt.track.elements:
            img = rec.images[el.image_id]
            xy = np.asarray(img.points2D[el.point2D_idx].xy)
            uv = img.project_point(pt.xyz)
            o_t.append(track_of_point[pid])
            o_f.append(frame_of_image[el.image_id])
            o_uv.append(xy - 0.5)
            o_e.append(np.inf if uv is None else float(np.linalg.norm(np.asarray(uv) - xy)))
    o_f_arr = np.asarray(o_f, dtype=np.int64)
    poses: dict[int, Pose] = {}
    for f in frames:
        if np.sum(o_f_arr == f) >= options.min_frame_points:
            M = rec.images[image_of[f]].cam_from_world().matrix()
            poses[f] = Pose(M[:, :3].T, -M[:, :3].T @ M[:, 3])
    if len(poses) < 2:
        return None
    # observations in registered frames only, points they still see twice
    obs_t, e = np.asarray(o_t, dtype=np.int64), np.asarray(o_e, dtype=np.float64)
    m = np.isin(o_f_arr, list(poses))
    ids = np.asarray(t_ids, dtype=np.int64)
    row = {int(t): k for k, t in enumerate(ids)}
    counts = np.bincount([row[int(t)] for t in obs_t[m]], minlength=len(ids))
    alive = counts >= 2
    m &= np.isin(obs_t, ids[alive])
    return Adjusted(
        poses=poses,
        points=np.asarray(pts, dtype=np.float64).reshape(-1, 3)[alive],
        track_ids=ids[alive],
        obs_track=obs_t[m],
        obs_frame=o_f_arr[m],
        obs_uv=np.asarray(o_uv, dtype=np.float64).reshape(-1, 2)[m],
        obs_error_px=e[m],
        sigma0_px=float(np.sqrt(np.mean(e[m] ** 2))) if m.any() else float("nan"),
        before_px=before,
    )


def components(adj: Adjusted, min_shared: int, min_frames: int = 3) -> list[Adjusted]:
    """`adj` split into its connected parts: frames linked when they share `min_shared` points
    (a run whose tracks break, e.g. over a blank stretch, is several reconstructions, each with
    its own datum); parts of fewer than `min_frames` frames are left out."""
    frames = sorted(adj.poses)
    parent = {f: f for f in frames}

    def root(f: int) -> int:
        while parent[f] != f:
            parent[f] = parent[parent[f]]
            f = parent[f]
        return f

    shared: dict[tuple[int, int], int] = {}
    for t in adj.track_ids:
        fs = sorted(set(adj.obs_frame[adj.obs_track == t].tolist()))
        for a, b in itertools.pairwise(fs):
            shared[(a, b)] = shared.get((a, b), 0) + 1
    for (a, b), k in shared.items():
        if k >= min_shared:
            parent[root(a)] = root(b)
    groups: dict[int, list[int]] = {}
    for f in frames:
        groups.setdefault(root(f), []).append(f)
    return [_part(adj, g) for g in groups.values() if len(g) >= min_frames]


def _part(adj: Adjusted, frames: list[int]) -> Adjusted:
    """The frames `frames` of `adj` with their observations and the points seen twice there."""
    m = np.isin(adj.obs_frame, frames)
    ids, counts = np.unique(adj.obs_track[m], return_counts=True)
    keep_t = ids[counts >= 2]
    m &= np.isin(adj.obs_track, keep_t)
    alive = np.isin(adj.track_ids, keep_t)
    e = adj.obs_error_px[m]
    return Adjusted(
        poses={f: adj.poses[f] for f in frames},
        points=adj.points[alive],
        track_ids=adj.track_ids[alive],
        obs_track=adj.obs_track[m],
        obs_frame=adj.obs_frame[m],
        obs_uv=adj.obs_uv[m],
        obs_error_px=e,
        sigma0_px=float(np.sqrt(np.mean(e**2))) if len(e) else float("nan"),
        before_px=adj.before_px,
    )

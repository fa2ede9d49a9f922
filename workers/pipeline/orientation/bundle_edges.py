"""The model-edge normal equations of every frame of a block at once (the bundle's edge term).

In: a `Camera`, per frame its pose, visible wireframe samples (`VisibleWireframe`) and image
features (`ImageFeatures`), the edge search radius, `FrameFitOptions`. Out: per frame the `(6, 6)`
normal matrix and `(6,)` right-hand side of its edge-normal distances, as
`edge_observations.normal_equations` gives them frame by frame without corner points and without
a prior (`H = Aᵀ W A`, `g = Aᵀ W d`).

Why (issue 18): the bundle adjustment of a 120-frame window linearises the edges of every frame
in each of its iterations; frame by frame that was 5,000 calls of some thirty small numpy
operations on a few hundred samples each per window, the largest part of the sequence
orientation's time. Here the samples of all frames are stacked, projected, searched and weighted
in one pass; only the gradient lookup (`cv2.remap` on each frame's own gradient image) stays
per frame. The arithmetic is the same as `normal_equations` sample by sample (same formulas,
same order of the per-sample operations), so the results agree to rounding. The calibration and
the joint fit take the same equations (`edge_equations`); the bundle's tie points are projected
the same way, a pose per observation (`stacked_project`, `stacked_project_jacobian`).
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import camera_point_jacobian
from workers.pipeline.orientation.edge_observations import edge_offsets, tukey
from workers.pipeline.orientation.features import ImageFeatures
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.wireframe import VisibleWireframe

__all__ = [
    "edge_equations",
    "stacked_edge_equations",
    "stacked_project",
    "stacked_project_jacobian",
]


def stacked_project(
    camera: Camera, R: np.ndarray, C: np.ndarray, X: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """`Pose.project` with a pose per point: rotations `R` `(N, 3, 3)` (world from camera),
    centres `C` `(N, 3)`, world points `X` `(N, 3)` -> (pixels `(N, 2)`, NaN behind the camera;
    depth `z_c` `(N,)`)."""
    xc = np.einsum("ni,nij->nj", X - C, R)
    return camera.project(xc), xc[:, 2]


def stacked_project_jacobian(
    camera: Camera, R: np.ndarray, C: np.ndarray, X: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`pose_increments.project_jacobian` with a pose per point: rotations `R` `(N, 3, 3)`
    (world from camera), centres `C` `(N, 3)`, world points `X` `(N, 3)` -> (pixels `(N, 2)`,
    depth `(N,)`, `∂uv/∂δ` `(N, 2, 6)`)."""
    return camera_point_jacobian(camera, np.einsum("ni,nij->nj", X - C, R), R)


def stacked_edge_equations(
    camera: Camera,
    poses: Sequence[Pose],
    vis: Sequence[VisibleWireframe],
    feats: Sequence[ImageFeatures],
    R_e: float,
    options: FrameFitOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """The edge normal equations of K frames (module docstring): frame k at `poses[k]` with its
    visible samples `vis[k]` (at least one each) and features `feats[k]`, edge search radius
    `R_e` px, Tukey constant floored at `options.tukey_min_px`.

    Returns (H `(K, 6, 6)`, g `(K, 6)`) on `δ = (ω_cam [rad], dC_world [m])`, px⁻² units.
    """
    K = len(poses)
    if K == 0:
        return np.zeros((0, 6, 6)), np.zeros((0, 6))
    counts = np.array([len(v.points) for v in vis])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    fid = np.repeat(np.arange(K), counts)
    P = np.concatenate([v.points for v in vis]).astype(np.float64)
    Dir = np.concatenate([v.direction for v in vis]).astype(np.float64)
    Wgt = np.concatenate([v.weight for v in vis])
    R = np.stack([p.R_world_from_cam for p in poses])[fid]
    C = np.stack([p.center for p in poses])[fid]
    uv, _, J = stacked_project_jacobian(camera, R, C, P)
    # image normals of the projected edges (`edge_observations.image_normals`)
    xc2 = np.einsum("ni,nij->nj", P + 0.05 * Dir - C, R)
    t = camera.project(xc2) - uv
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    nrm = np.stack([-t[:, 1], t[:, 0]], axis=1)
    off, found = _edge_search(feats, uv, nrm, R_e, options, counts, starts, fid)
    A = np.einsum("ni,nij->nj", nrm, J)
    bad = ~np.isfinite(A).all(axis=1) | ~np.isfinite(off)
    if bad.any():
        A[bad], off, found = 0.0, np.where(bad, 0.0, off), found & ~bad
    scale = np.empty(K)
    for k in range(K):
        sl = slice(starts[k], starts[k] + counts[k])
        fk = found[sl]
        scale[k] = 1.4826 * float(np.median(np.abs(off[sl][fk]))) if fk.any() else R_e
    c = np.maximum(options.tukey_min_px, 4.685 * scale)
    unit = options.edge_sample_weight / options.sigma_edge_px**2
    w_e = found * Wgt * tukey(off, np.minimum(c, R_e)[fid]) * unit
    Aw = A * w_e[:, None]
    # per frame `Aᵀ W A` and `Aᵀ W d` as small matrix products (an `(N, 6, 6)` stack of outer
    # products summed with `np.add.reduceat` took 9 times longer)
    H, g = np.empty((K, 6, 6)), np.empty((K, 6))
    for k in range(K):
        sl = slice(starts[k], starts[k] + counts[k])
        H[k], g[k] = Aw[sl].T @ A[sl], Aw[sl].T @ off[sl]
    return H, g


def edge_equations(
    camera: Camera,
    poses: Sequence[Pose],
    vis: Sequence[VisibleWireframe],
    feats: Sequence[ImageFeatures],
    R_e: float,
    options: FrameFitOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """`stacked_edge_equations` of the frames with at least `options.min_samples` visible
    samples; zeros `(6, 6)`, `(6,)` for the others (which observe nothing), in the given order.

    Returns (H `(K, 6, 6)`, g `(K, 6)`)."""
    K = len(poses)
    H, g = np.zeros((K, 6, 6)), np.zeros((K, 6))
    used = [k for k in range(K) if len(vis[k].points) >= options.min_samples]
    if used:
        H[used], g[used] = stacked_edge_equations(camera, [poses[k] for k in used], [vis[k] for k in used],
                                                  [feats[k] for k in used], R_e, options)
    return H, g


def _edge_search(
    feats: Sequence[ImageFeatures], uv: np.ndarray, normal: np.ndarray, radius: float,
    options: FrameFitOptions, counts: np.ndarray, starts: np.ndarray, fid: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """`edge_observations.edge_search` of the stacked samples `uv`, `normal` `(N, 2)`, frame k's
    `counts[k]` samples from `starts[k]` (`fid` `(N,)`: each sample's frame) searched in
    `feats[k]` -> (signed offsets `(N,)` px, found `(N,)`)."""
    n = len(uv)
    R = int(np.ceil(radius))
    k = np.arange(-R, R + 1, dtype=np.float64)
    roi = np.array([f.roi[:2] for f in feats], dtype=np.float64)[fid]
    shape = np.array([f.gx.shape for f in feats])[fid]
    ref = np.array([f.grad_ref for f in feats])[fid]
    pu = uv[:, 0:1] - roi[:, 0:1] + k[None, :] * normal[:, 0:1]
    pv = uv[:, 1:2] - roi[:, 1:2] + k[None, :] * normal[:, 1:2]
    inside = (pu >= 0) & (pu <= shape[:, 1:2] - 1) & (pv >= 0) & (pv <= shape[:, 0:1] - 1)
    pu32, pv32 = pu.astype(np.float32), pv.astype(np.float32)
    g = np.empty((n, 2 * R + 1, 2), np.float32)
    for j, f in enumerate(feats):
        sl = slice(starts[j], starts[j] + counts[j])
        g[sl] = cv2.remap(f.grad, pu32[sl], pv32[sl], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return edge_offsets(g, normal, inside, ref[:, None], R, options)

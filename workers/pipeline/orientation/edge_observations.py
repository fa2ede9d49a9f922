"""Edge observations of one frame against a model wireframe: what the orientation stages share.

In: a `Camera`, a pose, a `Wireframe` (`wireframe`) and the `RayCaster` of the scene, a frame's
`ImageFeatures` (`features`), `FrameFitOptions` (`fit_options`). Out: the visible edge
samples (thinned), the frame box around them, the 1-D search along each projected edge's normal
for the strongest image edge (signed sub-pixel offsets), the normal equations of the six
exterior-orientation parameters from those offsets (Tukey weights) and from corner-to-point
matches, and the edge support of a pose (share of samples on an image edge, and the same with
the samples moved off their edges: the null support).

Poses are corrected by `δ = (ω, dC)` with `R_world_from_cam ← R · exp([ω]×)` (ω in the camera
frame, radians) and `C ← C + dC` (world, metres), `geometry.pose_increments`. Used by the
per-frame fit (`frame_fit`), the joint fit (`common_correction`), the calibration (`calibration`),
the bundle adjustment (`bundle`) and the block's check of the sequence poses (`block`).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.pose_increments import pose_delta, project_jacobian, so3_log
from workers.pipeline.geometry.raycast import RayCaster
from workers.pipeline.orientation.features import (
    FeatureError,
    FeatureOptions,
    ImageFeatures,
    extract_features,
)
from workers.pipeline.orientation.fit_options import FrameFitOptions
from workers.pipeline.orientation.wireframe import EdgeOptions, VisibleWireframe, Wireframe, visible_wireframe

__all__ = [
    "FrameEdges",
    "FrameWireframes",
    "cull_wireframe",
    "edge_offsets",
    "edge_search",
    "edge_support",
    "frame_box",
    "frame_edges",
    "frustum_tangents",
    "image_normals",
    "match_corners",
    "matched_edges",
    "normal_equations",
    "thinned",
    "tukey",
    "visible_samples",
]


def edge_search(
    feats: ImageFeatures, uv: np.ndarray, normal: np.ndarray, radius: float, options: FrameFitOptions
) -> tuple[np.ndarray, np.ndarray]:
    """1-D search along `normal` `(N, 2)` from `uv` `(N, 2)` within ±`radius` px.

    Returns (signed offset `(N,)` px to the chosen edge (sub-pixel), found `(N,)` bool). The edge is
    the strongest gradient component along the normal (gradient within `edge_max_angle_deg` of
    it, above `edge_min_gradient_rel` × the ROI scale), mildly favouring small offsets.
    """
    n = len(uv)
    if n == 0:
        return np.zeros(0), np.zeros(0, bool)
    R = int(np.ceil(radius))
    k = np.arange(-R, R + 1, dtype=np.float64)
    u0, v0 = feats.roi[0], feats.roi[1]
    pu = uv[:, 0:1] - u0 + k[None, :] * normal[:, 0:1]
    pv = uv[:, 1:2] - v0 + k[None, :] * normal[:, 1:2]
    h, w = feats.gx.shape
    inside = (pu >= 0) & (pu <= w - 1) & (pv >= 0) & (pv <= h - 1)
    g = cv2.remap(feats.grad, pu.astype(np.float32), pv.astype(np.float32), cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_REPLICATE)
    return edge_offsets(g, normal, inside, feats.grad_ref, R, options)


def edge_offsets(
    g: np.ndarray, normal: np.ndarray, inside: np.ndarray, grad_ref: float | np.ndarray, R: int,
    options: FrameFitOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """The edge along each search line of `edge_search`: gradients `g` `(N, 2R + 1, 2)` (x, y)
    sampled at offsets `k = -R .. R` px along `normal` `(N, 2)`, `inside` `(N, 2R + 1)` where the
    sample lies in the image, `grad_ref` the gradient scale (a number, or `(N, 1)` one per line).

    Returns (signed offset `(N,)` px, sub-pixel; found `(N,)` bool)."""
    n = len(g)
    k = np.arange(-R, R + 1, dtype=np.float64)
    gx, gy = g[..., 0].astype(np.float64), g[..., 1].astype(np.float64)
    gn = np.abs(gx * normal[:, 0:1] + gy * normal[:, 1:2])
    gm = np.hypot(gx, gy)
    cos_lim = np.cos(np.radians(options.edge_max_angle_deg))
    valid = inside & (gn >= options.edge_min_gradient_rel * grad_ref) & (gn >= cos_lim * gm)
    # only interior local maxima of the gradient along the search line (a rising gradient at the
    # end of the line is no edge within the radius)
    valid[:, 1:] &= gn[:, 1:] >= gn[:, :-1]
    valid[:, :-1] &= gn[:, :-1] >= gn[:, 1:]
    valid[:, [0, -1]] = False
    score = np.where(valid, gn * _penalty(R, options.edge_distance_scale)[None, :], -1.0)
    rows = np.arange(n)
    j = np.argmax(score, axis=1)
    found = score[rows, j] > 0
    # parabolic sub-pixel refinement of the gradient peak
    jl = np.clip(j - 1, 0, 2 * R)
    jr = np.clip(j + 1, 0, 2 * R)
    gl, gc, gr = gn[rows, jl], gn[rows, j], gn[rows, jr]
    den = gl - 2 * gc + gr
    interior = (np.abs(den) > 1e-12) & (jl != j) & (jr != j)
    sub = np.where(interior, 0.5 * (gl - gr) / np.where(den == 0, 1, den), 0)
    return k[j] + np.clip(sub, -0.5, 0.5), found


@functools.lru_cache(maxsize=64)
def _penalty(R: int, scale: float) -> np.ndarray:
    """`(2R + 1,)` the search's mild preference for small offsets `k = -R .. R` (px):
    `exp(-k² / 2 (scale · max(R, 1))²)`. Read-only."""
    k = np.arange(-R, R + 1, dtype=np.float64)
    p = np.exp(-0.5 * (k / (scale * max(R, 1))) ** 2)
    p.flags.writeable = False
    return p


def image_normals(camera: Camera, pose: Pose, vis: VisibleWireframe, uv: np.ndarray) -> np.ndarray:
    """Unit image normals `(N, 2)` of the projected edges at the samples."""
    step = 0.05
    uv2, _ = pose.project(camera, vis.points + step * vis.direction)
    t = uv2 - uv
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    return np.stack([-t[:, 1], t[:, 0]], axis=1)


def tukey(r: np.ndarray, c: float) -> np.ndarray:
    x = np.abs(r) / c
    return np.where(x < 1, (1 - x * x) ** 2, 0.0)


def match_corners(
    uv_c: np.ndarray, points: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest image point `(K, 2)` within `radius` of each projected corner `(M, 2)` -> (index, ok)."""
    if len(uv_c) == 0 or len(points) == 0:
        return np.zeros(len(uv_c), int), np.zeros(len(uv_c), bool)
    d, j = cKDTree(points).query(uv_c, k=1)
    return np.asarray(j, dtype=int), np.asarray(d) <= radius


def visible_samples(
    wireframe: Wireframe, camera: Camera, pose: Pose, raycaster: RayCaster, edge_options: EdgeOptions,
    max_samples: int,
) -> VisibleWireframe:
    """`visible_wireframe` thinned to at most `max_samples` edge samples (evenly, per edge order)."""
    return thinned(visible_wireframe(wireframe, camera, pose, raycaster, edge_options), max_samples)


def thinned(vis: VisibleWireframe, max_samples: int) -> VisibleWireframe:
    """`vis` with at most `max_samples` edge samples (evenly, per edge order)."""
    n = len(vis.points)
    if n <= max_samples:
        return vis
    keep = np.unique(np.linspace(0, n - 1, max_samples).round().astype(int))
    return replace(vis, points=vis.points[keep], edge=vis.edge[keep], direction=vis.direction[keep],
                   weight=vis.weight[keep])


def frame_box(
    camera: Camera, pose: Pose, vis: VisibleWireframe, margin: float
) -> tuple[int, int, int, int] | None:
    """Pixel box `(u0, v0, u1, v1)` around the projected samples grown by `margin`, clipped to the
    frame; None when it is smaller than 16 px."""
    uv, _ = pose.project(camera, vis.points)
    uv = uv[np.isfinite(uv).all(axis=1)]
    if len(uv) == 0:
        return None
    lo = np.floor(uv.min(axis=0) - margin)
    hi = np.ceil(uv.max(axis=0) + margin) + 1
    u0, v0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
    u1, v1 = min(int(hi[0]), camera.width), min(int(hi[1]), camera.height)
    if u1 - u0 < 16 or v1 - v0 < 16:
        return None
    return u0, v0, u1, v1


def normal_equations(
    camera: Camera,
    pose: Pose,
    vis: VisibleWireframe,
    feats: ImageFeatures,
    points: np.ndarray,
    R_e: float,
    R_p: float,
    prior: Pose,
    prior_info: np.ndarray,
    options: FrameFitOptions,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One linearisation: (H `(6,6)`, g `(6,)`, edge weights, edge offsets, found, corner
    residuals `(M,2)`, corner weights `(M,)`, matched point index `(M,)`)."""
    uv, _, J = project_jacobian(camera, pose, vis.points)
    nrm = image_normals(camera, pose, vis, uv)
    off, found = edge_search(feats, uv, nrm, R_e, options)
    A = np.einsum("ni,nij->nj", nrm, J)
    # samples that do not project (behind the camera at a far-off candidate pose) observe nothing
    # (their search finds no edge; a NaN row would spoil the whole system even at weight 0)
    bad = ~np.isfinite(A).all(axis=1) | ~np.isfinite(off)
    if bad.any():
        A[bad], off, found = 0.0, np.where(bad, 0.0, off), found & ~bad
    scale = 1.4826 * float(np.median(np.abs(off[found]))) if found.any() else R_e
    c = max(options.tukey_min_px, 4.685 * scale)
    unit = options.edge_sample_weight / options.sigma_edge_px**2
    w_e = found * vis.weight * tukey(off, min(c, R_e)) * unit
    H = (A * w_e[:, None]).T @ A + prior_info
    g = A.T @ (w_e * off)
    if prior_info.any():  # a zero prior (the block's edge equations) adds nothing
        g = g - prior_info @ pose_delta(prior, pose)
    rc = np.zeros((0, 2))
    wc = np.zeros(0)
    idx = np.zeros(0, int)
    if len(vis.corner_points) and len(points):
        uv_c, _, Jc = project_jacobian(camera, pose, vis.corner_points)
        idx, ok = match_corners(uv_c, points, R_p)
        rc = points[idx] - uv_c
        dist = np.linalg.norm(rc, axis=1)
        wc = ok * tukey(dist, max(R_p, options.tukey_min_px)) / options.sigma_point_px**2
        H += np.einsum("m,mki,mkj->ij", wc, Jc, Jc)
        g += np.einsum("m,mki,mk->i", wc, Jc, rc)
    return H, g, w_e, off, found, rc, wc, idx


def edge_support(
    camera: Camera,
    wireframe: Wireframe,
    raycaster: RayCaster,
    pose: Pose,
    feats: ImageFeatures,
    edge_options: EdgeOptions,
    options: FrameFitOptions,
    null_shift_px: float = 0.0,
    visible: VisibleWireframe | None = None,
) -> tuple[float, float, np.ndarray, int] | None:
    """How well the wireframe projected with `pose` meets the frame's edges, at the final edge
    search radius: (support: class-weighted share of visible edge samples with an image edge
    within `support_px`; null support: the same share with the samples moved ±`null_shift_px`
    off their edges along the image normal, edge clutter and noise alone, 0 when
    `null_shift_px` is 0; inlier edge offsets `(N,)` px; matched edges: edges with at least half
    of their visible samples within `support_px`). None with fewer than `min_samples` visible
    samples. `visible`: the visible wireframe of `pose` when known (thinned here)."""
    if visible is None:
        v = visible_samples(wireframe, camera, pose, raycaster, edge_options, options.max_samples)
    else:
        v = thinned(visible, options.max_samples)
    if len(v.points) < options.min_samples:
        return None
    _, _, w, off, found, *_ = normal_equations(camera, pose, v, feats, np.zeros((0, 2)),
                                               options.edge_radius_min_px, options.point_radius_min_px,
                                               pose, np.zeros((6, 6)), options)
    wsum = max(float(np.sum(v.weight)), 1e-12)
    near = found & (np.abs(off) <= options.support_px)
    support = float(np.sum(v.weight * near)) / wsum
    null = 0.0
    if null_shift_px > 0:
        uv, _ = pose.project(camera, v.points)
        nrm = image_normals(camera, pose, v, uv)
        for sgn in (-1.0, 1.0):
            o2, f2 = edge_search(feats, uv + sgn * null_shift_px * nrm, nrm, options.edge_radius_min_px,
                                 options)
            null += float(np.sum(v.weight * (f2 & (np.abs(o2) <= options.support_px)))) / wsum / 2.0
    return support, null, off[w > 0], matched_edges(v.edge, near, len(wireframe.edges))


def matched_edges(edge: np.ndarray, near: np.ndarray, n_edges: int) -> int:
    """Edges with at least half of their visible samples (`edge` `(N,)` edge index per sample)
    matched (`near` `(N,)` bool)."""
    seen = np.bincount(edge, minlength=n_edges)
    hit = np.bincount(edge[near], minlength=n_edges)
    return int(np.sum((seen > 0) & (hit >= 0.5 * seen)))


@dataclass(eq=False)
class FrameEdges:
    """What a frame's edge observations need: its features around the wireframe and the visible
    samples (recomputed as the pose moves)."""

    feats: ImageFeatures
    vis: VisibleWireframe


def frame_edges(camera: Camera, wireframe: Wireframe | FrameWireframes, raycaster: RayCaster,
                frames: Sequence[int], images: Mapping[int, np.ndarray], poses: Mapping[int, Pose],
                margin: float, options: FrameFitOptions, edge_options: EdgeOptions,
                feature_options: FeatureOptions) -> dict[int, FrameEdges]:
    """Image gradients in a box `margin` px around the projected wireframe, and the visible
    samples, of every frame that sees at least `options.min_samples` of them (`wireframe`: the
    scene's, or its parts per frame). The edge searches use the gradient only: the features'
    strong-edge map (`ImageFeatures.edges`) is built on first use, so never here."""
    out = {}
    for f in frames:
        if isinstance(wireframe, FrameWireframes):
            vis = wireframe.visible(f, poses[f], raycaster, edge_options, options.max_samples)
        else:
            vis = visible_samples(wireframe, camera, poses[f], raycaster, edge_options, options.max_samples)
        if len(vis.points) < options.min_samples:
            continue
        roi = frame_box(camera, poses[f], vis, margin)
        if roi is None:
            continue
        try:
            feats = extract_features(images[f], feature_options, roi, points=False)
        except FeatureError:
            continue
        out[f] = FrameEdges(feats, vis)
    return out


def frustum_tangents(camera: Camera, margin_px: float = 0.0) -> tuple[float, float]:
    """Largest `|x/z|` and `|y/z|` (undistorted, camera frame) of a pixel inside the frame grown by
    `margin_px` on every side: the half-angle tangents of the field of view. Beyond the fold of
    the distortion model (`Camera.max_radius2`) nothing projects, which bounds both."""
    n = 64
    lo, hi_u, hi_v = -margin_px, camera.width - 1 + margin_px, camera.height - 1 + margin_px
    t = np.linspace(0.0, 1.0, n)
    u = lo + t * (hi_u - lo)
    v = lo + t * (hi_v - lo)
    border = np.concatenate([np.stack([u, np.full(n, lo)], 1), np.stack([u, np.full(n, hi_v)], 1),
                             np.stack([np.full(n, lo), v], 1), np.stack([np.full(n, hi_u), v], 1)])
    ab = camera.normalized_from_pixel(border)
    fold = float(np.sqrt(camera.max_radius2))
    if not np.all(np.isfinite(ab)):
        return fold, fold
    return min(float(np.max(np.abs(ab[:, 0]))), fold), min(float(np.max(np.abs(ab[:, 1]))), fold)


def cull_wireframe(wireframe: Wireframe, pose: Pose, tangents: tuple[float, float], margin_m: float,
                   margin_deg: float, ends: tuple[np.ndarray, np.ndarray] | None = None,
                   ) -> tuple[Wireframe, np.ndarray]:
    """The edges of `wireframe` that a camera at any pose within `margin_m` (world metres) and
    `margin_deg` (rotation angle) of `pose` may see inside the field of view of half-angle
    tangents `tangents` (`frustum_tangents`): those whose segment meets the frustum of `pose`,
    each half-angle widened for the rotation, each side plane moved `margin_m` outwards.

    Returns the part and the indices `(E',)` of its edges in `wireframe.edges`. The part keeps
    the vertices, corners and vertex offset directions of `wireframe`: its `VisibleWireframe` at
    such poses equals the whole one's, `edge` indexing the part's edges. `ends`: the edges' end
    points `(E, 3)` twice (world), when known."""
    R = pose.R_world_from_cam
    if ends is None:
        ends = (wireframe.vertices[wireframe.edges[:, 0]], wireframe.vertices[wireframe.edges[:, 1]])
    to_a, to_b = ends[0] - pose.center, ends[1] - pose.center
    # safety against rounding and the sampled border of `frustum_tangents`
    tangents = (tangents[0] * 1.02 + 1e-3, tangents[1] * 1.02 + 1e-3)
    margin_m = margin_m + 1e-6
    a, b = to_a @ R, to_b @ R
    d = np.radians(margin_deg)
    diag = np.arctan(np.hypot(*tangents))
    # directions within `d` of the frustum lie inside each side plane turned outwards by `wide`
    wide = np.arctan(np.sin(d) / max(np.cos(min(diag + d, np.pi / 2 - 1e-3)), 1e-3))
    t_lo, t_hi = np.zeros(len(a)), np.ones(len(a))
    for axis, tan in ((0, tangents[0]), (1, tangents[1])):
        half = np.arctan(tan) + wide
        if not np.isfinite(half) or half >= np.radians(89.0):
            continue
        s, c = np.sin(half), np.cos(half)
        for sign in (1.0, -1.0):
            fa = a[:, 2] * s - sign * a[:, axis] * c + margin_m  # >= 0: inside the grown plane
            fb = b[:, 2] * s - sign * b[:, axis] * c + margin_m
            df = fb - fa
            with np.errstate(divide="ignore", invalid="ignore"):
                tc = -fa / df
            rising, falling = df > 0, df < 0
            t_lo = np.where(rising, np.maximum(t_lo, tc), t_lo)
            t_hi = np.where(falling, np.minimum(t_hi, tc), t_hi)
            t_hi = np.where((df == 0) & (fa < 0), -1.0, t_hi)
    # at least one polygon of the edge may face a camera within `margin_m` (a polygon's normal
    # `(E, 2, 3)` is constant along its edge; a missing second polygon has a zero normal)
    nrm = wireframe.edge_normals
    va = -np.einsum("ekj,ej->ek", nrm, to_a)
    vb = -np.einsum("ekj,ej->ek", nrm, to_b)
    facing = np.any((np.maximum(va, vb) > -margin_m) & (np.abs(nrm).sum(axis=2) > 0), axis=1)
    keep = (t_lo <= t_hi) & facing
    sub = Wireframe(building_id=wireframe.building_id, vertices=wireframe.vertices,
                    edges=wireframe.edges[keep], edge_class=wireframe.edge_class[keep],
                    edge_weight=wireframe.edge_weight[keep], edge_normals=wireframe.edge_normals[keep],
                    corners=wireframe.corners)
    sub.__dict__["vertex_outward"] = wireframe.vertex_outward  # of all the vertex's edges
    return sub, np.flatnonzero(keep)


class FrameWireframes:
    """Per frame, the part of a scene wireframe (`cull_wireframe`) its camera may see from poses
    within `margin_m` (metres) and `margin_deg` (degrees) of the pose it was cut for, cut again
    around the pose asked for when that one strayed further, and the frame's last visible
    samples. `visible` equals `visible_samples` on the whole wireframe (the same samples in the
    same order, `edge` indexing `wireframe.edges`), at a cost that follows what the frame sees,
    not the size of the scene. `cull=False`: the whole wireframe always."""

    def __init__(self, wireframe: Wireframe, camera: Camera, margin_m: float = 2.0, margin_deg: float = 2.0,
                 cull: bool = True) -> None:
        self.wireframe = wireframe
        self.camera = camera
        self.margin_m = float(margin_m)
        self.margin_deg = float(margin_deg)
        self.cull = cull
        self._tangents: dict[float, tuple[float, float]] = {}
        self._ends = (wireframe.vertices[wireframe.edges[:, 0]], wireframe.vertices[wireframe.edges[:, 1]])
        self._parts: dict[tuple[int, float], tuple[Pose, Wireframe, np.ndarray]] = {}
        self._seen: dict[tuple[int, EdgeOptions], tuple[Pose, VisibleWireframe]] = {}

    def _part(self, frame: int, pose: Pose, edge_options: EdgeOptions) -> tuple[Wireframe, np.ndarray]:
        """The wireframe to see frame `frame` from `pose` with (its part, or the whole) and the
        indices of its edges in `wireframe.edges`, for visibility with `edge_options` (a negative
        `image_margin_px` asks for samples outside the frame: the part grows with it)."""
        if not self.cull:
            return self.wireframe, np.arange(len(self.wireframe.edges))
        px = max(-float(edge_options.image_margin_px), 0.0)
        got = self._parts.get((frame, px))
        if got is not None:
            ref, part, kept = got
            turn = so3_log(ref.R_world_from_cam.T @ pose.R_world_from_cam)
            if ref is pose or (np.linalg.norm(pose.center - ref.center) <= self.margin_m and
                               np.degrees(np.linalg.norm(turn)) <= self.margin_deg):
                return part, kept
        if px not in self._tangents:
            self._tangents[px] = frustum_tangents(self.camera, px)
        part, kept = cull_wireframe(self.wireframe, pose, self._tangents[px], self.margin_m, self.margin_deg,
                                    self._ends)
        self._parts[(frame, px)] = (pose, part, kept)
        return part, kept

    def visible(self, frame: int, pose: Pose, raycaster: RayCaster, edge_options: EdgeOptions,
                max_samples: int, reuse_px: float = 0.0) -> VisibleWireframe:
        """`visible_samples` of frame `frame` at `pose` (on its part); the frame's last visible
        wireframe again when `pose` is the pose it was computed at (the same rotation and centre),
        or moves none of its samples more than `reuse_px` pixels in the image (> 0: hidden-edge
        removal and sample spacing are kept while a fit converges)."""
        got = self._seen.get((frame, edge_options))
        if got is not None and _same_pose(got[0], pose):
            return thinned(got[1], max_samples)
        if got is not None and reuse_px > 0 and len(got[1].points):
            old = thinned(got[1], max_samples)
            uv0, _ = got[0].project(self.camera, old.points)
            uv1, _ = pose.project(self.camera, old.points)
            if np.all(np.abs(uv1 - uv0) <= reuse_px):  # NaN (behind the camera): recomputed
                return old
        part, kept = self._part(frame, pose, edge_options)
        vis = visible_wireframe(part, self.camera, pose, raycaster, edge_options)
        vis = replace(vis, edge=kept[vis.edge])
        self._seen[(frame, edge_options)] = (pose, vis)
        return thinned(vis, max_samples)


def _same_pose(a: Pose, b: Pose) -> bool:
    """True when `a` and `b` have the same rotation and centre (bit for bit)."""
    if a is b:
        return True
    return np.array_equal(a.center, b.center) and np.array_equal(a.R_world_from_cam, b.R_world_from_cam)

"""Dense point clouds of an image block by semi-global matching of consecutive frame pairs.

In: a block of frames (`load(i)`: TIR `(H, W)` float32 kelvin with NaN = no data, or RGB `(H, W,
3)` uint8), its `Camera` (OpenCV model, pixel centres at integers) and one `Pose` per frame
(`R_world_from_cam`, centre; world = model CRS, metres). Out: `DenseCloud`: points `(N, 3)`
float64 world metres and, per point, the frame whose camera carries it (the pair's first camera),
with per-pair figures and each pair's relative orientation (`x_b = R x_a + t`, metres).

Per pair (frames `a`, `b` whose centres are `min_baseline_m` … `max_baseline_m` apart, one pair
per frame at most): the relative orientation `b_from_a` from the poses, or, with
`refine_relative`, from the images (SIFT matches, essential matrix with RANSAC, cheirality) with
the baseline length of the smoothed trajectory (per-frame GNSS/INS noise of 0.2 m would distort
a 1.5 m stereo base by 20 %; the smoothed positions keep its length to a few mm) — what makes
prior poses with per-frame noise and vibration usable for stereo at all; with `prior_direction`
also the smoothed baseline's direction, and only the rotation from the images
(`rotation_given_direction`). With `smooth_positions`, each
pair's points are also placed with the smoothed centre of its camera. Then `cv2.stereoRectify`,
`cv2.StereoSGBM` on the rectified 8-bit images (TIR: stretched over its valid pixels, then CLAHE)
and triangulation with the rectification's `Q`, in camera `a`'s frame, placed in the world with
`a`'s pose. Consistency filtering: SGBM's left-right check (`disp12MaxDiff`), uniqueness and
speckle filters, the depth range, texture (RMS gradient in the block), a second partner of the
pair's first frame at a longer baseline whose depth must agree in the same pixel cell (a depth
check in one camera, free of that camera's pose error), then on the merged cloud, with
`min_views`, the support of other pairs (`views`: points of at least that many pairs within the
3 x 3 x 3 cells of `view_cell_m` about a point; a false match that both partners of a pair
confirm, a disparity off by a window period, lies where no other pair puts a point), a voxel
grid and a radius-outlier filter (a point must be supported by neighbours).

Why `min_views` (on for the TIR block, `rgb_method.TIR_BLOCK_DENSE`): on the method-3 bench (seed 1, 48
frames) the TIR cloud made with the true poses lay 0.125 m (mean) from the RGB cloud; 567 of its
97,901 points lay 20-50 m from their cameras where the true surface was 10-17 m away (false
matches, 15 m from any RGB point on average) and made 0.05 m of that mean. With two pairs
required: 74,254 points, none of them, mean 0.051 m, median 0.037 -> 0.030 m; three pairs left
23,723 points.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.signal import savgol_filter

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose


@dataclass(frozen=True)
class DenseOptions:
    """Parameters of `dense_cloud` (metres, pixels of the matched image, degrees)."""

    min_baseline_m: float = 1.0  # pair frames at least this far apart ...
    max_baseline_m: float = 3.0  # ... and at most this far
    max_width_px: int = 800  # wider images are downsampled (area) before matching
    min_depth_m: float = 5.0  # the disparity search range
    max_depth_m: float = 40.0
    max_disparities: int = 256
    block_size: int = 5
    uniqueness_ratio: int = 10
    disp12_max_diff: int = 1  # left-right consistency, pixels
    speckle_window: int = 100
    speckle_range: int = 2
    stride_px: int = 2  # keep every n-th pixel in both directions
    min_texture: float = 0.0  # RMS gradient over the block (grey levels / px) a match needs
    refine_relative: bool = True  # relative orientation of each pair from the images
    min_inliers: int = 30  # essential-matrix inliers needed to use the refined pair
    max_direction_change_deg: float = 15.0  # refined vs prior baseline direction
    max_rotation_change_deg: float = 3.0  # refined vs prior relative rotation
    prior_direction: bool = False  # keep the prior's baseline direction, refine the rotation only
    smooth_window: int = 15  # frames of the trajectory smoothing (baseline lengths)
    smooth_positions: bool = False  # place each pair's points with the smoothed camera centre
    check_baseline_factor: float = 1.7  # a second partner this much farther checks each depth (0: off)
    check_tolerance: float = 0.02  # depths of the two pairs must agree to this share
    voxel_m: float = 0.05
    outlier_radius_m: float = 0.2
    outlier_min_neighbours: int = 6
    min_views: int = 1  # a point needs points of this many pairs (first cameras) near it (1: off)
    view_cell_m: float = 0.1  # ... within the 3 x 3 x 3 cells of this size about it


@dataclass(frozen=True, eq=False)
class DenseCloud:
    """A block's dense cloud: `points` `(N, 3)` float64 world metres, `frame` `(N,)` int index
    of the camera carrying each point; `pairs` used `(a, b)`, `refined` how many of them got
    their relative orientation from the images, `points_per_pair` before the merge filters."""

    points: np.ndarray
    frame: np.ndarray
    pairs: tuple[tuple[int, int], ...]
    refined: int
    points_per_pair: tuple[int, ...]
    relative: tuple[tuple[np.ndarray, np.ndarray, bool], ...] = ()


def to_gray8(image: np.ndarray) -> np.ndarray:
    """A frame -> `(H, W)` uint8 for matching: RGB to grey; float (TIR kelvin, NaN = no data)
    stretched between its 1st and 99th percentile, then CLAHE (local contrast)."""
    a = np.asarray(image)
    if a.ndim == 3:
        return cv2.cvtColor(np.ascontiguousarray(a, dtype=np.uint8), cv2.COLOR_RGB2GRAY)
    if a.dtype == np.uint8:
        return a
    v = a[np.isfinite(a)]
    if len(v) == 0:
        return np.zeros(a.shape, np.uint8)
    lo, hi = np.percentile(v, [1, 99])
    g = np.clip((np.nan_to_num(a, nan=lo) - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)
    return cv2.createCLAHE(clipLimit=3.0, tileGridSize=(8, 8)).apply(g)


def select_pairs(centers: np.ndarray, options: DenseOptions) -> list[tuple[int, int]]:
    """Pairs `(a, b)`, `a < b`: for every frame `a` the first later frame whose centre is at least
    `min_baseline_m` away, kept if it is at most `max_baseline_m` away. `centers` `(F, 3)` m."""
    out = []
    for a in range(len(centers)):
        d = np.linalg.norm(centers[a + 1 :] - centers[a], axis=1)
        far = np.flatnonzero(d >= options.min_baseline_m)
        if len(far) and d[far[0]] <= options.max_baseline_m:
            out.append((a, a + 1 + int(far[0])))
    return out


def smoothed_centers(centers: np.ndarray, window: int) -> np.ndarray:
    """Savitzky-Golay (quadratic) smoothing of a trajectory `(F, 3)` over `window` frames."""
    n = len(centers)
    w = min(window, n if n % 2 else n - 1)
    if w < 5:
        return np.asarray(centers, dtype=np.float64)
    return savgol_filter(np.asarray(centers, dtype=np.float64), w, 2, axis=0, mode="interp")


def _relative(pa: Pose, pb: Pose) -> tuple[np.ndarray, np.ndarray]:
    """(`R_b_from_a` `(3, 3)`, `t_b_from_a` `(3,)`): `x_b = R x_a + t` in camera frames."""
    R = pb.R_world_from_cam.T @ pa.R_world_from_cam
    return R, pb.R_world_from_cam.T @ (pa.center - pb.center)


def _angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    c = float(np.dot(u, v) / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-12))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def refine_relative(
    ga: np.ndarray, gb: np.ndarray, camera: Camera, R0: np.ndarray, t0: np.ndarray, options: DenseOptions
) -> tuple[np.ndarray, np.ndarray] | None:
    """Relative orientation `b_from_a` of two 8-bit images from SIFT matches (essential matrix,
    RANSAC, cheirality): (`R` `(3, 3)`, unit `t` `(3,)`), or None when it has too few inliers or
    departs from the prior (`R0`, `t0`) by more than the options allow."""
    sift = cv2.SIFT_create(nfeatures=4000, contrastThreshold=0.01)
    ka, da = sift.detectAndCompute(ga, None)
    kb, db = sift.detectAndCompute(gb, None)
    if da is None or db is None or len(ka) < options.min_inliers or len(kb) < options.min_inliers:
        return None
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
    if len(good) < options.min_inliers:
        return None
    ua = np.float64([ka[m.queryIdx].pt for m in good])
    ub = np.float64([kb[m.trainIdx].pt for m in good])
    na = camera.normalized_from_pixel(ua)
    nb = camera.normalized_from_pixel(ub)
    thr = 1.0 / camera.fx
    E, mask = cv2.findEssentialMat(na, nb, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=thr)
    if E is None or E.shape != (3, 3):
        return None
    n_in, R, t, mask = cv2.recoverPose(E, na, nb, np.eye(3), mask=mask)
    t = t.reshape(3)
    if n_in < options.min_inliers or _angle_deg(t, t0) > options.max_direction_change_deg:
        return None
    dR = cv2.Rodrigues(R @ R0.T)[0]
    if np.degrees(np.linalg.norm(dR)) > options.max_rotation_change_deg:
        return None
    if options.prior_direction:
        keep = mask.reshape(-1) > 0
        u = t0 / np.linalg.norm(t0)
        return rotation_given_direction(na[keep], nb[keep], R, u, camera.fx), u
    return R, t


def rotation_given_direction(
    na: np.ndarray, nb: np.ndarray, R0: np.ndarray, t: np.ndarray, f_px: float
) -> np.ndarray:
    """`R_b_from_a` `(3, 3)` minimising the robust (Cauchy, 1 px) Sampson distances of matched
    normalised coordinates `na`, `nb` `(N, 2)` with the baseline direction fixed to the unit
    `t` `(3,)` (camera `b`'s frame), from `R0`: three unknowns instead of the essential matrix's
    five. On a street of facades the two-view translation direction and rotation trade off
    (a sideways baseline error looks like a turn); the smoothed trajectory's direction is known
    to about 1°, the essential matrix's rotation was measured 0.5° off on the bench's TIR pairs,
    the rotation given the direction 0.24°. What stays weak: the pan about the axis normal to
    the baseline and the viewing direction moves points along the epipolar lines; on a nearly
    fronto-parallel facade two views barely observe it, and it biases the disparities (depth
    error ≈ z² · pan / baseline): a multi-view adjustment is what fixes it."""
    from scipy.optimize import least_squares

    ha, hb = np.column_stack([na, np.ones(len(na))]), np.column_stack([nb, np.ones(len(nb))])
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])

    def rot(w: np.ndarray) -> np.ndarray:
        return cv2.Rodrigues(np.asarray(w, dtype=np.float64).reshape(3, 1))[0] @ R0

    def sampson(w: np.ndarray) -> np.ndarray:
        E = tx @ rot(w)
        ea, eb = ha @ E.T, hb @ E
        den = np.sqrt(ea[:, 0] ** 2 + ea[:, 1] ** 2 + eb[:, 0] ** 2 + eb[:, 1] ** 2)
        return np.einsum("ij,ij->i", hb, ea) / np.maximum(den, 1e-12) * f_px

    if len(na) < 3:
        return R0
    return rot(least_squares(sampson, np.zeros(3), loss="cauchy", f_scale=1.0).x)


def pair_points(
    ia: np.ndarray, ib: np.ndarray, camera: Camera, R: np.ndarray, t: np.ndarray, options: DenseOptions
) -> np.ndarray:
    """Dense points `(N, 3)` in camera `a`'s frame (metres) from 8-bit images `ia`, `ib` of
    `camera` with `x_b = R x_a + t` (`t` in metres): rectification, SGBM, triangulation, filters.
    The camera with the other one on its right (`t_x < 0`) is the left image."""
    size = (camera.width, camera.height)
    K, D = camera.K, camera.dist_coeffs
    swap = t[0] > 0  # b is left of a: match b -> a, then express the points in a's frame
    if swap:
        ia, ib, R, t = ib, ia, R.T, -R.T @ t
    zero = cv2.CALIB_ZERO_DISPARITY
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(K, D, K, D, size, R, t, flags=zero, alpha=-1)
    if abs(P2[1, 3]) > abs(P2[0, 3]):  # vertical stereo: not a pair this matcher handles
        return np.zeros((0, 3))
    m1 = cv2.initUndistortRectifyMap(K, D, R1, P1, size, cv2.CV_32FC1)
    m2 = cv2.initUndistortRectifyMap(K, D, R2, P2, size, cv2.CV_32FC1)
    ra = cv2.remap(ia, m1[0], m1[1], cv2.INTER_LINEAR, borderValue=0)
    rb = cv2.remap(ib, m2[0], m2[1], cv2.INTER_LINEAR, borderValue=0)
    f, base = P1[0, 0], float(np.linalg.norm(t))
    dmin = int(np.floor(f * base / options.max_depth_m))
    ndisp = int(np.ceil((f * base / options.min_depth_m - dmin) / 16.0)) * 16
    ndisp = max(16, min(ndisp, options.max_disparities))
    bs = options.block_size
    sgbm = cv2.StereoSGBM_create(
        minDisparity=dmin, numDisparities=ndisp, blockSize=bs, P1=8 * bs * bs, P2=32 * bs * bs,
        disp12MaxDiff=options.disp12_max_diff, uniquenessRatio=options.uniqueness_ratio,
        speckleWindowSize=options.speckle_window, speckleRange=options.speckle_range,
        mode=cv2.STEREO_SGBM_MODE_SGBM,
    )  # fmt: skip
    pad = dmin + ndisp  # SGBM leaves this many left columns unmatched: pad, match, crop
    border = cv2.BORDER_CONSTANT
    la, lb = (cv2.copyMakeBorder(x, 0, 0, pad, 0, border, value=0) for x in (ra, rb))
    disp = sgbm.compute(la, lb)[:, pad:].astype(np.float32) / 16.0
    s = options.stride_px
    valid = (disp > dmin) & (ra > 0) & (_texture(ra, bs) >= options.min_texture)
    sub = np.zeros_like(valid)
    sub[::s, ::s] = True
    valid &= sub
    X = cv2.reprojectImageTo3D(disp, Q)[valid].astype(np.float64)  # rectified frame of the left camera
    X = X[(X[:, 2] >= options.min_depth_m) & (X[:, 2] <= options.max_depth_m)]
    Xc = X @ R1  # camera frame of the left camera (R1: rectified_from_camera)
    if swap:  # the left camera was b; (R, t) now map b to a: x_a = R x_b + t
        Xc = Xc @ R.T + t
    return Xc


def _texture(image: np.ndarray, block: int) -> np.ndarray:
    """Local texture `(H, W)` float32: the RMS gradient (grey levels per pixel) over a
    `block`-sized window; matches in flatter windows are mostly noise."""
    f = image.astype(np.float32)
    gx, gy = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3) / 8, cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3) / 8
    return np.sqrt(cv2.blur(gx * gx + gy * gy, (block, block)))


def dense_cloud(
    load: Callable[[int], np.ndarray],
    camera: Camera,
    poses: Sequence[Pose],
    options: DenseOptions = DenseOptions(),
) -> DenseCloud:
    """The dense cloud of a block (see the module docstring). `load(i)` gives frame `i`,
    `poses[i]` its pose; frames are taken in index order (recording order)."""
    scale = min(1.0, options.max_width_px / camera.width)
    cam = camera.scaled(scale) if scale < 1.0 else camera
    centers = np.array([p.center for p in poses], dtype=np.float64)
    smooth = smoothed_centers(centers, options.smooth_window)
    pairs = select_pairs(smooth, options)
    gray: dict[int, np.ndarray] = {}

    def g(i: int) -> np.ndarray:
        if i not in gray:
            img = to_gray8(load(i))
            small = (cam.width, cam.height)
            gray[i] = img if scale >= 1.0 else cv2.resize(img, small, interpolation=cv2.INTER_AREA)
        return gray[i]

    if options.smooth_positions:
        poses = anchored_poses(poses, smooth)
    pts, owner, counts, refined, rel = [], [], [], 0, []
    for a, b in pairs:
        Xa, ok, R_ab, t_ab = _points(g, cam, poses, smooth, a, b, options)
        refined += ok
        rel.append((R_ab, t_ab, ok))
        if options.check_baseline_factor > 0:  # unchecked pairs (no second partner) are dropped
            c = _check_partner(smooth, a, b, options)
            Xc = _points(g, cam, poses, smooth, a, c, options)[0] if c is not None and len(Xa) else Xa[:0]
            Xa = consistent(Xa, Xc, cam, options.stride_px, options.check_tolerance)
        counts.append(len(Xa))
        pts.append(poses[a].world_from_cam(Xa))
        owner.append(np.full(len(Xa), a, np.int32))
        for k in [k for k in gray if k < a]:
            del gray[k]
    if not pts:
        return DenseCloud(np.zeros((0, 3)), np.zeros(0, np.int32), (), 0, ())
    P, F = _filtered(np.concatenate(pts), np.concatenate(owner), options)
    return DenseCloud(P, F, tuple(pairs), refined, tuple(counts), tuple(rel))


def anchored_poses(poses: Sequence[Pose], centers: np.ndarray) -> list[Pose]:
    """`poses` with their centres replaced by `centers` `(F, 3)` (e.g. the smoothed trajectory)."""
    return [Pose(p.R_world_from_cam, c) for p, c in zip(poses, centers, strict=True)]


def _points(
    g: Callable[[int], np.ndarray], cam: Camera, poses: Sequence[Pose], smooth: np.ndarray,
    a: int, b: int, options: DenseOptions,
) -> tuple[np.ndarray, bool, np.ndarray, np.ndarray]:  # fmt: skip
    """Points `(N, 3)` of pair `(a, b)` in camera `a`'s frame, whether the relative
    orientation came from the images (else from the poses), and that orientation (`R`, `t` m)."""
    R, t = _relative(poses[a], poses[b])
    ok = False
    if options.refine_relative:
        rel = refine_relative(g(a), g(b), cam, R, t, options)
        if rel is not None:
            R, t, ok = rel[0], rel[1] * float(np.linalg.norm(smooth[b] - smooth[a])), True
    return pair_points(g(a), g(b), cam, R, t, options), ok, R, t


def _check_partner(smooth: np.ndarray, a: int, b: int, options: DenseOptions) -> int | None:
    """The frame after `b` whose centre is `check_baseline_factor` times as far from `a` as
    `b`'s (within `max_baseline_m` × the factor), or None."""
    if options.check_baseline_factor <= 0:
        return None
    base = np.linalg.norm(smooth[b] - smooth[a])
    d = np.linalg.norm(smooth[b + 1 :] - smooth[a], axis=1)
    far = np.flatnonzero(d >= options.check_baseline_factor * base)
    if len(far) and d[far[0]] <= options.check_baseline_factor * options.max_baseline_m:
        return b + 1 + int(far[0])
    return None


def consistent(X: np.ndarray, Y: np.ndarray, camera: Camera, cell_px: int, tolerance: float) -> np.ndarray:
    """The points of `X` `(N, 3)` (camera frame, metres) whose depth agrees within `tolerance`
    (a share of the depth) with the depth of `Y` `(M, 3)` (same camera) in the same
    `cell_px`-sized pixel cell, each moved to the mean of the two depths along its ray."""
    if len(X) == 0 or len(Y) == 0:
        return X[:0]
    w, h = camera.width // cell_px + 1, camera.height // cell_px + 1

    def cells(P: np.ndarray) -> np.ndarray:
        uv = camera.project(P)
        ok = np.all(np.isfinite(uv), axis=1) & camera.in_image(uv)
        k = np.full(len(P), -1, np.int64)
        iu = np.rint(uv[ok] / cell_px).astype(np.int64)
        k[ok] = np.clip(iu[:, 1], 0, h - 1) * w + np.clip(iu[:, 0], 0, w - 1)
        return k

    depth = np.full(w * h, np.nan)
    ky = cells(Y)
    depth[ky[ky >= 0]] = Y[ky >= 0, 2]
    kx = cells(X)
    zy = np.where(kx >= 0, depth[np.maximum(kx, 0)], np.nan)
    keep = np.abs(zy - X[:, 2]) <= tolerance * X[:, 2]  # NaN compares False
    return X[keep] * (0.5 * (1.0 + zy[keep] / X[keep, 2]))[:, None]


def _filtered(points: np.ndarray, frame: np.ndarray, options: DenseOptions) -> tuple[np.ndarray, np.ndarray]:
    """Voxel grid (first point per voxel) and radius-outlier filter (Open3D) of `(N, 3)` world
    points (computed about their mean for precision) with their frames `(N,)`."""
    import open3d as o3d

    if len(points) == 0:
        return points, frame
    o = points.mean(axis=0)
    if options.min_views > 1:
        keep = views(points - o, frame, options.view_cell_m) >= options.min_views
        points, frame = points[keep], frame[keep]
    key = np.floor((points - o) / options.voxel_m).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    P, F = points[first], frame[first]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P - o))
    _, keep = pc.remove_radius_outlier(options.outlier_min_neighbours, options.outlier_radius_m)
    keep = np.asarray(keep, dtype=np.int64)
    return P[keep], F[keep]


def views(points: np.ndarray, frame: np.ndarray, cell_m: float) -> np.ndarray:
    """Per point of `points` `(N, 3)` (metres, near the origin) the number of distinct pairs
    (`frame` `(N,)`: the pair's first camera) with a point in the 3 x 3 x 3 cells of `cell_m`
    about the point's own cell: a surface point seen by several stereo pairs is reconstructed
    by several of them, a false match (a disparity off by a window period, a mismatch at an
    occluding edge) lies where no other pair puts one.

    >>> p = np.array([[0.0, 0, 0], [0.05, 0, 0], [0.02, 0, 0], [5.0, 0, 0]])
    >>> views(p, np.array([0, 1, 1, 2]), 0.1).tolist()
    [2, 2, 2, 1]
    """
    if len(points) == 0:
        return np.zeros(0, np.int64)
    c = np.floor(points / cell_m).astype(np.int64)
    c -= c.min(axis=0) - 1  # every cell and its neighbours non-negative
    dims = c.max(axis=0) + 2
    f = np.unique(frame, return_inverse=True)[1].astype(np.int64)
    n_f = int(f.max()) + 1
    cell = (c[:, 0] * dims[1] + c[:, 1]) * dims[2] + c[:, 2]
    own = np.unique(cell * n_f + f)  # (cell, pair) present
    oc, of = own // n_f, own % n_f
    k3 = (-1, 0, 1)
    off = np.array([(a * dims[1] + b) * dims[2] + d for a in k3 for b in k3 for d in k3])
    spread = np.unique(((oc[:, None] + off[None, :]) * n_f + of[:, None]).ravel())
    cells, count = np.unique(spread // n_f, return_counts=True)
    k = np.searchsorted(cells, cell)
    return count[np.minimum(k, len(cells) - 1)] * (cells[np.minimum(k, len(cells) - 1)] == cell)

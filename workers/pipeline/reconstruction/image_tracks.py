"""Feature tracks through a frame sequence from the images alone (no building model).

In: frames in recording order (`load(i)`: TIR `(H, W)` float32 kelvin with NaN = no data, or RGB
`(H, W, 3)` uint8), their `Camera` (pixel centres at integers) and a pose per frame (world,
metres: the GNSS/INS priors, only to choose which frames to match). Out: `Tracks` (observations
`(track, frame, uv)`; points zero and normals zero: no model plane), ready for triangulation and a
bundle adjustment (`colmap.triangulate`, `orientation.bundle.bundle_adjust`).

Why: the stereo pairs of method 3 (`dense_stereo`) need relative orientations consistent along the
sequence; two-view relative orientations on a street of facades trade the baseline direction
against the rotation (0.24-0.52° off on the bench's TIR pairs, which bends the dense clouds by
decimetres). Points tracked over many frames tie every frame to its neighbours at once; the
tracker of the sequence orientation (`orientation.tracks`) needs the model's surfaces, this one
does not (method 3 works where there is no model).

Steps: SIFT keypoints on the 8-bit matching copy (`dense_stereo.to_gray8`: stretched, CLAHE);
every frame matched with the next frames whose centres lie within `max_baseline_m` (at most
`max_partners`), Lowe's ratio test and mutual best matches (with `epipolar_band_px`, among the
keypoints near the epipolar line from the given poses only), then the essential matrix (RANSAC,
`ransac_px`) of each pair keeps its inliers; the verified matches are joined into tracks
(union-find over keypoints) and tracks that claim two keypoints in one frame are dropped.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.orientation.tracks import Tracks
from workers.pipeline.reconstruction.dense_stereo import to_gray8


@dataclass(frozen=True)
class ImageTrackOptions:
    """Parameters of `image_tracks` (pixels, metres)."""

    n_features: int = 3000  # SIFT keypoints per frame at most
    contrast_threshold: float = 0.01  # SIFT's (TIR after CLAHE is low in contrast)
    ratio: float = 0.8  # Lowe's ratio test
    max_partners: int = 6  # each frame matched with at most this many later frames ...
    max_baseline_m: float = 6.0  # ... whose centres lie within this distance
    ransac_px: float = 1.0  # essential-matrix RANSAC threshold
    min_inliers: int = 20  # a pair with fewer verified matches adds none
    min_length: int = 3  # tracks observed in fewer frames are dropped
    # guided matching: a keypoint's candidates lie within this distance of its epipolar line
    # from the given poses (None: every keypoint of the other frame; see `verified_matches`)
    epipolar_band_px: float | None = None


def image_tracks(
    load: Callable[[int], np.ndarray],
    camera: Camera,
    poses: Sequence[Pose],
    options: ImageTrackOptions = ImageTrackOptions(),
) -> Tracks:
    """Tracks of frames `0 … F-1` (see the module docstring); `poses[i]` frame `i`'s pose."""
    sift = cv2.SIFT_create(nfeatures=options.n_features, contrastThreshold=options.contrast_threshold)
    kps: list[np.ndarray] = []
    descs: list[np.ndarray] = []
    for i in range(len(poses)):
        k, d = sift.detectAndCompute(to_gray8(load(i)), None)
        kps.append(np.float64([p.pt for p in k]).reshape(-1, 2))
        descs.append(np.zeros((0, 128), np.float32) if d is None else d)
    offset = np.cumsum([0] + [len(k) for k in kps])
    parent = np.arange(offset[-1])
    centers = np.array([p.center for p in poses], dtype=np.float64)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    for a in range(len(poses)):
        for b in _partners(centers, a, options):
            band = None
            if options.epipolar_band_px is not None:
                band = epipolar_band(kps[a], kps[b], camera, poses[a], poses[b], options.epipolar_band_px)
            ia, ib = verified_matches(kps[a], descs[a], kps[b], descs[b], camera, matcher, options, band)
            for x, y in zip(ia + offset[a], ib + offset[b], strict=True):
                _union(parent, int(x), int(y))
    return _tracks(parent, kps, offset, options.min_length)


def _partners(centers: np.ndarray, a: int, options: ImageTrackOptions) -> list[int]:
    """The later frames `a` is matched with (centres within `max_baseline_m`, the nearest
    `max_partners` in recording order)."""
    d = np.linalg.norm(centers[a + 1 :] - centers[a], axis=1)
    near = np.flatnonzero(d <= options.max_baseline_m)[: options.max_partners]
    return [a + 1 + int(k) for k in near]


def verified_matches(
    ka: np.ndarray, da: np.ndarray, kb: np.ndarray, db: np.ndarray, camera: Camera,
    matcher: cv2.BFMatcher, options: ImageTrackOptions, band: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Indices `(K,)`, `(K,)` of keypoints `ka` `(Na, 2)`, `kb` `(Nb, 2)` (pixels) that match
    (ratio test, mutual best) and agree with the pair's essential matrix (RANSAC). With `band`
    `(Na, Nb)` bool (`epipolar_band`) a keypoint's candidates, for the best match and for the
    ratio test's second best, are those of its band only: a window repeated up the facade is no
    rival of the true match, so the ratio test keeps matches it drops among all keypoints."""
    none = np.zeros(0, np.int64), np.zeros(0, np.int64)
    if len(da) < options.min_inliers or len(db) < options.min_inliers:
        return none
    if band is None:
        fwd = matcher.knnMatch(da, db, k=2)
        back = {m[0].queryIdx: m[0].trainIdx for m in matcher.knnMatch(db, da, k=1) if m}
        good = [m[0] for m in fwd if len(m) == 2 and m[0].distance < options.ratio * m[1].distance]
        pairs = [(m.queryIdx, m.trainIdx) for m in good if back.get(m.trainIdx) == m.queryIdx]
        ia, ib = none
        if pairs:
            ia, ib = (np.array(c, dtype=np.int64) for c in zip(*pairs, strict=True))
    else:
        ia, ib = _banded_matches(da, db, band, options.ratio)
    if len(ia) < options.min_inliers:
        return none
    na, nb = camera.normalized_from_pixel(ka[ia]), camera.normalized_from_pixel(kb[ib])
    thr = options.ransac_px / camera.fx
    E, mask = cv2.findEssentialMat(na, nb, np.eye(3), method=cv2.RANSAC, prob=0.999, threshold=thr)
    if E is None or E.shape != (3, 3):
        return none
    keep = mask.reshape(-1) > 0
    if np.count_nonzero(keep) < options.min_inliers:
        return none
    return ia[keep], ib[keep]


def epipolar_band(
    ka: np.ndarray, kb: np.ndarray, camera: Camera, pa: Pose, pb: Pose, band_px: float
) -> np.ndarray:
    """`(Na, Nb)` bool: keypoint `kb[j]` (pixels) lies within `band_px` of the epipolar line of
    `ka[i]` from the poses `pa`, `pb` (world) — the distance measured in normalised coordinates
    times the focal length."""
    R = pb.R_world_from_cam.T @ pa.R_world_from_cam  # cam_b from cam_a
    t = pb.R_world_from_cam.T @ (pa.center - pb.center)
    E = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]]) @ R
    na = np.column_stack([camera.normalized_from_pixel(ka), np.ones(len(ka))])
    nb = np.column_stack([camera.normalized_from_pixel(kb), np.ones(len(kb))])
    lines = na @ E.T  # (Na, 3): line of each a-keypoint in b's normalised plane
    lines /= np.maximum(np.linalg.norm(lines[:, :2], axis=1, keepdims=True), 1e-12)
    return np.abs(lines @ nb.T) * camera.fx <= band_px


def _banded_matches(
    da: np.ndarray, db: np.ndarray, band: np.ndarray, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual best matches of descriptors `da` `(Na, D)`, `db` `(Nb, D)` among the pairs `band`
    `(Na, Nb)` allows, passing the ratio test against the second best in the band (a single
    candidate passes). Returns keypoint indices `(K,)`, `(K,)`."""
    a = da.astype(np.float32)
    b = db.astype(np.float32)
    d2 = np.sum(a**2, axis=1)[:, None] + np.sum(b**2, axis=1)[None, :] - 2.0 * (a @ b.T)
    d = np.sqrt(np.maximum(d2, 0.0))
    d[~band] = np.inf
    best = np.argmin(d, axis=1)
    rows = np.arange(len(d))
    first = d[rows, best]
    d_second = d.copy()
    d_second[rows, best] = np.inf
    second = np.min(d_second, axis=1) if d.shape[1] > 1 else np.full(len(d), np.inf)
    mutual = np.argmin(d, axis=0)[best] == rows
    ok = np.isfinite(first) & (first < ratio * second) & mutual
    return rows[ok].astype(np.int64), best[ok].astype(np.int64)


def _union(parent: np.ndarray, x: int, y: int) -> None:
    rx, ry = _root(parent, x), _root(parent, y)
    if rx != ry:
        parent[max(rx, ry)] = min(rx, ry)


def _root(parent: np.ndarray, x: int) -> int:
    while parent[x] != x:
        parent[x] = parent[parent[x]]
        x = int(parent[x])
    return x


def _tracks(parent: np.ndarray, kps: list[np.ndarray], offset: np.ndarray, min_length: int) -> Tracks:
    """The union-find's sets of keypoints as `Tracks`: sets with one keypoint per frame and at
    least `min_length` frames."""
    roots = np.array([_root(parent, i) for i in range(len(parent))], dtype=np.int64)
    frame = np.repeat(np.arange(len(kps)), [len(k) for k in kps])
    uv = np.concatenate(kps) if kps else np.zeros((0, 2))
    _, tid, size = np.unique(roots, return_inverse=True, return_counts=True)
    per_frame = np.unique(np.column_stack([tid, frame]), axis=0)
    frames_of = np.bincount(per_frame[:, 0], minlength=len(size))
    good = (size == frames_of) & (size >= min_length)  # one keypoint per frame
    m = good[tid]
    new_id = np.cumsum(good) - 1
    n = int(good.sum())
    z = np.zeros((n, 3))
    return Tracks(new_id[tid[m]], frame[m], uv[m], z, z.copy(), np.zeros(n))

"""Image side of model-to-image coregistration: features of one TIR frame.

In: a frame as float32 physical values `(H, W)` (kelvin or counts), optionally a region of
interest. Out: an `ImageFeatures` holding, in full-frame pixel coordinates (pixel centres at
integers, `u` right, `v` down):

- Förstner interest points (structure tensor; roundness `q` and weight `w` thresholds; sub-pixel
  position as the least-squares intersection of the gradient-normal lines in the window),
- LSD line segments (`cv2.createLineSegmentDetector`) and the intersection points of segment
  pairs (angle and length thresholds, as in Avbelj et al. 2012), sub-pixel by construction,
- the gradient `(gx, gy)` of the smoothed, contrast-normalised image (for edge searches along
  projected model edges) and a pyramid of truncated distance transforms of a strong-edge map
  (for the correspondence-free coarse search).

Physical values are kept as float32; contrast normalisation (a percentile stretch to 0..1) is
used for detection only. Nothing here knows the model.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np


class FeatureError(ValueError):
    """Invalid input to feature extraction (wrong image shape or type, empty ROI)."""


@dataclass(frozen=True)
class FeatureOptions:
    """Parameters of the image-side feature extraction (pixels unless stated)."""

    # contrast normalisation: percentiles of the ROI mapped to 0 and 1 (detection only)
    stretch_percentiles: tuple[float, float] = (0.5, 99.5)
    # Gaussian pre-smoothing sigma before derivatives (TIR is blurred and noisy)
    smooth_sigma: float = 1.0
    # Förstner: integration window (Gaussian sigma) of the structure tensor
    forstner_window_sigma: float = 1.5
    # Förstner: minimum roundness q = 4 det / trace² (0..1; 1 = isotropic)
    forstner_q_min: float = 0.5
    # Förstner: w = det / trace must exceed this factor × mean positive w of the ROI ...
    forstner_w_factor: float = 1.5
    # ... and this absolute floor (normalised-intensity units² per pixel²)
    forstner_w_min: float = 2e-4
    # Förstner: non-maximum suppression radius of w
    forstner_nms_radius: int = 3
    # Förstner: keep at most this many points (strongest w first)
    forstner_max_points: int = 300
    # LSD: minimum segment length
    segment_min_length: float = 8.0
    # LSD: keep at most this many segments (longest first) for the pairwise intersections
    segment_max_count: int = 150
    # intersections: minimum angle between the two segments, degrees
    intersection_min_angle_deg: float = 30.0
    # intersections: the point may lie at most this far beyond either segment's end point
    # (absolute px plus a share of the segment length)
    intersection_max_gap: float = 3.0
    intersection_max_gap_rel: float = 0.15
    # intersections: at most this many (those of the longest segment pairs)
    intersection_max_count: int = 400
    # robust gradient scale of the ROI: this percentile of the gradient magnitude (the strongest
    # edges, building outlines against the sky, cover a few per cent of the ROI at most)
    gradient_ref_percentile: float = 99.7
    # strong-edge map: Canny thresholds as shares of the gradient scale (keeps building outlines,
    # drops the weaker window and texture edges)
    edge_low_rel: float = 0.2
    edge_high_rel: float = 0.45
    # distance transforms are truncated at this many pixels of their own level
    dt_truncate: float = 12.0
    # pyramid levels (downsampling factors) of the distance transform
    dt_levels: tuple[int, ...] = (4,)
    # percentiles are estimated on every n-th pixel in both directions (speed)
    percentile_stride: int = 3


@dataclass(frozen=True, eq=False)
class ImageFeatures:
    """Features of one frame (all coordinates in full-frame pixels).

    Attributes:
        forstner: `(N, 2)` float64 Förstner points.
        forstner_w: `(N,)` their weight w (normalised units).
        segments: `(M, 4)` float64 LSD segments `u0, v0, u1, v1`.
        intersections: `(K, 2)` float64 intersection points of segment pairs.
        roi: `(u0, v0, u1, v1)` integer pixel box (exclusive end) the features were computed in.
        gx, gy: `(h, w)` float32 gradient of the smoothed normalised image over the ROI
            (per pixel; index `[v - v0, u - u0]`).
        grad_ref: robust gradient scale of the ROI (a high percentile of the magnitude), for thresholds.
        dt: level -> `(h_l, w_l)` float32 distance (in level pixels, truncated) to the nearest
            strong edge; level pixel `(i, j)` covers full-frame pixel `(u0 + s j + (s-1)/2, ...)`.
        edges: `(h, w)` uint8 strong-edge map of the ROI (255 = edge).
        norm: `(h, w)` float32 contrast-normalised ROI (0..1).
    """

    forstner: np.ndarray
    forstner_w: np.ndarray
    segments: np.ndarray
    intersections: np.ndarray
    roi: tuple[int, int, int, int]
    gx: np.ndarray
    gy: np.ndarray
    grad_ref: float
    dt: dict[int, np.ndarray]
    edges: np.ndarray
    norm: np.ndarray

    @property
    def grad(self) -> np.ndarray:
        """`(h, w, 2)` float32 gradient `(gx, gy)` stacked (built once, for `cv2.remap`)."""
        g = self.__dict__.get("_grad")
        if g is None:
            g = np.dstack([self.gx, self.gy])
            object.__setattr__(self, "_grad", g)
        return g

    @property
    def points(self) -> np.ndarray:
        """All interest points `(N + K, 2)`: Förstner points, then segment intersections."""
        return np.concatenate([self.forstner, self.intersections], axis=0)


def normalize_contrast(
    image: np.ndarray, percentiles: tuple[float, float] = (0.5, 99.5), stride: int = 1
) -> np.ndarray:
    """Percentile stretch of a float image `(H, W)` to float32 0..1 (clipped; NaN -> 0); the
    percentiles are taken on every `stride`-th pixel.

    >>> normalize_contrast(np.array([[0.0, 1.0], [2.0, 4.0]]), (0, 100)).tolist()
    [[0.0, 0.25], [0.5, 1.0]]
    """
    img = np.asarray(image, dtype=np.float32)
    sample = img[::stride, ::stride]
    sample = sample[np.isfinite(sample)]
    if sample.size == 0:
        return np.zeros(img.shape, np.float32)
    finite = np.isfinite(img)
    lo, hi = np.percentile(sample, percentiles)
    span = float(hi - lo) if hi > lo else 1.0
    out = (np.where(finite, img, lo) - np.float32(lo)) / np.float32(span)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def _gauss(img: np.ndarray, sigma: float) -> np.ndarray:
    if sigma <= 0:
        return img
    return cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)


def gradients(norm: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed image `(H, W)` float32 -> `(gx, gy)` per-pixel central-difference gradients."""
    s = _gauss(norm, sigma)
    gx = cv2.Sobel(s, cv2.CV_32F, 1, 0, ksize=3, scale=0.125, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Sobel(s, cv2.CV_32F, 0, 1, ksize=3, scale=0.125, borderType=cv2.BORDER_REFLECT)
    return gx, gy


def forstner_points(
    gx: np.ndarray, gy: np.ndarray, options: FeatureOptions = FeatureOptions()
) -> tuple[np.ndarray, np.ndarray]:
    """Förstner operator on gradients `(H, W)` -> (points `(N, 2)` u, v in ROI pixels, weights w `(N,)`).

    Structure tensor `N = G * [gx², gxgy; gxgy, gy²]`; `w = det N / tr N`, `q = 4 det N / tr² N`.
    Candidates: local maxima of w with `q ≥ q_min` and `w` above the thresholds; position
    `x = x0 + N⁻¹ Σ G(k) (∇g ∇gᵀ)(x0 + k) k` (intersection of the lines through each window pixel
    perpendicular to its gradient; exact for an ideal corner).
    """
    sig = options.forstner_window_sigma
    r = int(np.ceil(3 * sig))
    k1 = np.arange(-r, r + 1, dtype=np.float32)
    g1 = np.exp(-0.5 * (k1 / sig) ** 2).astype(np.float32)
    g1 /= g1.sum()
    gxx, gxy, gyy = gx * gx, gx * gy, gy * gy
    border = cv2.BORDER_REFLECT
    A = cv2.sepFilter2D(gxx, cv2.CV_32F, g1, g1, borderType=border)
    B = cv2.sepFilter2D(gxy, cv2.CV_32F, g1, g1, borderType=border)
    C = cv2.sepFilter2D(gyy, cv2.CV_32F, g1, g1, borderType=border)
    det = A * C - B * B
    tr = A + C
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(tr > 1e-12, det / tr, 0.0).astype(np.float32)
        q = np.where(tr > 1e-12, 4.0 * det / (tr * tr), 0.0)
    pos = w[w > 0]
    if pos.size == 0:
        return np.zeros((0, 2)), np.zeros(0)
    w_thr = max(options.forstner_w_factor * float(pos.mean()), options.forstner_w_min)
    nms = options.forstner_nms_radius
    dil = cv2.dilate(w, cv2.getStructuringElement(cv2.MORPH_RECT, (2 * nms + 1, 2 * nms + 1)))
    cand = (w >= dil) & (w > w_thr) & (q >= options.forstner_q_min)
    cand[:r, :] = cand[-r:, :] = False
    cand[:, :r] = cand[:, -r:] = False
    vs, us = np.nonzero(cand)
    if len(vs) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    order = np.argsort(-w[vs, us])[: options.forstner_max_points]
    vs, us = vs[order], us[order]
    # b = Σ G(k) M(x0+k) k, via correlation with kernels G·kx and G·ky (separable)
    gk = (g1 * k1).astype(np.float32)
    patch_sum = np.zeros((len(vs), 2))
    for img, col in ((gxx, 0), (gxy, 1)):  # first row of M·k: gxx kx + gxy ky
        fx = cv2.sepFilter2D(img, cv2.CV_32F, gk, g1, borderType=border)
        fy = cv2.sepFilter2D(img, cv2.CV_32F, g1, gk, borderType=border)
        patch_sum[:, 0] += (fx if col == 0 else fy)[vs, us]
    for img, col in ((gxy, 0), (gyy, 1)):  # second row: gxy kx + gyy ky
        fx = cv2.sepFilter2D(img, cv2.CV_32F, gk, g1, borderType=border)
        fy = cv2.sepFilter2D(img, cv2.CV_32F, g1, gk, borderType=border)
        patch_sum[:, 1] += (fx if col == 0 else fy)[vs, us]
    a, b, c = A[vs, us].astype(np.float64), B[vs, us].astype(np.float64), C[vs, us].astype(np.float64)
    d = a * c - b * b
    du = (c * patch_sum[:, 0] - b * patch_sum[:, 1]) / d
    dv = (-b * patch_sum[:, 0] + a * patch_sum[:, 1]) / d
    ok = np.isfinite(du) & np.isfinite(dv) & (np.abs(du) <= 1.5) & (np.abs(dv) <= 1.5)
    pts = np.stack([us + du, vs + dv], axis=1)[ok]
    return pts, w[vs, us][ok].astype(np.float64)


_LSD = None


def line_segments(norm: np.ndarray, options: FeatureOptions = FeatureOptions()) -> np.ndarray:
    """LSD segments of a normalised image `(H, W)` 0..1 -> `(M, 4)` `u0, v0, u1, v1` (ROI pixels).

    Segments shorter than `segment_min_length` are dropped; at most `segment_max_count` (longest).
    """
    global _LSD
    if _LSD is None:
        _LSD = cv2.createLineSegmentDetector()
    img8 = np.clip(norm * 255.0 + 0.5, 0, 255).astype(np.uint8)
    lines = _LSD.detect(img8)[0]
    if lines is None:
        return np.zeros((0, 4))
    seg = lines.reshape(-1, 4).astype(np.float64)
    length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    keep = length >= options.segment_min_length
    seg, length = seg[keep], length[keep]
    order = np.argsort(-length)[: options.segment_max_count]
    # LSD's coordinates already follow the pixel-centre convention (checked on an antialiased box)
    return seg[order]


def segment_intersections(segments: np.ndarray, options: FeatureOptions = FeatureOptions()) -> np.ndarray:
    """Intersection points `(K, 2)` of all segment pairs `(M, 4)` meeting the angle and gap thresholds.

    A pair qualifies when the angle between the lines is at least `intersection_min_angle_deg` and
    the intersection lies within each segment extended by `max_gap + max_gap_rel × length` at
    both ends (corners where two edges end, T- and X-junctions).
    """
    m = len(segments)
    if m < 2:
        return np.zeros((0, 2))
    p = segments[:, :2]
    d = segments[:, 2:] - p
    length = np.linalg.norm(d, axis=1)
    t_hat = d / length[:, None]
    i, j = np.triu_indices(m, k=1)
    cross = t_hat[i, 0] * t_hat[j, 1] - t_hat[i, 1] * t_hat[j, 0]
    ok = np.abs(cross) >= np.sin(np.radians(options.intersection_min_angle_deg))
    i, j, cross = i[ok], j[ok], cross[ok]
    w = p[j] - p[i]
    # p_i + s d_i = p_j + r d_j, in units of the segment lengths (s, r in 0..1 on the segments)
    denom = d[i, 0] * d[j, 1] - d[i, 1] * d[j, 0]
    s = (w[:, 0] * d[j, 1] - w[:, 1] * d[j, 0]) / denom
    r = (w[:, 0] * d[i, 1] - w[:, 1] * d[i, 0]) / denom
    gap_i = (options.intersection_max_gap + options.intersection_max_gap_rel * length[i]) / length[i]
    gap_j = (options.intersection_max_gap + options.intersection_max_gap_rel * length[j]) / length[j]
    ok = (s >= -gap_i) & (s <= 1 + gap_i) & (r >= -gap_j) & (r <= 1 + gap_j)
    i, j, s = i[ok], j[ok], s[ok]
    if len(i) > options.intersection_max_count:  # keep the pairs of the longest segments
        order = np.argsort(-np.minimum(length[i], length[j]), kind="stable")[: options.intersection_max_count]
        i, s = i[order], s[order]
    return p[i] + s[:, None] * d[i]


def _distance_pyramid(edges: np.ndarray, options: FeatureOptions) -> dict[int, np.ndarray]:
    """Strong-edge map `(h, w)` uint8 -> level -> truncated distance transform (level pixels)."""
    out: dict[int, np.ndarray] = {}
    h, w = edges.shape
    for lev in options.dt_levels:
        if lev == 1:
            e = edges
        else:
            hh, ww = max(h // lev, 1), max(w // lev, 1)
            e = cv2.resize(edges[: hh * lev, : ww * lev], (ww, hh), interpolation=cv2.INTER_AREA)
        if not e.any():
            out[lev] = np.full(e.shape, options.dt_truncate, np.float32)
            continue
        dt = cv2.distanceTransform(np.where(e > 0, 0, 255).astype(np.uint8), cv2.DIST_L2, 3)
        out[lev] = np.minimum(dt, options.dt_truncate).astype(np.float32)
    return out


def extract_features(
    image: np.ndarray,
    options: FeatureOptions = FeatureOptions(),
    roi: tuple[int, int, int, int] | None = None,
    points: bool = True,
    strong_edges: bool = True,
) -> ImageFeatures:
    """All features of a frame `(H, W)` float32 physical values within `roi` `(u0, v0, u1, v1)`.

    The ROI is clipped to the frame; contrast normalisation uses the ROI's own percentiles.
    Returned coordinates are full-frame pixels. With `points=False` the point features (Förstner,
    LSD, intersections) are left empty; `with_points` adds them later for a smaller box. With
    `strong_edges=False` the strong-edge map and its distance transforms (the coarse search's) are
    left empty (`edges` `(0, 0)`, `dt` `{}`): the edge searches along projected model edges need
    the gradient only (`edge_observations.frame_edges`; a tenth of a bundle window's features).
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise FeatureError(f"frame must be a 2-D array (H, W), got shape {img.shape}")
    H, W = img.shape
    u0, v0, u1, v1 = roi if roi is not None else (0, 0, W, H)
    u0, v0 = max(int(u0), 0), max(int(v0), 0)
    u1, v1 = min(int(u1), W), min(int(v1), H)
    if u1 - u0 < 8 or v1 - v0 < 8:
        raise FeatureError(f"region of interest {roi} is empty or smaller than 8x8 pixels inside {W}x{H}")
    sub = img[v0:v1, u0:u1].astype(np.float32, copy=False)
    norm = normalize_contrast(sub, options.stretch_percentiles, options.percentile_stride)
    gx, gy = gradients(norm, options.smooth_sigma)
    st = options.percentile_stride
    mag = np.hypot(gx[::st, ::st], gy[::st, ::st])
    grad_ref = float(np.percentile(mag, options.gradient_ref_percentile)) or 1e-6
    empty = np.zeros((0, 2))
    if not strong_edges:
        return ImageFeatures(forstner=empty, forstner_w=np.zeros(0), segments=np.zeros((0, 4)),
                             intersections=empty, roi=(u0, v0, u1, v1), gx=gx, gy=gy, grad_ref=grad_ref,
                             dt={}, edges=np.zeros((0, 0), np.uint8), norm=norm)
    # strong-edge map: Canny on the 8-bit smoothed image, thresholds relative to the ROI contrast
    img8 = np.clip(_gauss(norm, options.smooth_sigma) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    sobel_ref = grad_ref * 255.0 * 8.0  # Canny's Sobel aperture-3 magnitude of the same step
    edges = cv2.Canny(
        img8, options.edge_low_rel * sobel_ref, options.edge_high_rel * sobel_ref, L2gradient=True
    )
    feats = ImageFeatures(
        forstner=empty,
        forstner_w=np.zeros(0),
        segments=np.zeros((0, 4)),
        intersections=empty,
        roi=(u0, v0, u1, v1),
        gx=gx,
        gy=gy,
        grad_ref=grad_ref,
        dt=_distance_pyramid(edges, options),
        edges=edges,
        norm=norm,
    )
    return with_points(feats, feats.roi, options) if points else feats


def with_points(
    feats: ImageFeatures, box: tuple[int, int, int, int], options: FeatureOptions = FeatureOptions()
) -> ImageFeatures:
    """`feats` with Förstner points, LSD segments and their intersections detected inside `box`
    `(u0, v0, u1, v1)` (full-frame pixels, clipped to the features' ROI)."""
    r0, r1 = feats.roi[:2], feats.roi[2:]
    u0, v0 = max(int(box[0]), r0[0]), max(int(box[1]), r0[1])
    u1, v1 = min(int(box[2]), r1[0]), min(int(box[3]), r1[1])
    if u1 - u0 < 8 or v1 - v0 < 8:
        return feats
    sl = (slice(v0 - r0[1], v1 - r0[1]), slice(u0 - r0[0], u1 - r0[0]))
    gx, gy = np.ascontiguousarray(feats.gx[sl]), np.ascontiguousarray(feats.gy[sl])
    fpts, fw = forstner_points(gx, gy, options)
    segs = line_segments(_gauss(np.ascontiguousarray(feats.norm[sl]), 0.6), options)
    inter = segment_intersections(segs, options)
    off = np.array([u0, v0], dtype=np.float64)
    return replace(
        feats,
        forstner=fpts + off if len(fpts) else np.zeros((0, 2)),
        forstner_w=fw,
        segments=segs + np.tile(off, 2) if len(segs) else np.zeros((0, 4)),
        intersections=inter + off if len(inter) else np.zeros((0, 2)),
    )

"""What the tracker (`tracks.track_sequence`) takes from each frame independently of its pose: the
8-bit high-pass copy the coarse Lucas-Kanade runs on and the texture peaks new tracks start from.

In: frames in recording order with their images `(H, W)` float32 (physical values), the
tracker's options. Out: per frame the high-pass copy `(H, W)` uint8 and the candidate pixels
`(K, 2)` (u, v), strongest first.

Why: a block is tracked twice (`block.adjust_block`: again from its adjusted poses), and both
products depend only on the image and on the block's frames (the high-pass gain comes from its
middle frame): made once per frame in `TrackerFrames`, they serve both trackings. The texture
strength of a frame cost about a third of its tracking (the 300-frame NRW drive, issue 18).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "TrackOptions", "TrackerFrames", "highpass", "highpass8", "in_free_cells", "texture_peaks",
    "texture_strength",
]


@dataclass(frozen=True)
class TrackOptions:
    """Parameters of detection and tracking (pixels)."""

    # structure tensor: Gaussian window σ; a point's smaller eigenvalue must reach this multiple
    # of the frame's median (the floor of noise and fixed-pattern stripes); non-maximum
    # suppression radius
    window_sigma_px: float = 2.5
    min_texture_ratio: float = 10.0
    nms_radius_px: int = 4
    # new tracks: at most one per free cell of this size, up to `max_tracks` active ones, this far
    # from the frame border
    cell_px: int = 32
    max_tracks: int = 200
    border_px: int = 16
    # the rays this far around a point must meet the same model polygon (else: an occlusion
    # boundary or no surface), at incidence |cos| ≥ `min_incidence`
    boundary_px: float = 6.0
    min_incidence: float = 0.15
    # coarse: pyramidal LK window, levels, forward-backward tolerance; the high-pass copy: blur σ
    lk_window_px: int = 21
    lk_levels: int = 3
    fb_tolerance_px: float = 1.0
    highpass_sigma_px: float = 32.0
    # fine: half window of the float LK (Gaussian weights of σ = half window / 2), iterations,
    # the largest step from the coarse position, the correlation a track needs to go on
    fine_half_window_px: int = 7
    fine_iterations: int = 12
    fine_max_shift_px: float = 3.0
    min_ncc: float = 0.85
    # RANSAC of the essential matrix between consecutive frames: threshold
    ransac_px: float = 1.0
    # a track ends after this many views (the template ages)
    max_length: int = 12


def texture_strength(image: np.ndarray, window_sigma: float) -> np.ndarray:
    """Smaller eigenvalue `(H, W)` float32 of the structure tensor of `image` `(H, W)` (central
    differences in the image's units per pixel, Gaussian window `window_sigma` px, weights summing
    to 1): the texture a translation-only tracker can lock onto in its weakest direction."""
    img = np.asarray(image, dtype=np.float32)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=1, scale=0.5)
    k = max(3, 2 * round(2.5 * window_sigma) + 1)
    sxx = cv2.GaussianBlur(gx * gx, (k, k), window_sigma)
    syy = cv2.GaussianBlur(gy * gy, (k, k), window_sigma)
    sxy = cv2.GaussianBlur(gx * gy, (k, k), window_sigma)
    half = 0.5 * (sxx + syy)
    return half - np.sqrt(np.maximum(half * half - (sxx * syy - sxy * sxy), 0.0))


def highpass(image: np.ndarray, sigma: float) -> np.ndarray:
    """`image − blur(image)` `(H, W)` float32; the Gaussian blur of σ `sigma` px is taken at a
    resolution reduced to about σ / 4 per pixel (a wide kernel at full resolution is slow)."""
    img = np.asarray(image, dtype=np.float32)
    H, W = img.shape
    f = max(1, int(sigma // 4))
    small = cv2.resize(img, (max(W // f, 1), max(H // f, 1)), interpolation=cv2.INTER_AREA)
    blur = cv2.resize(cv2.GaussianBlur(small, (0, 0), sigma / f), (W, H), interpolation=cv2.INTER_LINEAR)
    return img - blur


def highpass8(image: np.ndarray, sigma: float, gain: float) -> np.ndarray:
    """8-bit copy `(H, W)` uint8 of `image`: `128 + gain · (image − blur(image))`, clipped."""
    return np.clip(128.0 + gain * highpass(image, sigma), 0, 255).astype(np.uint8)


def texture_peaks(strength: np.ndarray, options: TrackOptions) -> np.ndarray:
    """Candidate pixels `(K, 2)` (u, v) float64, strongest first: local maxima of `strength`
    `(H, W)` (non-maximum suppression over `nms_radius_px`) above the texture floor
    (`min_texture_ratio` × the median), at least `border_px` inside the frame."""
    floor = float(np.median(strength[::4, ::4])) * options.min_texture_ratio
    r = options.nms_radius_px
    peak = strength >= cv2.dilate(strength, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
    b = options.border_px
    H, W = strength.shape
    peak[:b] = False
    peak[H - b:] = False
    peak[:, :b] = False
    peak[:, W - b:] = False
    v, u = np.nonzero(peak & (strength > floor))
    order = np.argsort(-strength[v, u])
    return np.stack([u[order], v[order]], axis=1).astype(np.float64)


def in_free_cells(peaks: np.ndarray, occupied: np.ndarray, cell_px: int, n_max: int) -> np.ndarray:
    """The strongest of `peaks` `(K, 2)` (u, v; strongest first) in each cell of `cell_px` that
    `occupied` `(rows, cols)` bool leaves free, at most `n_max` of them, in the order of `peaks`
    -> `(k, 2)`."""
    if n_max <= 0 or len(peaks) == 0:
        return np.zeros((0, 2))
    u, v = peaks[:, 0].astype(np.int64), peaks[:, 1].astype(np.int64)
    cell = (v // cell_px) * occupied.shape[1] + (u // cell_px)
    free = ~occupied.ravel()[cell]
    kept, cell = peaks[free], cell[free]
    _, first = np.unique(cell, return_index=True)
    return kept[np.sort(first)[:n_max]]


class TrackerFrames:
    """The pose-independent products of a block's frames for the tracker, made on first use and
    kept (see the module docstring): `highpass8(f)`, `peaks(f)`. One instance serves every
    tracking of the same `frames` with the same options."""

    def __init__(
        self, frames: Sequence[int], images: Mapping[int, np.ndarray], options: TrackOptions
    ) -> None:
        """`frames` in recording order, `images` `(H, W)` float32 per frame; the high-pass gain
        is set from the middle frame (90th percentile of its high-pass magnitude to 40 grey values)."""
        self.images = images
        self.options = options
        self.gain = 0.0
        if len(frames):
            hp = highpass(self.image(frames[len(frames) // 2]), options.highpass_sigma_px)
            self.gain = 40.0 / max(float(np.percentile(np.abs(hp[::2, ::2]), 90)), 1e-6)
        self._hp8: dict[int, np.ndarray] = {}
        self._peaks: dict[int, np.ndarray] = {}

    def image(self, f: int) -> np.ndarray:
        """Frame `f` `(H, W)` float32."""
        return np.asarray(self.images[f], dtype=np.float32)

    def highpass8(self, f: int) -> np.ndarray:
        """The 8-bit high-pass copy `(H, W)` uint8 of frame `f` (`highpass8` at the block's gain)."""
        got = self._hp8.get(f)
        if got is None:
            got = self._hp8[f] = highpass8(self.image(f), self.options.highpass_sigma_px, self.gain)
        return got

    def peaks(self, f: int) -> np.ndarray:
        """The texture peaks `(K, 2)` (u, v) of frame `f`, strongest first (`texture_peaks`)."""
        got = self._peaks.get(f)
        if got is None:
            strength = texture_strength(self.image(f), self.options.window_sigma_px)
            got = self._peaks[f] = texture_peaks(strength, self.options)
        return got

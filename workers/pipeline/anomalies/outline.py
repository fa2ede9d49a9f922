"""Outlines: a region of texels -> a closed 3D ring on the surface plane (model CRS).

In: a region `(H, W)` bool of a `TexelGrid`, the grid. Out: `(N, 3)` ring, first == last,
counter-clockwise seen from the front (the side the normal points to), at most `MAX_VERTICES`
distinct vertices, and the area it encloses (m²).

The region is traced on a raster 4× finer than the texels (`cv2.findContours`), so the ring
follows the texel edges to 1/8 texel; where the region meets the polygon outline it is cut back to
half a texel inside the outline texels' centres (texel centres lie inside the polygon, so the ring
does too). The largest outer contour is simplified with `cv2.approxPolyDP`, with a tolerance
growing from 1/8 texel until at most `MAX_VERTICES` vertices remain.
"""

from __future__ import annotations

import cv2
import numpy as np

from workers.pipeline.texture.texel import TexelGrid

UP = 4  # sub-texels per texel side
MAX_VERTICES = 32
_ERODE = np.ones((UP + 1, UP + 1), np.uint8)  # removes UP/2 sub-texels: half a texel


def bbox(region: np.ndarray) -> tuple[slice, slice] | None:
    """Row and column slices of the bounding box of `region (H, W)` bool (None: empty)."""
    x, y, w, h = cv2.boundingRect(region.view(np.uint8))
    return None if w == 0 else (slice(y, y + h), slice(x, x + w))


def _fine(a: np.ndarray) -> np.ndarray:
    return cv2.resize(a, None, fx=UP, fy=UP, interpolation=cv2.INTER_NEAREST)


def region_ring(region: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
    """Open ring `(N, 2)` in continuous raster coordinates `(x, y)` around the largest part of
    `region (H, W)`, kept inside `mask (H, W)` (module docstring); None for an empty region."""
    box = bbox(region)
    if box is None:
        return None
    H, W = region.shape
    y0, y1 = max(box[0].start - 1, 0), min(box[0].stop + 1, H)
    x0, x1 = max(box[1].start - 1, 0), min(box[1].stop + 1, W)
    pad = (int(y0 == 0), int(y1 == H), int(x0 == 0), int(x1 == W))  # raster border: outside
    m = cv2.copyMakeBorder(mask[y0:y1, x0:x1].view(np.uint8), *pad, cv2.BORDER_CONSTANT, value=0)
    r = cv2.copyMakeBorder(region[y0:y1, x0:x1].view(np.uint8), *pad, cv2.BORDER_CONSTANT, value=0)
    allowed = cv2.erode(_fine(m), _ERODE)  # half a texel off the texels outside the mask
    fine = cv2.copyMakeBorder(_fine(r) & allowed, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    contours, _ = cv2.findContours(fine, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    c = max(contours, key=cv2.contourArea)
    eps = 0.125 * UP
    approx = cv2.approxPolyDP(c, eps, True)
    while len(approx) > MAX_VERTICES:
        eps *= 1.5
        approx = cv2.approxPolyDP(c, eps, True)
    if len(approx) < 3:
        return None
    p = approx.reshape(-1, 2).astype(np.float64) + (0.5 - 1.0)  # sub-texel centres, unpadded
    return np.stack([x0 - pad[2] + p[:, 0] / UP, y0 - pad[0] + p[:, 1] / UP], axis=1)


def box_ring(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """Open ring `(4, 2)` of a raster rectangle."""
    return np.array([[x0, y0], [x0, y1], [x1, y1], [x1, y0]], dtype=np.float64)


def ring_area(xy: np.ndarray) -> float:
    """Signed shoelace area of an open ring `(N, 2)` in (x, y) raster coordinates (positive:
    counter-clockwise with y down, i.e. clockwise seen with y up).

    >>> ring_area(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]))
    1.0
    """
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(x[:-1] @ y[1:] - x[1:] @ y[:-1] + x[-1] * y[0] - x[0] * y[-1])


def world_ring(grid: TexelGrid, xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Raster ring `(N, 2)` (open) -> closed world ring `(N+1, 3)`, counter-clockwise seen from
    the front, and its area in m²."""
    a = ring_area(xy)
    if a > 0:  # y runs down the raster: positive = clockwise on the wall seen from the front
        xy = xy[::-1]
    pts = grid.points_at(xy)
    return np.vstack([pts, pts[:1]]), abs(a) * grid.size**2


def outline(grid: TexelGrid, region: np.ndarray) -> tuple[np.ndarray, float] | None:
    """3D outline and area (m²) of `region (H, W)` on `grid` (None: nothing to outline)."""
    xy = region_ring(region, grid.mask)
    if xy is None:
        return None
    return world_ring(grid, xy)

"""The exact half of the clean-pixel test: does a visible polygon boundary cross a footprint?

In: the buildings of a unit's scene and the mesh built from them (`SceneMesh`, local frame
`origin`, metres; the outlines are the polygons' rings), each polygon's plane group
(`occlusion.plane_groups`), the camera, a frame's pose (world = model CRS), and per
sample the pixel `uv (N, 2)` (pixel centres at integers) of a texel and the plane group of its
polygon. Out: `(N,)` bool: some boundary edge of a scene polygon that can be seen in front of
the texel's plane crosses or touches the sample's footprint, the closed area of the `(2 + 2m)²`
pixels around it (`VisibilityOptions.blur_margin_px` = m; `occlusion.OcclusionScene.visible`).

Why: the ray test of `occlusion` reads rays through the footprint's pixel centres and corners,
every 1/2 px (and, away from silhouettes, the coarse grid's every 3rd pixel only). A polygon
corner that reaches less than half a pixel into the footprint between those rays, or a strip
thinner than that, is not seen by any of them. The edges close the gap exactly: inside a
footprint, the region a polygon shows is bounded by projected boundary edges — of the polygon
itself, or of polygons in front of its plane (a silhouette of a polygonal scene is a polygon
edge). A footprint that some ray sees on the texel's own polygon and that no such edge crosses
lies wholly on the own polygon.

Which edges count for a sample: every boundary edge of its own plane group (the polygon's
outline and holes: the other side of it is another surface; seams between the coplanar
polygons of one group, `coplanar_clean`, excepted), and the parts of the other polygons' edges
that lie on the camera's side of the texel's plane, or less than `tolerance_m` behind it
(`VisibilityOptions.occlusion_tolerance_m`): a point there, projecting into the footprint, is
seen there or hidden by something nearer, a foreign surface either way. Edges farther behind
are hidden by the own polygon (when it covers the footprint; when it does not, the rays see it).

Geometry: straight 3D edges are straight in undistorted normalised coordinates `(x/z, y/z)`.
Edges are clipped to the near plane, each edge's part on the relevant side of the sample's plane
is clipped to a box around the footprint there (its pixel corners undistorted, as
`occlusion.corner_rays`, grown by `BOX_MARGIN_PX`), and the short piece left is mapped back to
pixels (the lens's distortion applied) and tested against the footprint's pixel square
(Liang-Barsky both times). Over a few pixels a distorted straight edge is a straight chord to far
better than 1/100 px. A box in normalised coordinates alone is not exact at the footprint's
corners (away from the image centre the undistorted square is slightly skewed): on the NRW test
flight it rejected 166 of 192 footprints checked that a dense cast (every 1/20 px) finds clean,
edges passing a few 1/100 px outside a corner.

Cost: per frame, the edges projected once and cut into pieces no longer than a cell (`CELL_PX`)
inside the samples' region; pieces and footprints are hashed into those cells and only
footprint-edge pairs that share a cell are tested.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import cv2
import numpy as np

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.polygons import open_ring
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import SceneMesh

#: side of a hash cell, pixels (undistorted, at the mean focal length); a footprint of 4 pixels
#: spans at most 2 cells along each axis
CELL_PX = 8.0
#: edges are clipped to this depth (metres) in front of the projection centre
NEAR_M = 0.01
#: the footprints' normalised boxes are grown by this much (pixels) before the exact test
BOX_MARGIN_PX = 0.05


@functools.lru_cache(maxsize=8)
def footprint_boxes(camera: Camera, size: int) -> np.ndarray:
    """`(4, H + 1 - size, W + 1 - size)` float64: per footprint of `size × size` pixels whose top-
    left pixel is `(v, u)` at `[:, v, u]`, the box `(a_min, a_max, b_min, b_max)` of its pixel
    corners in undistorted normalised coordinates (its closed area; cached, read-only)."""
    uu, vv = np.meshgrid(np.arange(camera.width + 1.0) - 0.5, np.arange(camera.height + 1.0) - 0.5)
    ab = camera.normalized_from_pixel(np.stack([uu.ravel(), vv.ravel()], axis=1))
    ab = ab.reshape(camera.height + 1, camera.width + 1, 2)
    k = np.ones((size + 1, size + 1), np.uint8)
    out = []
    for c in (0, 1):
        img = np.ascontiguousarray(ab[..., c])
        lo = cv2.erode(img, k, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
        hi = cv2.dilate(img, k, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
        rows, cols = img.shape[0] - size, img.shape[1] - size
        out += [lo[:rows, :cols], hi[:rows, :cols]]
    boxes = np.ascontiguousarray(np.stack(out))
    boxes.flags.writeable = False
    return boxes


def outline_edges(
    buildings: Sequence[Building], mesh: SceneMesh
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The outline and hole edges of every polygon of `mesh`, from the rings of the `buildings` it
    was built from (`raycast.build_scene_mesh`, same order): end points `(E, 3)` and `(E, 3)`
    float64 in the mesh's local frame, and the polygon index `(E,)` of each. Polygons the mesh
    could not triangulate (nothing hits them) have none. The triangles' edges are no substitute:
    with collinear vertices (the bottoms of two windows in a row) a triangulation joins them into
    one edge that runs across the wall between the holes."""
    hit = np.bincount(mesh.triangle_polygon, minlength=mesh.n_polygons) > 0
    a: list[np.ndarray] = []
    poly: list[int] = []
    k = 0
    for building in buildings:
        for p in building.iter_polygons():
            if k < len(hit) and hit[k]:
                for ring in (p.exterior, *p.interiors):
                    r = open_ring(ring.coords)
                    if len(r) >= 2:
                        a.append(r)
                        poly.append(k)
            k += 1
    if k != mesh.n_polygons:
        raise ValueError(f"{k} polygons in the buildings, {mesh.n_polygons} in the mesh")
    if not a:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.intp)
    A = np.concatenate(a) - mesh.origin
    B = np.concatenate([np.roll(r, -1, axis=0) for r in a]) - mesh.origin
    owner = np.repeat(np.asarray(poly, np.intp), [len(r) for r in a])
    keep = np.any(A != B, axis=1)
    return A[keep], B[keep], owner[keep]


def _seams(A: np.ndarray, B: np.ndarray, group: np.ndarray) -> np.ndarray:
    """`(E,)` bool: edges `A -> B` (`(E, 3)` each) that two polygons of one plane group share (the
    same two end points, to the millimetre, either way round): seams inside a group of coplanar
    polygons."""
    if len(A) == 0:
        return np.zeros(0, bool)
    qa, qb = np.round(A * 1000.0).astype(np.int64), np.round(B * 1000.0).astype(np.int64)
    lo = np.where(_lex_less(qa, qb)[:, None], qa, qb)
    hi = np.where(_lex_less(qa, qb)[:, None], qb, qa)
    key = np.concatenate([group[:, None].astype(np.int64), lo, hi], axis=1)
    _, inv, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return count[inv.ravel()] > 1


def _lex_less(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`(N,)` bool: row `a[i]` comes before row `b[i]` in lexicographic order (`(N, 3)` ints)."""
    less = a[:, 2] < b[:, 2]
    for j in (1, 0):
        less = np.where(a[:, j] != b[:, j], a[:, j] < b[:, j], less)
    return less


def _clip_box(
    p: np.ndarray, q: np.ndarray, box: np.ndarray, t0: np.ndarray, t1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Liang-Barsky: the parameter range `[t0, t1]` (each `(K,)`, narrowed, returned) of the 2D
    segments `p + t (q - p)` (`(K, 2)` each) inside the closed boxes `box (K, 4)` = `(x_min,
    x_max, y_min, y_max)`; the segment misses its box where the returned `t0 > t1`."""
    t0, t1 = t0.copy(), t1.copy()
    for axis in (0, 1):
        d = q[:, axis] - p[:, axis]
        for bound, sign in ((box[:, 2 * axis], -1.0), (box[:, 2 * axis + 1], 1.0)):
            # inside: sign · (p + t d - bound) <= 0
            num = sign * (bound - p[:, axis])
            den = sign * d
            with np.errstate(divide="ignore", invalid="ignore"):
                t = num / den
            enter = den < 0  # moving inwards: t is a lower bound
            leave = den > 0
            t0 = np.where(enter, np.maximum(t0, t), t0)
            t1 = np.where(leave, np.minimum(t1, t), t1)
            parallel_out = (den == 0) & (num < 0)
            t1 = np.where(parallel_out, -1.0, t1)
    return t0, t1


class FootprintEdges:
    """The boundary edges of a unit's scene, for `crossed` (see the module docstring). Built once
    per unit (`occlusion.OcclusionScene`)."""

    def __init__(self, buildings: Sequence[Building], mesh: SceneMesh, camera: Camera,
                 polygon_group: np.ndarray, tolerance_m: float, coplanar: bool) -> None:  # fmt: skip
        """`buildings`: those `mesh` was built from (`outline_edges`); `polygon_group (P,)`: plane
        group of each polygon (the smallest polygon index of the group); `tolerance_m`: how far
        behind a sample's plane an edge still counts; `coplanar`: seams between polygons of one
        group do not count."""
        self.camera = camera
        self.tolerance_m = float(tolerance_m)
        a, b, poly = outline_edges(buildings, mesh)
        group = polygon_group[poly] if len(poly) else np.zeros(0, np.intp)
        if coplanar and len(poly):
            keep = ~_seams(a, b, group)
            a, b, group = a[keep], b[keep], group[keep]
        self.a, self.b = a, b
        self.group = np.asarray(group, np.intp)
        v = mesh.vertices.astype(np.float64)
        self.origin = mesh.origin
        # each polygon's plane (local frame): unit normal and offset (mean over its vertices)
        P = mesh.n_polygons
        self.normal = np.asarray(mesh.polygon_normals, np.float64).reshape(P, 3)
        tv = mesh.triangles.reshape(-1)
        tp = np.repeat(mesh.triangle_polygon, 3)
        dots = np.einsum("ij,ij->i", self.normal[tp], v[tv]) if len(tv) else np.zeros(0)
        n_each = np.bincount(tp, minlength=P) if len(tv) else np.zeros(P)
        self.offset = np.bincount(tp, dots, minlength=P) / np.maximum(n_each, 1) if len(tv) else np.zeros(P)
        self.f = 0.5 * (camera.fx + camera.fy)

    def crossed(self, pose: Pose, uv: np.ndarray, group: np.ndarray, margin: int) -> np.ndarray:
        """`(N,)` bool: a counting edge (module docstring) crosses or touches the closed footprint
        of the samples at `uv (N, 2)` — the 2 × 2 bilinear pixels grown by `margin` — whose texel
        lies on a polygon of plane group `group (N,)` (a polygon index, as `plane_groups`)."""
        n = len(uv)
        out = np.zeros(n, bool)
        if n == 0 or len(self.a) == 0:
            return out
        size = 2 + 2 * margin
        boxes = footprint_boxes(self.camera, size)
        H1, W1 = boxes.shape[1:]
        c0 = np.clip(np.floor(uv[:, 0]).astype(np.intp) - margin, 0, W1 - 1)
        r0 = np.clip(np.floor(uv[:, 1]).astype(np.intp) - margin, 0, H1 - 1)
        g = BOX_MARGIN_PX / self.f
        box = boxes[:, r0, c0].T + np.array([-g, g, -g, g])  # (N, 4), a superset of the footprint
        square = np.stack([c0 - 0.5, c0 + size - 0.5, r0 - 0.5, r0 + size - 0.5], axis=1)  # pixels
        lo = np.array([box[:, 0].min(), box[:, 2].min()])
        hi = np.array([box[:, 1].max(), box[:, 3].max()])
        # edges in the camera frame, clipped to the near plane and to the samples' region
        c = pose.center - self.origin
        R = pose.R_world_from_cam
        pa = np.einsum("ij,jk->ik", self.a - c, R)
        pb = np.einsum("ij,jk->ik", self.b - c, R)
        za, zb = pa[:, 2], pb[:, 2]
        # cheap cull first: both ends beyond one side plane of the region's pyramid (x < lo·z ...)
        out_side = (pa[:, 0] < lo[0] * za) & (pb[:, 0] < lo[0] * zb)
        out_side |= (pa[:, 0] > hi[0] * za) & (pb[:, 0] > hi[0] * zb)
        out_side |= (pa[:, 1] < lo[1] * za) & (pb[:, 1] < lo[1] * zb)
        out_side |= (pa[:, 1] > hi[1] * za) & (pb[:, 1] > hi[1] * zb)
        e = np.flatnonzero(((za >= NEAR_M) | (zb >= NEAR_M)) & ~out_side)
        pa, pb, za, zb = pa[e], pb[e], za[e], zb[e]
        with np.errstate(divide="ignore", invalid="ignore"):
            tz = (NEAR_M - za) / (zb - za)
        e_t0 = np.where(za >= NEAR_M, 0.0, tz)
        e_t1 = np.where(zb >= NEAR_M, 1.0, tz)
        d = pb - pa
        p, q = pa + e_t0[:, None] * d, pa + e_t1[:, None] * d
        p2, q2 = p[:, :2] / p[:, 2:], q[:, :2] / q[:, 2:]
        region = np.array([[lo[0], hi[0], lo[1], hi[1]]])
        s0, s1 = _clip_box(p2, q2, region, np.zeros(len(e)), np.ones(len(e)))
        k = np.flatnonzero(s0 <= s1)
        if len(k) == 0:
            return out
        e, pa, pb, e_t0, e_t1 = e[k], pa[k], pb[k], e_t0[k], e_t1[k]
        p2, q2, s0, s1 = p2[k], q2[k], s0[k], s1[k]
        # of those, the parts that count for each sample group (module docstring): parameter
        # ranges `(E', G)` on the camera's side of the group's plane (whole for its own edges)
        gs, col = np.unique(group, return_inverse=True)
        col = col.ravel()
        tol = self.tolerance_m
        sa = np.einsum("ij,kj->ik", self.a[e], self.normal[gs]) - self.offset[gs]
        sb = np.einsum("ij,kj->ik", self.b[e], self.normal[gs]) - self.offset[gs]
        own = self.group[e][:, None] == gs[None, :]
        with np.errstate(divide="ignore", invalid="ignore"):
            tp = (-tol - sa) / (sb - sa)
        g_t0 = np.where(own | (sa >= -tol), 0.0, tp)
        g_t1 = np.where(own | (sb >= -tol), 1.0, tp)
        g_t0[~(own | (sa >= -tol) | (sb >= -tol))] = 2.0
        k = np.flatnonzero((g_t0 <= g_t1).any(axis=1))
        if len(k) == 0:
            return out
        e, pa, pb, e_t0, e_t1, g_t0, g_t1 = e[k], pa[k], pb[k], e_t0[k], e_t1[k], g_t0[k], g_t1[k]
        p2, q2, s0, s1 = p2[k], q2[k], s0[k], s1[k]
        cell = CELL_PX / self.f
        x0 = (p2 + s0[:, None] * (q2 - p2) - lo) / cell
        x1 = (p2 + s1[:, None] * (q2 - p2) - lo) / cell
        pieces = np.maximum(np.ceil(np.abs(x1 - x0).max(axis=1)), 1).astype(np.intp)
        pe = np.repeat(np.arange(len(e)), pieces)
        k = np.arange(len(pe)) - np.repeat(np.cumsum(pieces) - pieces, pieces)
        frac = np.stack([k / pieces[pe], (k + 1) / pieces[pe]])  # (2, Q)
        ends = x0[pe] + frac[..., None] * (x1 - x0)[pe]  # (2, Q, 2) in cells
        nx = int(np.floor((hi[0] - lo[0]) / cell)) + 1
        cmin = np.floor(ends.min(axis=0)).astype(np.int64)
        cmax = np.floor(ends.max(axis=0)).astype(np.int64)
        keys = []
        for dy in (0, 1):
            for dx in (0, 1):
                cx, cy = cmin[:, 0] + dx, cmin[:, 1] + dy
                ok = (cx <= cmax[:, 0]) & (cy <= cmax[:, 1])
                keys.append(np.where(ok, cy * nx + cx, -1))
        kq = np.stack(keys, axis=1).ravel()
        eq = np.repeat(pe, 4)
        sel = kq >= 0
        pair_key = np.unique(kq[sel] * len(e) + eq[sel])
        cell_of, edge_of = pair_key // len(e), pair_key % len(e)
        # the samples' cells
        bmin = np.floor((box[:, [0, 2]] - lo) / cell).astype(np.int64)
        bmax = np.floor((box[:, [1, 3]] - lo) / cell).astype(np.int64)
        s_idx, s_key = [], []
        span = int((bmax - bmin).max()) + 1
        for dy in range(span):
            for dx in range(span):
                cx, cy = bmin[:, 0] + dx, bmin[:, 1] + dy
                ok = np.flatnonzero((cx <= bmax[:, 0]) & (cy <= bmax[:, 1]))
                s_idx.append(ok)
                s_key.append(cy[ok] * nx + cx[ok])
        si, sk = np.concatenate(s_idx), np.concatenate(s_key)
        first = np.searchsorted(cell_of, sk, "left")
        cnt = np.searchsorted(cell_of, sk, "right") - first
        if cnt.sum() == 0:
            return out
        ps = np.repeat(si, cnt)
        j = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(first, cnt)
        pe2 = edge_of[j]  # index into `e`
        t0 = np.maximum(e_t0[pe2], g_t0[pe2, col[ps]])
        t1 = np.minimum(e_t1[pe2], g_t1[pe2, col[ps]])
        return self._exact(out, ps, pe2, pa, pb, t0, t1, box, square)

    def _exact(self, out: np.ndarray, ps: np.ndarray, pe: np.ndarray, pa: np.ndarray, pb: np.ndarray,
               t0: np.ndarray, t1: np.ndarray, box: np.ndarray,
               square: np.ndarray) -> np.ndarray:  # fmt: skip
        """Mark in `out (N,)` the samples `ps (K,)` whose footprint the counting part `[t0, t1]`
        (`(K,)` each, empty where `t0 > t1`) of edge `pe (K,)` (camera frame `pa`, `pb`) meets:
        the part is clipped to the footprint's normalised box `box[ps]` (a superset), the piece
        left mapped to pixels (distortion applied; over a few pixels a straight chord) and tested
        against the footprint's pixel square `square[ps]` `(u_min, u_max, v_min, v_max)`."""
        live = t0 <= t1
        ps, pe, t0, t1 = ps[live], pe[live], t0[live], t1[live]
        if len(ps) == 0:
            return out
        d = pb[pe] - pa[pe]
        p = pa[pe] + t0[:, None] * d
        q = pa[pe] + t1[:, None] * d
        p2, q2 = p[:, :2] / p[:, 2:], q[:, :2] / q[:, 2:]
        s0, s1 = _clip_box(p2, q2, box[ps], np.zeros(len(ps)), np.ones(len(ps)))
        near = s0 <= s1
        ps, p2, q2, s0, s1 = ps[near], p2[near], q2[near], s0[near], s1[near]
        if len(ps) == 0:
            return out
        pix0 = self.camera.pixel_from_normalized(p2 + s0[:, None] * (q2 - p2))
        pix1 = self.camera.pixel_from_normalized(p2 + s1[:, None] * (q2 - p2))
        u0, u1 = _clip_box(pix0, pix1, square[ps], np.zeros(len(ps)), np.ones(len(ps)))
        out[ps[u0 <= u1]] = True
        return out

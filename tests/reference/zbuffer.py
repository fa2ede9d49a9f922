"""The reference's camera and z-buffer: OpenCV projection and a polygon rasterizer of its own.

Camera conventions (spec `sequence-format.md`): camera frame x right, y down, z forward;
`x_c = R_wcᵀ (X − C)`; OpenCV distortion `k1, k2, p1, p2, k3`; pixel centres at integer
coordinates, `(0, 0)` the centre of the top-left pixel.

The z-buffer: straight edges stay straight only without distortion, so every polygon is
rasterized (`cv2.fillPoly`, holes by the even-odd rule, near plane clipped) into a *virtual
pinhole image* of `supersample` × the real resolution that covers the real image's undistorted
field; the depth of a pixel is exact from the polygon's plane (`z = δ / (n_c · (a, b, 1))`). The
analytic ground plane `z = ground_z` (the synthetic world's) fills it first; a terrain
(`RefGround`: a TIN inside the plane, the synthetic world's `ground` read as plain arrays) clears
the plane inside the TIN's outer boundary and is rasterized triangle by triangle like the polygons
(label `GROUND`). Then each real pixel
looks up the virtual pixels under `supersample²` points spread over its closed area, edges
included (their undistorted positions, `cv2.undistortPointsIter`): `centre` is the id under the
pixel centre, `pure` the common id of all of them, `MIXED` where they disagree (an edge crosses
or touches the pixel).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
import shapely

from tests.reference.geometry import GROUND, MIXED, SKY, ScenePolygon

NEAR_M = 0.05  # near clipping plane, metres in front of the projection centre


@dataclass(frozen=True, eq=False)
class RefCamera:
    """Interior orientation as OpenCV wants it: `K` `(3, 3)`, `dist` `(5,)` (k1, k2, p1, p2, k3),
    image `width × height` pixels; `supersample` sets the z-buffer's virtual resolution."""

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    supersample: int = 3

    @classmethod
    def from_params(cls, cam: object, supersample: int = 3) -> RefCamera:
        """From any object with the plain attributes `width, height, fx, fy, cx, cy, k1, k2, p1,
        p2, k3` (e.g. the product's `Camera`, read as numbers only)."""

        def g(name: str) -> float:
            return float(getattr(cam, name))

        K = np.array([[g("fx"), 0.0, g("cx")], [0.0, g("fy"), g("cy")], [0.0, 0.0, 1.0]])
        dist = np.array([g("k1"), g("k2"), g("p1"), g("p2"), g("k3")])
        return cls(int(g("width")), int(g("height")), K, dist, supersample)

    @property
    def f(self) -> float:
        """Mean focal length, pixels."""
        return 0.5 * float(self.K[0, 0] + self.K[1, 1])

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Pixels `(N, 2)` -> undistorted normalised coordinates `(N, 2)` (a, b) = (x/z, y/z)."""
        pts = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        return cv2.undistortPointsIter(pts, self.K, self.dist, None, None, crit).reshape(-1, 2)

    @cached_property
    def field(self) -> tuple[float, float, float, float]:
        """Undistorted normalised bounds `(a_min, a_max, b_min, b_max)` of the image grown by two
        pixels on every side (points outside are never inside the image; inside this window the
        distortion model is used only where it is monotonic)."""
        W, H = self.width, self.height
        u = np.arange(-2.0, W + 2.0, 0.5)
        v = np.arange(-2.0, H + 2.0, 0.5)
        border = np.concatenate(
            [np.stack([u, np.full_like(u, -2.0)], 1), np.stack([u, np.full_like(u, H + 1.0)], 1),
             np.stack([np.full_like(v, -2.0), v], 1), np.stack([np.full_like(v, W + 1.0), v], 1)]
        )  # fmt: skip
        ab = self.undistort(border)
        return float(ab[:, 0].min()), float(ab[:, 0].max()), float(ab[:, 1].min()), float(ab[:, 1].max())

    @cached_property
    def virtual(self) -> tuple[float, float, float, int, int]:
        """The virtual pinhole image `(f_v, c_x, c_y, W_v, H_v)`: `x_v = f_v·a + c_x`,
        `y_v = f_v·b + c_y`, covering `field` with a margin of 2 virtual pixels."""
        a0, a1, b0, b1 = self.field
        fv = self.f * self.supersample
        cx, cy = -a0 * fv + 2.0, -b0 * fv + 2.0
        return fv, cx, cy, int(np.ceil((a1 - a0) * fv + 5)), int(np.ceil((b1 - b0) * fv + 5))

    @cached_property
    def lookups(self) -> tuple[np.ndarray, np.ndarray]:
        """Flat virtual-pixel indices `(S, H·W)` int64 of the `S = supersample²` area samples of
        every real pixel (row-major), and the index of the one at the pixel centre `(H·W,)`."""
        ss = self.supersample
        # spread over the pixel's closed area, its edges included (shared with the neighbours): a
        # footprint of whole pixels is tested up to its boundary, as the rule wants
        offs = np.linspace(-0.5, 0.5, ss) if ss > 1 else np.zeros(1)
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        fv, cx, cy, Wv, Hv = self.virtual

        def index(du: float, dv: float) -> np.ndarray:
            ab = self.undistort(np.stack([u.ravel() + du, v.ravel() + dv], 1))
            xv = np.clip(np.rint(fv * ab[:, 0] + cx), 0, Wv - 1).astype(np.int64)
            yv = np.clip(np.rint(fv * ab[:, 1] + cy), 0, Hv - 1).astype(np.int64)
            return yv * Wv + xv

        return np.stack([index(du, dv) for dv in offs for du in offs]), index(0.0, 0.0)

    @cached_property
    def virtual_ab(self) -> tuple[np.ndarray, np.ndarray]:
        """Normalised coordinates of the virtual pixel columns `(W_v,)` and rows `(H_v,)`."""
        fv, cx, cy, Wv, Hv = self.virtual
        return (np.arange(Wv) - cx) / fv, (np.arange(Hv) - cy) / fv

    def project(
        self, X: np.ndarray, R_wc: np.ndarray, C: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points `(N, 3)` -> (pixels `(N, 2)` by `cv2.projectPoints`, depth `z_c` `(N,)` m,
        `ok (N,)`: in front of the near plane and inside the undistorted `field`, where the
        pixels mean something; elsewhere the pixels are NaN)."""
        X = np.asarray(X, dtype=np.float64)
        xc = (X - C) @ R_wc
        z = xc[:, 2]
        a0, a1, b0, b1 = self.field
        with np.errstate(divide="ignore", invalid="ignore"):
            a, b = xc[:, 0] / z, xc[:, 1] / z
        ok = (z > NEAR_M) & (a >= a0) & (a <= a1) & (b >= b0) & (b <= b1)
        uv = np.full((len(X), 2), np.nan)
        if ok.any():
            R_cw = np.ascontiguousarray(R_wc.T)
            rvec, _ = cv2.Rodrigues(R_cw)
            tvec = -R_cw @ C
            p, _ = cv2.projectPoints(X[ok].reshape(-1, 1, 3), rvec, tvec, self.K, self.dist)
            uv[ok] = p.reshape(-1, 2)
        return uv, z, ok


@dataclass(frozen=True, eq=False)
class IdBuffer:
    """What each real pixel sees, for one frame.

    Attributes:
        centre: `(H, W)` int32 id under the pixel centre (polygon index, `SKY`, `GROUND`).
        pure: `(H, W)` int32 the id all area samples agree on, else `MIXED`.
        depth: `(H, W)` float32 `z_c` (metres along the optical axis) at the pixel centre, inf for sky.
        edge_dist: `(H, W)` float32 pixels from the nearest change of `centre` id.
    """

    centre: np.ndarray
    pure: np.ndarray
    depth: np.ndarray
    edge_dist: np.ndarray


def _clip_near(ring_c: np.ndarray) -> np.ndarray:
    """Sutherland–Hodgman clip of a camera-frame ring `(N, 3)` to `z >= NEAR_M` -> `(M, 3)`."""
    out = []
    n = len(ring_c)
    for i in range(n):
        p, q = ring_c[i], ring_c[(i + 1) % n]
        pin, qin = p[2] >= NEAR_M, q[2] >= NEAR_M
        if pin:
            out.append(p)
        if pin != qin:
            t = (NEAR_M - p[2]) / (q[2] - p[2])
            out.append(p + t * (q - p))
    return np.array(out) if out else np.zeros((0, 3))


@dataclass(frozen=True, eq=False)
class RefGround:
    """The synthetic world's ground as the reference renders it: the plane `z = z` and, inside
    the outer boundary of a TIN (`vertices (V, 3)` world m, `triangles (T, 3)` indices; empty: the
    plane alone), the TIN's triangles. The TIN's outer boundary must be convex and lie on the
    plane (the synthetic world's terrain: a square at the plane's height around it)."""

    z: float
    vertices: np.ndarray
    triangles: np.ndarray

    @classmethod
    def from_truth(cls, truth: object) -> RefGround:
        """From a synthetic truth's plain numbers: `ground_z` and, when it has a terrain, its
        `ground.vertices` / `ground.triangles` (arrays only, no code of it is used)."""
        g = getattr(truth, "ground", None)
        V = np.zeros((0, 3)) if g is None else np.asarray(g.vertices, np.float64).reshape(-1, 3)
        T = np.zeros((0, 3), np.int64) if g is None else np.asarray(g.triangles, np.int64).reshape(-1, 3)
        return cls(float(truth.ground_z), V, T)  # type: ignore[attr-defined]

    @cached_property
    def hull(self) -> np.ndarray:
        """`(K, 3)` the TIN's outer boundary (convex hull of its vertices in x/y, counter-
        clockwise), checked to lie on the plane."""
        hull = shapely.MultiPoint(self.vertices[:, :2]).convex_hull
        xy = np.asarray(hull.exterior.coords)[:-1]
        ring = np.c_[xy, np.full(len(xy), self.z)]
        V = {(round(x, 6), round(y, 6)): z for x, y, z in self.vertices}
        if any(abs(V.get((round(x, 6), round(y, 6)), np.inf) - self.z) > 1e-6 for x, y in xy):
            raise ValueError("RefGround: the TIN's outer boundary must lie on the plane")
        return ring

    @cached_property
    def planes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per triangle: upward unit normal `(T, 3)`, plane offset `(T,)`, centre `(T, 3)` and
        bounding-sphere radius `(T,)`."""
        a, b, c = (self.vertices[self.triangles[:, i]] for i in range(3))
        n = np.cross(b - a, c - a)
        n *= np.sign(n[:, 2:3]) / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        centre = (a + b + c) / 3.0
        radius = np.max(np.stack([np.linalg.norm(v - centre, axis=1) for v in (a, b, c)]), axis=0)
        return n, np.einsum("ij,ij->i", n, a), centre, radius


class ZBuffer:
    """Renders `IdBuffer`s of a fixed list of scene polygons (plus an optional ground).

    Args:
        camera: the reference camera.
        polygons: the scene (all occluders and all textured surfaces), ids = their `index`.
        ground_z: height of an infinite horizontal ground plane, or a `RefGround` (a terrain
            inside the plane), or None: no ground.
    """

    def __init__(
        self, camera: RefCamera, polygons: list[ScenePolygon], ground_z: float | RefGround | None
    ) -> None:
        self.camera, self.polygons = camera, polygons
        self.ground: RefGround | None = None  # the terrain, when there is one
        self.ground_z: float | None = (
            None if ground_z is None else float(ground_z.z if isinstance(ground_z, RefGround) else ground_z)
        )
        if isinstance(ground_z, RefGround) and len(ground_z.triangles):
            self.ground = ground_z
        self.centres = np.array([p.centre for p in polygons]).reshape(-1, 3)
        self.radii = np.array([p.radius for p in polygons])
        a0, a1, b0, b1 = camera.field
        # inward normals of the four side planes of the virtual frustum (camera frame)
        planes = np.array([[1.0, 0.0, -a0], [-1.0, 0.0, a1], [0.0, 1.0, -b0], [0.0, -1.0, b1]])
        self.side_planes = planes / np.linalg.norm(planes, axis=1, keepdims=True)

    def candidates(self, R_wc: np.ndarray, C: np.ndarray) -> np.ndarray:
        """Indices of the polygons whose bounding sphere meets the view frustum."""
        return self._in_frustum(self.centres, self.radii, R_wc, C)

    def _in_frustum(
        self, centres: np.ndarray, radii: np.ndarray, R_wc: np.ndarray, C: np.ndarray
    ) -> np.ndarray:
        """Indices of the bounding spheres (`centres (N, 3)`, `radii (N,)`) meeting the view frustum."""
        xc = (centres - C) @ R_wc
        ok = xc[:, 2] + radii > NEAR_M
        ok &= np.all(xc @ self.side_planes.T > -radii[:, None], axis=1)
        return np.flatnonzero(ok)

    def _raster(
        self, rings: tuple[np.ndarray, ...] | list[np.ndarray], R_wc: np.ndarray, C: np.ndarray
    ) -> tuple[np.ndarray, int, int] | None:
        """The virtual-image mask of a planar polygon (`rings` world `(N, 3)`, exterior first, holes
        by the even-odd rule), near plane clipped: (mask `(h, w)` bool, x0, y0 of its window), None
        when nothing of it is in the virtual image."""
        fv, cx, cy, Wv, Hv = self.camera.virtual
        contours = []
        for ring in rings:
            rc = (ring - C) @ R_wc
            if rc[:, 2].min() < NEAR_M:
                rc = _clip_near(rc)
                if len(rc) < 3:
                    continue
            xy = np.stack([fv * rc[:, 0] / rc[:, 2] + cx, fv * rc[:, 1] / rc[:, 2] + cy], 1)
            contours.append(np.clip(xy, -1e5, 1e5))
        if not contours:
            return None
        allp = np.concatenate(contours)
        x0, y0 = max(int(np.floor(allp[:, 0].min())), 0), max(int(np.floor(allp[:, 1].min())), 0)
        x1, y1 = min(int(np.ceil(allp[:, 0].max())), Wv - 1), min(int(np.ceil(allp[:, 1].max())), Hv - 1)
        if x1 < x0 or y1 < y0:
            return None
        mask = np.zeros((y1 - y0 + 1, x1 - x0 + 1), np.uint8)
        pts = [np.rint((c - [x0, y0]) * 16).astype(np.int32) for c in contours]
        cv2.fillPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=4)
        return mask.astype(bool), x0, y0

    def _fill_terrain(self, zbuf: np.ndarray, ids: np.ndarray, R_wc: np.ndarray, C: np.ndarray) -> None:
        """The terrain: clear the plane (already filled) inside the TIN's outer boundary, then
        depth-test its triangles in (label `GROUND`)."""
        g = self.ground
        assert g is not None
        hull = self._raster([g.hull], R_wc, C)
        if hull is not None:
            mask, x0, y0 = hull
            h, w = mask.shape
            sub_z, sub_id = zbuf[y0 : y0 + h, x0 : x0 + w], ids[y0 : y0 + h, x0 : x0 + w]
            clear = mask & (sub_id == GROUND)
            sub_z[clear] = np.inf
            sub_id[clear] = SKY
        normals, offsets, centres, radii = g.planes
        for k in self._in_frustum(centres, radii, R_wc, C):
            if normals[k] @ C <= offsets[k]:
                continue  # seen from below
            r = self._raster([g.vertices[g.triangles[k]]], R_wc, C)
            if r is not None:
                mask, x0, y0 = r
                n_c = R_wc.T @ normals[k]
                self._fill_plane(zbuf, ids, mask, x0, y0, n_c, offsets[k] - normals[k] @ C, GROUND)

    def _fill_plane(
        self, zbuf: np.ndarray, ids: np.ndarray, mask: np.ndarray, x0: int, y0: int,
        n_c: np.ndarray, delta: float, label: int,
    ) -> None:  # fmt: skip
        """Depth-test the plane `n_c · x_c = delta` over `mask` (a window at `(x0, y0)`) and write
        the nearer pixels' depth and `label` into `zbuf` / `ids`."""
        A, B = self.camera.virtual_ab
        h, w = mask.shape
        a, b = A[x0 : x0 + w][None, :], B[y0 : y0 + h][:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (delta / (n_c[0] * a + n_c[1] * b + n_c[2])).astype(np.float32)
        sub_z, sub_id = zbuf[y0 : y0 + h, x0 : x0 + w], ids[y0 : y0 + h, x0 : x0 + w]
        upd = mask & (z > NEAR_M) & (z < sub_z)
        sub_z[upd] = z[upd]
        sub_id[upd] = label

    def render(self, R_wc: np.ndarray, C: np.ndarray) -> IdBuffer:
        """The `IdBuffer` of the camera at `R_wc` `(3, 3)` (camera to world), centre `C` `(3,)`."""
        cam = self.camera
        _, _, _, Wv, Hv = cam.virtual
        zbuf = np.full((Hv, Wv), np.inf, np.float32)
        ids = np.full((Hv, Wv), SKY, np.int32)
        if self.ground_z is not None:
            n_c = R_wc.T @ np.array([0.0, 0.0, 1.0])
            self._fill_plane(zbuf, ids, np.ones((Hv, Wv), bool), 0, 0, n_c, self.ground_z - C[2], GROUND)
        if self.ground is not None:
            self._fill_terrain(zbuf, ids, R_wc, C)
        for k in self.candidates(R_wc, C):
            p = self.polygons[k]
            r = self._raster(p.rings, R_wc, C)
            if r is None:
                continue
            mask, x0, y0 = r
            n_c = R_wc.T @ p.normal
            self._fill_plane(zbuf, ids, mask, x0, y0, n_c, p.offset - p.normal @ C, p.index)
        samples, centre_idx = cam.lookups
        flat_ids, flat_z = ids.ravel(), zbuf.ravel()
        H, W = cam.height, cam.width
        centre = flat_ids[centre_idx].reshape(H, W)
        pure = centre.copy()
        for idx in samples:
            pure[flat_ids[idx].reshape(H, W) != centre] = MIXED
        edge = np.zeros((H, W), bool)
        dh = centre[:, 1:] != centre[:, :-1]
        dv = centre[1:, :] != centre[:-1, :]
        edge[:, 1:] |= dh
        edge[:, :-1] |= dh
        edge[1:, :] |= dv
        edge[:-1, :] |= dv
        edge_dist = cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L2, 3)
        return IdBuffer(centre, pure, flat_z[centre_idx].reshape(H, W), edge_dist)

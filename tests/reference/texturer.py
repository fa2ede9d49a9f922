"""The reference texturer: the yardstick the product's textures are measured against.

In: the scene polygons (`geometry.scene_polygons`: every building that may occlude or be
textured), the surfaces to texture (a subset, by polygon id), a `RefCamera`, the frames' poses as
plain arrays (`R_wc` `(3, 3)` camera to world, centre `C` `(3,)`, world = model CRS, metres), a
frame loader (`index -> (H, W) float32 kelvin`), the ground of the synthetic world (its plane's
height, or a `zbuffer.RefGround` terrain) and `ReferenceOptions`. Out: per surface a `RefTexture`
on its own `RefGrid`: the fused value per texel, the observation count, which frames saw it, the
best view angle, ground resolution and distance to an id edge, and whether any frame sees its
centre at all.

Per frame and texel (the whole rule, nothing else):
1. project the texel centre (`cv2.projectPoints`); it must be in front, inside the image with
   `margin_px`, and face the camera within `grazing_limit_deg`;
2. mixed-pixel test: the 2 × 2 bilinear support plus a ring of `footprint_ring_px` pixels (the
   sensor's blur), i.e. a 4 × 4 block, must be *pure* pixels of the texel's own polygon in the
   frame's z-buffer (`zbuffer.IdBuffer.pure`), at the texel's depth;
3. value: bilinear sample of the kelvin frame; weight `cos θ / gsd²` with `gsd = range / f`
   (metres per pixel across the ray).
Fusion per texel: only the views about as sharp as its sharpest one (footprint on the surface
`gsd / cos θ` within `resolution_ratio` of the smallest: a blurred distant view must not soften a
sharp near one); of those, the observations more than `outlier_sigmas` robust sigmas (1.4826 ·
MAD, at least `sigma_floor_k`) from the median are dropped, the rest averaged with their weights.

Split halves (`reference_half_textures`): the same, with each frame's observations of a surface
going to the even or the odd half of the frames that see the surface's building (the product's
`--split-half` rule); both halves of a surface share its grid.

Independent of the product: no import of `workers.pipeline` texture, ray casting, camera
projection or units code; the z-buffer, the grids and the projection are this package's own
(OpenCV and shapely underneath).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field

import numpy as np

from tests.reference.geometry import RefGrid, ScenePolygon, coplanar_groups, ref_grid
from tests.reference.zbuffer import IdBuffer, RefCamera, RefGround, ZBuffer

#: frame index -> float32 kelvin image `(H, W)`
FrameLoader = Callable[[int], np.ndarray]


@dataclass(frozen=True)
class ReferenceOptions:
    """The reference's few parameters.

    Attributes:
        texels_per_m: texel density of the reference's own grids.
        margin_px: texel projections closer than this to the image border are not used.
        grazing_limit_deg: largest angle between the surface normal and the ray to the camera.
        footprint_ring_px: pixels around the 2 × 2 bilinear support that must be clean too (PSF).
        depth_tolerance: allowed relative difference between the z-buffer depth at the texel's
            pixel and the texel's own depth (plus `depth_tolerance_m`).
        depth_tolerance_m: absolute part of the depth tolerance, metres.
        resolution_ratio: views whose footprint on the surface is more than this times the
            texel's sharpest view's are left out of the fusion.
        outlier_sigmas: observations farther than this many robust sigmas from the median go.
        sigma_floor_k: smallest robust sigma, kelvin (two or three agreeing frames have MAD ~ 0).
        coplanar_ok: pixels of a coplanar polygon of the same building and class count as clean.
        supersample: area samples per real pixel side in the z-buffer (edge pixels become MIXED);
            `compare.run_reference` and the split halves render with it. The samples of a pixel
            span its closed area, edges included (shared with the neighbours, `RefCamera.lookups`):
            with 6, every 1/5 px, so the 4 × 4 block of step 2 is tested over its whole closed
            area, boundary included, as the product's test (`pixel_area`: rays through the block's
            pixel corners and centres) does. Samples at the sub-pixel centres only (`(k + ½)/ss`)
            left the outermost 1/(2·ss) px of the block untested (1/6 px at 3: 3 thin walls of the
            NRW test drive counted as clean; 1/12 px at 6: on the quick NRW flight the reference
            observed ~6 % more area per surface than the product, median ratio 0.938).
        sees_min_pixels: split halves only (`reference_half_textures`): a frame sees a building
            when at least this many of its pixel centres show the building (128: about what the
            product's planning needs, two hits of rays through every 8th pixel).
    """

    texels_per_m: float = 10.0
    margin_px: float = 2.0
    grazing_limit_deg: float = 80.0
    footprint_ring_px: int = 1
    depth_tolerance: float = 0.02
    depth_tolerance_m: float = 0.1
    resolution_ratio: float = 1.5
    outlier_sigmas: float = 3.0
    sigma_floor_k: float = 0.1
    coplanar_ok: bool = False
    supersample: int = 6
    sees_min_pixels: int = 128


@dataclass(eq=False)
class RefTexture:
    """The reference's texture of one surface (arrays over the grid's `N` texels).

    Attributes:
        grid: the texel grid.
        value: `(N,)` float32 kelvin, NaN where no clean observation.
        count: `(N,)` int observations kept by the fusion.
        seen: `(N,)` bool some frame sees the texel centre at all (in front, in the image,
            facing, its own polygon under the centre pixel: no footprint test).
        best_frame: `(N,)` int frame of the highest-weight kept observation, -1 if none.
        best_angle_deg, best_gsd_m, best_edge_px: `(N,)` that observation's view angle, ground
            resolution (m/pixel across the ray) and distance to the nearest id edge (pixels);
            for texels seen but never clean: the values of the frame that saw the centre best.
        obs_texel, obs_frame: `(M,)` every clean observation's texel and frame ("which frames
            saw it"); obs_kept: `(M,)` bool kept by the fusion.
    """

    grid: RefGrid
    value: np.ndarray
    count: np.ndarray
    seen: np.ndarray
    best_frame: np.ndarray
    best_angle_deg: np.ndarray
    best_gsd_m: np.ndarray
    best_edge_px: np.ndarray
    obs_texel: np.ndarray
    obs_frame: np.ndarray
    obs_kept: np.ndarray

    @property
    def observed(self) -> np.ndarray:
        """`(N,)` bool texels with a value."""
        return np.isfinite(self.value)

    def frames_of(self, texel: int) -> np.ndarray:
        """Frame indices of the clean observations of one texel."""
        return np.unique(self.obs_frame[self.obs_texel == texel])


@dataclass(eq=False)
class _Acc:
    """Per-surface accumulator of observations (lists of per-frame arrays)."""

    grid: RefGrid
    parts: list[tuple[np.ndarray, ...]] = field(default_factory=list)
    seen: np.ndarray | None = None
    seen_w: np.ndarray | None = None  # best weight among centre-visible frames
    seen_attr: np.ndarray | None = None  # (N, 3): angle, gsd, edge distance of that frame


def bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples `(N,)` float64 of `image (H, W)` at pixels `uv (N, 2)` (centres at
    integers; every `uv` must lie in `[0, W-1) × [0, H-1)`).

    >>> bilinear(np.array([[0., 1.], [2., 3.]]), np.array([[0.5, 0.5], [0.25, 0.0]])).tolist()
    [1.5, 0.25]
    """
    u0 = np.floor(uv[:, 0]).astype(np.int64)
    v0 = np.floor(uv[:, 1]).astype(np.int64)
    fu, fv = uv[:, 0] - u0, uv[:, 1] - v0
    u1 = np.minimum(u0 + 1, image.shape[1] - 1)
    v1 = np.minimum(v0 + 1, image.shape[0] - 1)
    img = np.asarray(image, dtype=np.float64)
    top = img[v0, u0] * (1 - fu) + img[v0, u1] * fu
    bot = img[v1, u0] * (1 - fu) + img[v1, u1] * fu
    return top * (1 - fv) + bot * fv


def _observe(
    acc: _Acc, frame: int, buf: IdBuffer, load: Callable[[], np.ndarray], cam: RefCamera,
    R_wc: np.ndarray, C: np.ndarray, group: np.ndarray, o: ReferenceOptions,
) -> None:  # fmt: skip
    """Add frame `frame`'s observations of one surface to `acc` (see the module docstring)."""
    g = acc.grid
    poly = g.polygon
    X = g.centres
    d = C - X
    rng = np.linalg.norm(d, axis=1)
    cos = (d @ poly.normal) / rng
    front = cos > 1e-3
    if not front.any():
        return
    idx = np.flatnonzero(front)
    uv, z, ok = cam.project(X[idx], R_wc, C)
    W, H = cam.width, cam.height
    with np.errstate(invalid="ignore"):
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
    idx, uv, z = idx[ok], uv[ok], z[ok]
    if len(idx) == 0:
        return
    ur, vr = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
    at_centre = buf.centre[vr, ur] == poly.index
    gsd = rng[idx] / cam.f
    w = cos[idx] / gsd**2
    angle = np.degrees(np.arccos(np.clip(cos[idx], -1, 1)))
    edge = buf.edge_dist[vr, ur]
    # what the best centre-visible frame saw (for texels never clean: their class)
    s = idx[at_centre]
    better = w[at_centre] > acc.seen_w[s]
    acc.seen[s] = True
    acc.seen_w[s[better]] = w[at_centre][better]
    acc.seen_attr[s[better]] = np.stack([angle, gsd, edge], 1)[at_centre][better]
    # the clean-observation test
    r = o.footprint_ring_px
    m = o.margin_px
    keep = at_centre & (cos[idx] >= np.cos(np.radians(o.grazing_limit_deg)))
    keep &= (uv[:, 0] >= max(m, r)) & (uv[:, 0] < W - 1 - max(m, r)) & (uv[:, 1] >= max(m, r))
    keep &= uv[:, 1] < H - 1 - max(m, r)
    # the margin keeps the whole (2 + 2r)² block inside the image
    test = np.flatnonzero(keep)
    u0 = np.floor(uv[test, 0]).astype(np.int64)
    v0 = np.floor(uv[test, 1]).astype(np.int64)
    own = group[poly.index]
    clean = np.ones(len(test), bool)
    for dv in range(-r, 2 + r):
        for du in range(-r, 2 + r):
            pid = buf.pure[v0 + dv, u0 + du]
            clean &= (pid >= 0) & (group[np.maximum(pid, 0)] == own)
    keep[test] = clean
    zb = buf.depth[vr, ur]
    keep &= np.abs(zb - z) <= o.depth_tolerance * z + o.depth_tolerance_m
    if not keep.any():
        return
    vals = bilinear(load(), uv[keep])
    acc.parts.append(
        (
            idx[keep],
            np.full(int(keep.sum()), frame, np.int32),
            vals,
            w[keep],
            angle[keep],
            gsd[keep],
            edge[keep],
        )
    )


def _fuse(acc: _Acc, o: ReferenceOptions) -> RefTexture:
    """Fuse the accumulated observations per texel (module docstring: sharpest views, robust
    rejection, weighted mean) into the surface's `RefTexture`."""
    n = len(acc.grid.rows)
    value = np.full(n, np.nan, np.float32)
    count = np.zeros(n, np.int32)
    best = np.full(n, -1, np.int32)
    attr = acc.seen_attr.copy()
    attr[~acc.seen] = np.nan
    if not acc.parts:
        e = np.zeros(0, np.int64)
        return RefTexture(acc.grid, value, count, acc.seen, best, attr[:, 0], attr[:, 1], attr[:, 2], e,
                          e.astype(np.int32), e.astype(bool))  # fmt: skip
    all_tex, all_frm, val, w, ang, gsd, edge = (np.concatenate(c) for c in zip(*acc.parts, strict=True))
    # only views about as sharp as the texel's sharpest (footprint on the surface gsd / cos θ)
    foot = gsd / np.cos(np.radians(ang))
    sharpest = np.full(n, np.inf)
    np.minimum.at(sharpest, all_tex, foot)
    sel = np.flatnonzero(foot <= o.resolution_ratio * sharpest[all_tex])
    order = sel[np.lexsort((val[sel], all_tex[sel]))]
    tex, frm, val, w, ang, gsd, edge = (a[order] for a in (all_tex, all_frm, val, w, ang, gsd, edge))
    starts = np.flatnonzero(np.r_[True, tex[1:] != tex[:-1]])
    sizes = np.diff(np.r_[starts, len(tex)])
    group = np.repeat(np.arange(len(starts)), sizes)

    def group_median(sorted_vals: np.ndarray) -> np.ndarray:
        lo = starts + (sizes - 1) // 2
        hi = starts + sizes // 2
        return 0.5 * (sorted_vals[lo] + sorted_vals[hi])

    med = group_median(val)  # values are sorted within each texel
    dev = np.abs(val - med[group])
    mad = group_median(dev[np.lexsort((dev, group))])
    sigma = np.maximum(1.4826 * mad, o.sigma_floor_k)
    kept = dev <= o.outlier_sigmas * sigma[group]
    wk = np.where(kept, w, 0.0)
    sw = np.bincount(group, wk, len(starts))
    mean = np.bincount(group, wk * val, len(starts)) / sw
    texels = tex[starts]
    value[texels] = mean.astype(np.float32)
    count[texels] = np.bincount(group, kept, len(starts)).astype(np.int32)
    # best kept observation per texel: the largest weight
    score = np.where(kept, w, -1.0)
    top = np.lexsort((score, group))
    last = np.r_[starts[1:], len(tex)] - 1
    pick = top[last]
    best[texels] = frm[pick]
    attr[texels] = np.stack([ang[pick], gsd[pick], edge[pick]], 1)
    kept_all = np.zeros(len(all_tex), bool)
    kept_all[order] = kept
    return RefTexture(
        acc.grid, value, count, acc.seen, best, attr[:, 0], attr[:, 1], attr[:, 2],
        all_tex.astype(np.int64), all_frm, kept_all,
    )  # fmt: skip


def reference_textures(
    polygons: list[ScenePolygon],
    surfaces: Collection[str] | None,
    camera: RefCamera,
    poses: Sequence[tuple[np.ndarray, np.ndarray]],
    load_frame: FrameLoader,
    options: ReferenceOptions = ReferenceOptions(),
    ground_z: float | RefGround | None = None,
) -> dict[str, RefTexture]:
    """Texture `surfaces` (polygon ids; None: every polygon) of the scene `polygons` from the
    frames `0 .. len(poses)-1` with poses `(R_wc (3, 3), C (3,))`; every polygon of `polygons`
    (and the ground: the plane at `ground_z`, or a `RefGround` terrain) occludes. Returns
    polygon id -> `RefTexture` for every surface that some frame's view frustum reaches from its
    front side (observed or not); the others are seen by no frame."""
    accs, _ = _accumulate(polygons, surfaces, camera, poses, load_frame, options, ground_z, halves=False)
    return {a[0].grid.polygon.polygon_id: _fuse(a[0], options) for a in accs.values()}


def reference_half_textures(
    polygons: list[ScenePolygon],
    surfaces: Collection[str] | None,
    camera: RefCamera,
    poses: Sequence[tuple[np.ndarray, np.ndarray]],
    load_frame: FrameLoader,
    options: ReferenceOptions = ReferenceOptions(),
    ground_z: float | RefGround | None = None,
) -> tuple[dict[str, tuple[RefTexture, RefTexture]], dict[str, list[int]]]:
    """As `reference_textures`, but each surface textured twice, from the even and from the odd
    half of its building's frames. Returns polygon id -> `(even, odd)` textures on one `RefGrid`,
    and building id -> the frames that see it (recording order; even half = positions 0, 2, ...)
    for the buildings of the wanted surfaces.

    The halves follow the product's split-half rule (`citytherm run --split-half`): alternate
    frames of those that see the building, in recording order (the 1st, 3rd, ... and the 2nd,
    4th, ...). "Sees the building" is the reference's own: at least `options.sees_min_pixels`
    pixel centres of the frame's z-buffer show the building's (top-level building, parts
    included) polygons. A frame that does not see the building adds nothing to its surfaces.
    """
    accs, frames = _accumulate(polygons, surfaces, camera, poses, load_frame, options, ground_z, halves=True)
    tex = {a[0].grid.polygon.polygon_id: (_fuse(a[0], options), _fuse(a[1], options)) for a in accs.values()}
    wanted = {polygons[i].building_id for i in accs}
    return tex, {b: f for b, f in frames.items() if b in wanted}


def _new_acc(g: RefGrid) -> _Acc:
    """An empty accumulator on grid `g`."""
    n = len(g.rows)
    return _Acc(g, [], np.zeros(n, bool), np.zeros(n), np.full((n, 3), np.nan))


def _accumulate(
    polygons: list[ScenePolygon],
    surfaces: Collection[str] | None,
    camera: RefCamera,
    poses: Sequence[tuple[np.ndarray, np.ndarray]],
    load_frame: FrameLoader,
    options: ReferenceOptions,
    ground_z: float | RefGround | None,
    halves: bool,
) -> tuple[dict[int, tuple[_Acc, ...]], dict[str, list[int]]]:
    """The observations of every wanted surface a frame may see (see `reference_textures`):
    polygon index -> one accumulator, or (`halves`) two, the even and the odd half of the
    frames that see the polygon's building (`reference_half_textures`); and (`halves`) building
    id -> the frames rendered that see it, recording order (empty without `halves`)."""
    zbuf = ZBuffer(camera, polygons, ground_z)
    group = coplanar_groups(polygons) if options.coplanar_ok else np.arange(len(polygons))
    wanted = np.array([surfaces is None or p.polygon_id in surfaces for p in polygons], bool)
    building_of = np.array([p.building_id for p in polygons], dtype=object)
    # halves: a frame that may see any polygon of a wanted surface's building is rendered, so that
    # every frame that sees the building is counted, whichever of its polygons are wanted
    render_for = np.isin(building_of, list(set(building_of[wanted]))) if halves else wanted
    seen_by: dict[str, list[int]] = {}  # building id -> frames so far that see it (halves)
    accs: dict[int, tuple[_Acc, ...] | None] = {}  # grids are laid when a frame first may see the surface
    for k, (R_wc, C) in enumerate(poses):
        R_wc, C = np.asarray(R_wc, np.float64), np.asarray(C, np.float64)
        near = [int(i) for i in zbuf.candidates(R_wc, C) if render_for[i]]
        near = [i for i in near if polygons[i].normal @ C > polygons[i].offset]  # camera in front
        cand = [i for i in near if wanted[i]]
        for i in cand:
            if i not in accs:
                g = ref_grid(polygons[i], options.texels_per_m)
                accs[i] = None if g is None else tuple(_new_acc(g) for _ in range(2 if halves else 1))
        cand = [i for i in cand if accs[i] is not None]
        if not (cand or (halves and near)):
            continue
        buf = zbuf.render(R_wc, C)
        half: dict[str, int] = {}
        if halves:
            ids, counts = np.unique(buf.centre, return_counts=True)
            pixels: dict[str, int] = {}
            for i, c in zip(ids[ids >= 0], counts[ids >= 0], strict=True):
                pixels[building_of[i]] = pixels.get(building_of[i], 0) + int(c)
            for b in sorted(b for b, c in pixels.items() if c >= options.sees_min_pixels):
                seen = seen_by.setdefault(b, [])
                half[b] = len(seen) % 2
                seen.append(k)
        frame: list[np.ndarray] = []

        def load(k: int = k, frame: list[np.ndarray] = frame) -> np.ndarray:
            if not frame:
                frame.append(np.asarray(load_frame(k), dtype=np.float32))
            return frame[0]

        for i in cand:
            b = polygons[i].building_id
            if halves and b not in half:
                continue  # the frame does not see the building (as the product: not in its unit)
            acc = accs[i][half[b] if halves else 0]  # type: ignore[index]
            _observe(acc, k, buf, load, camera, R_wc, C, group, options)
    return {i: a for i, a in accs.items() if a is not None}, seen_by

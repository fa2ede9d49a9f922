"""Geometry encoding between the domain dataclasses and PostGIS, vectorised over batches.

In: `Polygon`s / `Building`s (`workers/pipeline/geometry/citymodel.py`), coordinates in the model CRS
(metres). Out: hex EWKB strings with the model SRID (what PostGIS parses from text input and
COPY), plane figures per polygon, footprints and 3DCityDB-style envelopes; and back: WKB of a
`POLYGON Z` -> rings `(N, 3)` float64, bit-exact (EWKB carries IEEE doubles unchanged).

Rings are written exactly as read; a ring that was not closed is closed for PostGIS (which refuses
open rings) and flagged so the export can drop the closing vertex again. A polygon with a ring of
fewer than 3 distinct vertices cannot be held by PostGIS: it gets no geometry (NULL) and its rings
are kept as JSON instead.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import shapely

from workers.pipeline.geometry.citymodel import Building, Polygon

__all__ = [
    "EncodedPolygons",
    "encode_envelope",
    "encode_footprints",
    "encode_linestring_z",
    "encode_point_z",
    "encode_polygon_z",
    "encode_polygons",
    "polygon_rings_from_wkb",
]

_WKB_Z = 0x80000000
_WKB_SRID = 0x20000000
_POINT, _LINESTRING, _POLYGON = 1, 2, 3
#: polygons whose unit normal has z below this count as downward-facing (ground) for footprints.
_DOWNWARD_NZ = -0.5


def _header(geom_type: int, srid: int) -> bytes:
    return struct.pack("<BII", 1, geom_type | _WKB_Z | _WKB_SRID, srid)


def encode_polygon_z(rings: Sequence[np.ndarray], srid: int) -> str:
    """Closed rings (each `(N, 3)` float64, N ≥ 4, exterior first) -> hex EWKB `POLYGON Z`."""
    parts = [_header(_POLYGON, srid), struct.pack("<I", len(rings))]
    for r in rings:
        r = np.ascontiguousarray(r, dtype="<f8")
        parts.append(struct.pack("<I", r.shape[0]))
        parts.append(r.tobytes())
    return b"".join(parts).hex()


def encode_point_z(xyz: np.ndarray, srid: int) -> str:
    """`(3,)` -> hex EWKB `POINT Z`."""
    return (_header(_POINT, srid) + np.ascontiguousarray(xyz, dtype="<f8").reshape(3).tobytes()).hex()


def encode_linestring_z(points: np.ndarray, srid: int) -> str:
    """`(N, 3)`, N ≥ 2 -> hex EWKB `LINESTRING Z`."""
    p = np.ascontiguousarray(points, dtype="<f8").reshape(-1, 3)
    return (_header(_LINESTRING, srid) + struct.pack("<I", p.shape[0]) + p.tobytes()).hex()


def encode_envelope(lo: np.ndarray, hi: np.ndarray, srid: int) -> str:
    """3D box `(3,)`, `(3,)` -> hex EWKB `POLYGON Z` through its corners as 3DCityDB stores an
    envelope: (x0 y0 z0, x1 y0 z0, x1 y1 z1, x0 y1 z1, x0 y0 z0)."""
    x0, y0, z0 = (float(v) for v in lo)
    x1, y1, z1 = (float(v) for v in hi)
    ring = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z1], [x0, y1, z1], [x0, y0, z0]])
    return encode_polygon_z([ring], srid)


@dataclass(frozen=True)
class EncodedPolygons:
    """Per polygon of a batch (in input order).

    Attributes:
        ewkb: hex EWKB `POLYGON Z` or None (PostGIS cannot hold the rings: see `raw_rings`).
        ring_closed: per polygon, per ring: was the ring closed in the input.
        normal: `(P, 3)` unit plane normals (right-hand rule of the exterior ring; NaN if degenerate).
        offset: `(P,)` plane offsets, `normal · x = offset`, metres.
        area: `(P,)` areas (exterior minus holes), m².
        planarity: `(P,)` largest distance of any vertex (all rings) from the plane, m.
        min_vertices: `(P,)` fewest vertices of any ring, closing vertex not counted.
        lo, hi: `(P, 3)` 3D bounds of each polygon (NaN for a polygon without vertices).
    """

    ewkb: list[str | None]
    ring_closed: list[list[bool]]
    normal: np.ndarray
    offset: np.ndarray
    area: np.ndarray
    planarity: np.ndarray
    min_vertices: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


@lru_cache(maxsize=4096)
def _u32_hex(n: int) -> str:
    return struct.pack("<I", n).hex()


def _polygons_ewkb(
    cat: np.ndarray,
    counts: Sequence[int],
    lengths: np.ndarray,
    starts: np.ndarray,
    closed: np.ndarray,
    srid: int,
) -> tuple[list[str | None], list[list[bool]]]:
    """Hex EWKB `POLYGON Z` per polygon from the concatenated closed rings `cat` `(V, 3)`
    (`counts`: rings per polygon; `lengths`, `starts`: vertices and first row of each ring), None
    for a polygon with a ring of fewer than 4 vertices; and the per-ring `closed` flags, grouped
    by polygon."""
    hexcat = np.ascontiguousarray(cat, dtype="<f8").tobytes().hex()
    header = _header(_POLYGON, srid).hex()
    closed_l, len_l, start_l = closed.tolist(), lengths.tolist(), starts.tolist()
    ewkb: list[str | None] = []
    closed_flags: list[list[bool]] = []
    r = 0
    head1 = header + _u32_hex(1)
    for cnt in counts:
        if cnt == 1:  # the usual polygon: one ring
            n, s0 = len_l[r], start_l[r]
            ewkb.append(head1 + _u32_hex(n) + hexcat[48 * s0 : 48 * (s0 + n)] if n >= 4 else None)
            closed_flags.append(closed_l[r : r + 1])
            r += 1
            continue
        ok = True
        pieces = [header, _u32_hex(cnt)]
        for j in range(r, r + cnt):
            n = len_l[j]
            ok = ok and n >= 4
            pieces.append(_u32_hex(n))
            pieces.append(hexcat[48 * start_l[j] : 48 * (start_l[j] + n)])
        ewkb.append("".join(pieces) if ok else None)
        closed_flags.append(closed_l[r : r + cnt])
        r += cnt
    return ewkb, closed_flags


def encode_polygons(polygons: Sequence[Polygon], srid: int) -> EncodedPolygons:
    """Encode a batch of polygons and compute their planes (Newell's method, vectorised)."""
    n_poly = len(polygons)
    if n_poly == 0:
        e, e3 = np.zeros(0), np.zeros((0, 3))
        return EncodedPolygons([], [], e3, e, e, e, np.zeros(0, dtype=np.int64), e3, e3)
    rings_all = [r.coords for p in polygons for r in p.rings]
    counts = [len(p.interiors) + 1 for p in polygons]
    ring_poly_a = np.repeat(np.arange(n_poly), counts)
    ext = np.zeros(len(rings_all), dtype=bool)
    ext[np.cumsum([0, *counts[:-1]]).astype(np.int64)] = True
    raw_len = np.array([len(c) for c in rings_all], dtype=np.int64)
    cat = np.concatenate(rings_all, axis=0).astype(np.float64, copy=False) if rings_all else np.zeros((0, 3))
    raw_start = np.concatenate([[0], np.cumsum(raw_len)[:-1]]).astype(np.int64)
    nonempty = raw_len > 0
    first = cat[np.where(nonempty, raw_start, 0)] if len(cat) else np.zeros((len(raw_len), 3))
    last = cat[np.where(nonempty, raw_start + raw_len - 1, 0)] if len(cat) else first
    closed = nonempty & (raw_len >= 2) & np.all(first == last, axis=1)
    lengths = raw_len.copy()
    if not closed[nonempty].all():
        # close the open rings (PostGIS refuses them): rebuild the concatenation with the first vertex
        parts = []
        for c, is_closed in zip(rings_all, closed.tolist(), strict=True):
            parts.append(c if is_closed or len(c) == 0 else np.vstack([c, c[:1]]))
        cat = np.concatenate(parts, axis=0).astype(np.float64, copy=False)
        lengths = np.array([len(c) for c in parts], dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    ewkb, closed_flags = _polygons_ewkb(cat, counts, lengths, starts, closed, srid)
    normal = np.full((n_poly, 3), np.nan)
    offset = np.full(n_poly, np.nan)
    area = np.full(n_poly, np.nan)
    planarity = np.full(n_poly, np.nan)
    min_vertices = np.zeros(n_poly, dtype=np.int64)
    lo = np.full((n_poly, 3), np.nan)
    hi = np.full((n_poly, 3), np.nan)
    keep = lengths > 0
    if not keep.any():
        return EncodedPolygons(ewkb, closed_flags, normal, offset, area, planarity, min_vertices, lo, hi)
    lengths, starts, ring_poly_a, ext = lengths[keep], starts[keep], ring_poly_a[keep], ext[keep]
    abs_pts = cat
    # centre each ring on its first vertex: large UTM coordinates lose no precision in the products
    pts = cat - np.repeat(cat[starts], lengths, axis=0)
    a, b = pts[:-1], pts[1:]
    terms = np.stack(
        [
            (a[:, 1] - b[:, 1]) * (a[:, 2] + b[:, 2]),
            (a[:, 2] - b[:, 2]) * (a[:, 0] + b[:, 0]),
            (a[:, 0] - b[:, 0]) * (a[:, 1] + b[:, 1]),
        ],
        axis=1,
    )
    # drop the pair joining the last vertex of one ring to the first of the next
    edge_ok = np.ones(len(terms), dtype=bool)
    edge_ok[(starts[1:] - 1)] = False
    terms[~edge_ok] = 0.0
    terms = np.vstack([terms, np.zeros((1, 3))])
    newell = np.add.reduceat(terms, starts, axis=0)  # (R, 3), length = 2 × area
    ring_area = 0.5 * np.linalg.norm(newell, axis=1)
    # exterior ring centroid (distinct vertices: closing vertex excluded)
    sums = np.add.reduceat(abs_pts, starts, axis=0) - abs_pts[starts + lengths - 1]
    centroid = sums / np.maximum(lengths - 1, 1)[:, None]
    ext_idx = np.flatnonzero(ext)
    n_len = np.linalg.norm(newell[ext_idx], axis=1)
    good = n_len > 1e-12
    pk = ring_poly_a[ext_idx]
    unit = np.where(good[:, None], newell[ext_idx] / np.where(good, n_len, 1.0)[:, None], np.nan)
    normal[pk] = unit
    offset[pk] = np.einsum("ij,ij->i", unit, centroid[ext_idx])
    area_acc = np.zeros(n_poly)
    np.add.at(area_acc, ring_poly_a, np.where(ext, ring_area, -ring_area))
    area[pk] = area_acc[pk]
    # non-planarity: max |n · x - offset| over every vertex of the polygon (rings are contiguous)
    vert_poly = np.repeat(ring_poly_a, lengths)
    dist = np.abs(np.einsum("ij,ij->i", abs_pts, normal[vert_poly]) - offset[vert_poly])
    poly_start = np.concatenate([[0], np.flatnonzero(np.diff(vert_poly)) + 1])
    planarity[vert_poly[poly_start]] = np.maximum.reduceat(dist, poly_start)
    lo[vert_poly[poly_start]] = np.minimum.reduceat(abs_pts, poly_start, axis=0)
    hi[vert_poly[poly_start]] = np.maximum.reduceat(abs_pts, poly_start, axis=0)
    min_vertices[:] = np.iinfo(np.int64).max
    np.minimum.at(min_vertices, ring_poly_a, lengths - 1)
    min_vertices[min_vertices == np.iinfo(np.int64).max] = 0
    return EncodedPolygons(ewkb, closed_flags, normal, offset, area, planarity, min_vertices, lo, hi)


def _ground(building: Building, normals: dict[str, np.ndarray]) -> list[Polygon]:
    """The polygons making the footprint: ground surfaces, else downward-facing polygons."""
    polys = list(building.iter_polygons())
    ground = [p for p in polys if p.surface_class == "GroundSurface"]
    if not ground:
        ground = [p for p in polys if p.id in normals and normals[p.id][2] < _DOWNWARD_NZ]
    return [p for p in ground if len(p.exterior.coords) >= 3]


def _shapes_2d(polys: Sequence[Polygon]) -> list[shapely.Geometry | None]:
    """2D shapely polygons of `polys` (z dropped), made valid; None where degenerate. Polygons
    without holes are built in one vectorised call."""
    out: list[shapely.Geometry | None] = [None] * len(polys)
    simple = [k for k, p in enumerate(polys) if not p.interiors]
    if simple:
        coords = np.concatenate([polys[k].exterior.coords[:, :2] for k in simple], axis=0)
        idx = np.repeat(np.arange(len(simple)), [len(polys[k].exterior.coords) for k in simple])
        try:
            geoms = shapely.polygons(shapely.linearrings(coords, indices=idx))
        except (ValueError, shapely.errors.GEOSException):
            geoms = None
        if geoms is not None:
            for k, g in zip(simple, geoms, strict=True):
                out[k] = g
    for k, p in enumerate(polys):
        if out[k] is None:
            try:
                out[k] = shapely.Polygon(p.exterior.coords[:, :2], [h.coords[:, :2] for h in p.interiors])
            except (ValueError, shapely.errors.GEOSException):
                out[k] = None
    arr = np.array(out, dtype=object)
    ok = np.array([g is not None for g in out], dtype=bool)
    if ok.any():
        bad = ok.copy()
        bad[ok] = ~shapely.is_valid(arr[ok])
        if bad.any():
            arr[bad] = shapely.make_valid(arr[bad])
    return [None if g is None or g.is_empty or g.area <= 0 else g for g in arr]


def encode_footprints(
    buildings: Sequence[Building], normals: dict[str, np.ndarray], srid: int
) -> list[str | None]:
    """Hex EWKB `MULTIPOLYGON` footprints (2D, SRID set) per building, None where there is none:
    the union of its ground surfaces (parts included), else of its downward-facing polygons,
    else the convex hull of all its vertices; always valid.

    `normals` maps polygon id -> unit normal `(3,)` (from `encode_polygons`)."""
    if not buildings:
        return []
    grounds = [_ground(b, normals) for b in buildings]
    shapes = _shapes_2d([p for g in grounds for p in g])
    merged: list[shapely.Geometry | None] = []
    k = 0
    for b, g in zip(buildings, grounds, strict=True):
        mine = [s for s in shapes[k : k + len(g)] if s is not None]
        k += len(g)
        if len(mine) == 1:
            merged.append(mine[0])
        elif mine:
            merged.append(shapely.union_all(mine))
        else:
            rings = [r.coords[:, :2] for p in b.iter_polygons() for r in p.rings]
            merged.append(shapely.MultiPoint(np.concatenate(rings, axis=0)).convex_hull if rings else None)
    return _multipolygon_wkb(merged, srid)


def _multipolygon_wkb(merged: Sequence[shapely.Geometry | None], srid: int) -> list[str | None]:
    """Each geometry made valid and reduced to its polygons of positive area -> hex EWKB 2D
    `MULTIPOLYGON` with `srid`; None where nothing is left. Vectorised for the usual case (one
    valid polygon)."""
    arr = np.array(merged, dtype=object)
    have = np.flatnonzero(np.array([g is not None for g in merged], dtype=bool))
    geoms: list[shapely.Geometry | None] = [None] * len(merged)
    if len(have):
        sub = arr[have]
        bad = ~shapely.is_valid(sub)
        if bad.any():
            sub[bad] = shapely.make_valid(sub[bad])
        is_poly = shapely.get_type_id(sub) == shapely.GeometryType.POLYGON
        area_ok = shapely.area(sub) > 0
        simple = np.flatnonzero(is_poly & area_ok)
        if len(simple):
            multi = shapely.multipolygons(sub[simple], indices=np.arange(len(simple)))
            for j, g in zip(have[simple].tolist(), multi, strict=True):
                geoms[j] = g
        for j in np.flatnonzero(~is_poly).tolist():
            parts = [x for x in shapely.get_parts(sub[j]) if x.geom_type == "Polygon" and x.area > 0]
            geoms[have[j]] = shapely.MultiPolygon(parts) if parts else None
    out_arr = shapely.set_srid(np.array(geoms, dtype=object), srid)
    out = shapely.to_wkb(out_arr, hex=True, include_srid=True, output_dimension=2)
    return [None if g is None else str(o) for g, o in zip(geoms, out, strict=True)]


def polygon_rings_from_wkb(wkb: bytes | memoryview) -> list[np.ndarray]:
    """(E)WKB `POLYGON Z` -> rings, each `(N, 3)` float64 (exterior first); bit-exact."""
    buf = bytes(wkb)
    order = "<" if buf[0] == 1 else ">"
    (gtype,) = struct.unpack_from(order + "I", buf, 1)
    pos = 5
    if gtype & _WKB_SRID:
        pos += 4
    base = gtype & 0x0FFFFFFF
    has_z = bool(gtype & _WKB_Z) or base // 1000 in (1, 3)
    if base % 1000 != _POLYGON:
        raise ValueError(f"expected a POLYGON in WKB, got type {gtype:#x}")
    dim = 3 if has_z else 2
    (nrings,) = struct.unpack_from(order + "I", buf, pos)
    pos += 4
    rings = []
    dt = np.dtype(order + "f8")
    for _ in range(nrings):
        (n,) = struct.unpack_from(order + "I", buf, pos)
        pos += 4
        c = np.frombuffer(buf, dtype=dt, count=n * dim, offset=pos).reshape(n, dim).astype(np.float64)
        pos += 8 * n * dim
        if dim == 2:
            c = np.hstack([c, np.zeros((n, 1))])
        rings.append(c)
    return rings

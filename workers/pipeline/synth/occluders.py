"""Occluders the city model lacks: street trees and parked cars of a synthetic scene.

Real drives see facades through trees and past parked cars; no LoD2 model holds them. They hide
parts of the facades, carry their own thermal texture (leaves near the air temperature, a warm
engine hood) and move against the facades with parallax, so features tracked on them and edges
next to them are wrong for a model-based orientation (issue 19, the paper's table 1: orientation
with and without model knowledge, on a scene with occluders the model lacks).

In: the ground path of the platform `(K, 2)` (model CRS, metres, a closed loop for drives), the
buildings' footprints (shapely, x/y), the ground plane height `ground_z` (m), `OccluderOptions`
and a seed. Out: `Occluders`: one triangle mesh in world coordinates (model CRS, metres) with a
temperature per triangle (K) and the list of placed objects (kind, centre, size) for the truth.

Placement: along the path every `spacing` metres (drawn from the densities), on the side of the
nearest building: cars at `car_offset_m` from the path (parked at the kerb, long axis along the
path), trees at `tree_offset_m` (between the kerb and the facades); a candidate whose outline
comes closer than `clearance_m` to a footprint, to the path or to an object already placed is
dropped. Flights (`platform` not a drive) get trees only, at random points within
`flight_radius_m` of the path's centre, outside the footprints (density per hectare).

Shapes: a tree is a trunk (octagonal prism, radius 0.15–0.25 m, up to the crown) under a crown
(an icosphere of 80 faces, radius and centre height drawn from the options); a car is a box
(4.4 × 1.8 m, 1.45 m high) whose top front third is the hood. Temperatures per triangle: the
crown `tree_k` plus Gaussian leaf noise `tree_noise_k` (independent per triangle: a speckled
texture), the trunk `tree_k + 0.5`, the car body `car_k`, the hood `car_hood_k`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import shapely

from workers.pipeline.synth.common import SynthError, rng_for

#: `Occluders.kind` codes per triangle
TREE_CROWN, TREE_TRUNK, CAR_BODY, CAR_HOOD = 0, 1, 2, 3


@dataclass(frozen=True)
class OccluderOptions:
    """Densities, sizes and temperatures of the occluders (see the module docstring)."""

    trees_per_100m: float = 3.0  # along a drive's path
    cars_per_100m: float = 5.0
    trees_per_hectare: float = 12.0  # flights: within `flight_radius_m` of the path's centre
    flight_radius_m: float = 120.0
    tree_offset_m: float = 6.0  # crown centre from the path's centre line
    car_offset_m: float = 3.2  # car centre from the path's centre line
    crown_radius_m: tuple[float, float] = (1.6, 2.8)
    crown_height_m: tuple[float, float] = (5.0, 8.0)  # crown centre above the ground
    clearance_m: float = 0.6  # from footprints, the path and other objects
    tree_k: float = 271.8
    tree_noise_k: float = 0.8
    car_k: float = 272.8
    car_hood_k: float = 283.0

    def __post_init__(self) -> None:
        for name in ("trees_per_100m", "cars_per_100m", "trees_per_hectare", "tree_noise_k"):
            if getattr(self, name) < 0:
                raise SynthError(f"occluders {name} must be >= 0, got {getattr(self, name)}")
        for name in ("crown_radius_m", "crown_height_m"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise SynthError(f"occluders {name} must be 0 < low <= high, got {(lo, hi)}")


@dataclass(frozen=True, eq=False)
class Occluders:
    """A triangle mesh of placed occluders.

    Attributes:
        vertices: `(V, 3)` float64 world coordinates (model CRS, metres).
        triangles: `(T, 3)` int32 vertex indices.
        temperature: `(T,)` float32 kelvin per triangle.
        kind: `(T,)` int8 per triangle (`TREE_CROWN`, `TREE_TRUNK`, `CAR_BODY`, `CAR_HOOD`).
        items: per placed object `{"kind": "tree"|"car", "center": [x, y, z], "size": [...]}`
            (tree: crown radius, crown centre height above ground; car: length, width, height,
            heading in degrees from +x).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    temperature: np.ndarray
    kind: np.ndarray
    items: tuple[dict, ...] = field(default_factory=tuple)

    def __len__(self) -> int:
        return len(self.items)


def _icosphere() -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere with one subdivision: vertices `(42, 3)`, triangles `(80, 3)`."""
    t = (1.0 + 5**0.5) / 2.0
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
         (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]  # fmt: skip
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
         (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]  # fmt: skip
    verts = [np.asarray(p, float) / np.linalg.norm(p) for p in v]
    mid: dict[tuple[int, int], int] = {}

    def middle(a: int, b: int) -> int:
        key = (min(a, b), max(a, b))
        if key not in mid:
            m = verts[a] + verts[b]
            verts.append(m / np.linalg.norm(m))
            mid[key] = len(verts) - 1
        return mid[key]

    faces = []
    for a, b, c in f:
        ab, bc, ca = middle(a, b), middle(b, c), middle(c, a)
        faces += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
    return np.asarray(verts), np.asarray(faces, np.int32)


_SPHERE = _icosphere()


def _prism(
    center: np.ndarray, radius: float, z0: float, z1: float, n: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """Closed-side prism (no caps) of `n` sides: vertices `(2n, 3)`, triangles `(2n, 3)`."""
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([center[0] + radius * np.cos(a), center[1] + radius * np.sin(a)], axis=1)
    verts = np.concatenate([np.c_[ring, np.full(n, z0)], np.c_[ring, np.full(n, z1)]])
    i = np.arange(n)
    j = (i + 1) % n
    tris = np.concatenate([np.stack([i, j, n + j], 1), np.stack([i, n + j, n + i], 1)])
    return verts, tris.astype(np.int32)


def _box(
    center: np.ndarray, size: tuple[float, float, float], heading: float, z0: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box on the ground (`z0`) with its long axis along `heading` (rad from +x): vertices
    `(8, 3)`, triangles `(12, 3)` and whether each triangle belongs to the top front third (the
    hood: the top face's triangles whose centroid lies in the front third)."""
    length, width, height = size
    c, s = np.cos(heading), np.sin(heading)
    u, v = np.array([c, s]), np.array([-s, c])
    corners = [
        center + a * 0.5 * length * u + b * 0.5 * width * v for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))
    ]
    verts = np.array([[*p, z] for z in (z0, z0 + height) for p in corners])
    quads = [(0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    tris = np.array([t for a, b, cc, d in quads for t in ((a, b, cc), (a, cc, d))], np.int32)
    top = np.zeros(len(tris), bool)
    top[2:4] = True  # the top quad (4, 5, 6, 7)
    cent = verts[tris].mean(axis=1)[:, :2] - center
    hood = top & (cent @ u > length / 6.0)
    return verts, tris, hood


class _Builder:
    """Accumulates the occluders' triangles."""

    def __init__(self) -> None:
        self.verts: list[np.ndarray] = []
        self.tris: list[np.ndarray] = []
        self.temp: list[np.ndarray] = []
        self.kind: list[np.ndarray] = []
        self.n = 0

    def add(self, verts: np.ndarray, tris: np.ndarray, temp: np.ndarray, kind: np.ndarray) -> None:
        self.verts.append(verts)
        self.tris.append(tris + self.n)
        self.temp.append(np.asarray(temp, np.float32))
        self.kind.append(np.asarray(kind, np.int8))
        self.n += len(verts)

    def build(self, items: list[dict]) -> Occluders:
        if not self.verts:
            return Occluders(np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros(0, np.float32),
                             np.zeros(0, np.int8), ())  # fmt: skip
        return Occluders(
            np.concatenate(self.verts), np.concatenate(self.tris).astype(np.int32),
            np.concatenate(self.temp), np.concatenate(self.kind), tuple(items),
        )  # fmt: skip


def _tree(b: _Builder, xy: np.ndarray, ground_z: float, o: OccluderOptions, rng: np.random.Generator) -> dict:
    """One tree at `xy` (crown centre above it); its truth item."""
    r = float(rng.uniform(*o.crown_radius_m))
    h = float(rng.uniform(*o.crown_height_m))
    sv, st = _SPHERE
    crown = np.c_[xy[0] + r * sv[:, 0], xy[1] + r * sv[:, 1], ground_z + h + 0.8 * r * sv[:, 2]]
    leaves = o.tree_k + o.tree_noise_k * rng.standard_normal(len(st))
    b.add(crown, st, leaves, np.full(len(st), TREE_CROWN))
    tv, tt = _prism(xy, float(rng.uniform(0.15, 0.25)), ground_z, ground_z + h - 0.5 * r)
    b.add(tv, tt, np.full(len(tt), o.tree_k + 0.5), np.full(len(tt), TREE_TRUNK))
    return {"kind": "tree", "center": [float(xy[0]), float(xy[1]), ground_z + h], "size": [r, h]}


def _car(b: _Builder, xy: np.ndarray, heading: float, ground_z: float, o: OccluderOptions) -> dict:
    """One car at `xy` along `heading` (rad); its truth item."""
    size = (4.4, 1.8, 1.45)
    verts, tris, hood = _box(xy, size, heading, ground_z)
    temp = np.where(hood, o.car_hood_k, o.car_k)
    b.add(verts, tris, temp, np.where(hood, CAR_HOOD, CAR_BODY))
    return {"kind": "car", "center": [float(xy[0]), float(xy[1]), ground_z + 0.5 * size[2]],
            "size": [*size, float(np.degrees(heading))]}  # fmt: skip


def _free(
    shape: shapely.Geometry, blocked: shapely.Geometry | None, placed: list[shapely.Geometry], gap: float
) -> bool:
    """Whether `shape` keeps `gap` from the blocked area and from every placed outline."""
    if blocked is not None and shape.distance(blocked) < gap:
        return False
    return all(shape.distance(p) >= gap for p in placed)


def place_occluders(
    path_xy: np.ndarray,
    footprints: Sequence[shapely.Geometry],
    ground_z: float,
    options: OccluderOptions,
    seed: int,
    drive: bool = True,
    height: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Occluders:
    """Trees and cars along `path_xy` `(K, 2)` (a drive's closed loop; `drive=False`: trees
    scattered around the path's centre), outside `footprints`; see the module docstring. Each
    stands on the ground `height(xy (N, 2)) -> (N,)` m at its centre (None: on `ground_z`)."""
    o = options

    def base(xy: np.ndarray) -> float:
        return ground_z if height is None else float(height(np.asarray(xy, float).reshape(1, 2))[0])

    rng = rng_for(seed, "occluders")
    path = np.asarray(path_xy, float)[:, :2]
    if len(path) < 2:
        raise SynthError("occluders need a path of at least 2 points")
    fps = (
        shapely.union_all([f for f in footprints if f is not None and not f.is_empty]) if footprints else None
    )
    line = shapely.LineString(path)
    b, items, placed = _Builder(), [], []
    if not drive:
        centre = path.mean(axis=0)
        n = rng.poisson(o.trees_per_hectare * np.pi * o.flight_radius_m**2 / 1e4)
        for _ in range(n):
            rad = o.flight_radius_m * np.sqrt(rng.uniform())
            ang = rng.uniform(0, 2 * np.pi)
            xy = centre + rad * np.array([np.cos(ang), np.sin(ang)])
            crown = shapely.Point(xy).buffer(o.crown_radius_m[1])
            if _free(crown, fps, placed, o.clearance_m):
                placed.append(crown)
                items.append(_tree(b, xy, base(xy), o, rng))
        return b.build(items)
    length = line.length
    crowns: list[shapely.Geometry] = []  # trees keep apart from each other by their crowns,
    bodies: list[shapely.Geometry] = []  # from cars and trunks by their bodies (crowns overhang cars)
    for kind, per_100m, offset in (
        ("car", o.cars_per_100m, o.car_offset_m),
        ("tree", o.trees_per_100m, o.tree_offset_m),
    ):
        if per_100m <= 0:
            continue
        spacing = 100.0 / per_100m
        s = float(rng.uniform(0, spacing))
        while s < length:
            p = np.asarray(line.interpolate(s).coords[0])
            q = np.asarray(line.interpolate(min(s + 0.5, length)).coords[0])
            tangent = q - p
            if np.linalg.norm(tangent) < 1e-6:
                tangent = p - np.asarray(line.interpolate(max(s - 0.5, 0.0)).coords[0])
            tangent /= max(np.linalg.norm(tangent), 1e-9)
            normal = np.array([-tangent[1], tangent[0]])
            sides = (normal, -normal)
            if fps is not None:  # the side of the nearest building first
                sides = tuple(sorted(sides, key=lambda n: fps.distance(shapely.Point(p + offset * n))))
            for n in sides:
                xy = p + offset * n
                if line.distance(shapely.Point(xy)) < offset - 0.5:
                    continue  # the path bends: too close to another stretch of it
                if kind == "car":
                    half = 0.5 * np.array([[-4.4, -1.8], [4.4, -1.8], [4.4, 1.8], [-4.4, 1.8]])
                    body = shapely.Polygon(xy + half[:, :1] * tangent + half[:, 1:] * normal)
                    if not _free(body, fps, bodies, o.clearance_m):
                        continue
                    bodies.append(body)
                    items.append(_car(b, xy, float(np.arctan2(tangent[1], tangent[0])), base(xy), o))
                else:
                    crown = shapely.Point(xy).buffer(o.crown_radius_m[1])
                    trunk = shapely.Point(xy).buffer(0.3)
                    if not (
                        _free(crown, fps, crowns, o.clearance_m) and _free(trunk, None, bodies, o.clearance_m)
                    ):
                        continue
                    crowns.append(crown)
                    bodies.append(trunk)
                    items.append(_tree(b, xy, base(xy), o, rng))
                break
            s += spacing * float(rng.uniform(0.6, 1.4))
    return b.build(items)

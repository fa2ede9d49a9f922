"""Model side of model-to-image coregistration: the visible wireframe of one building.

In: a top-level `Building` (its parts included), and per frame a `Camera`, a `Pose` and a
`RayCaster` built over the building and its neighbours. Out:

- `Wireframe` (frame-independent, built once per building): vertices merged within a
  tolerance, edges split at T-junctions and merged where adjacent polygons share them (the
  duplicated edges that were a main failure cause in Avbelj et al. 2012 are gone), creases
  between coplanar polygons of one surface class dropped (they have no image edge), every edge
  classed roof / wall / ground with a matching weight (ground edges are weak in TIR), and model
  corners: vertices where two or more non-collinear edges meet.
- `VisibleWireframe` (per frame and pose): sample points along the edges with hidden parts
  removed by ray casting against the whole scene (points offset off the surfaces along the
  edge's outward normal), edges facing away from the camera dropped, visible corners.

Coordinates: world = model CRS, metres; pixels with the camera's convention.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from workers.pipeline.geometry.camera import Camera
from workers.pipeline.geometry.citymodel import Building
from workers.pipeline.geometry.polygons import fit_plane, open_ring
from workers.pipeline.geometry.pose import Pose
from workers.pipeline.geometry.raycast import RayCaster, SceneMesh

ROOF, WALL, GROUND = 0, 1, 2
EDGE_CLASSES: tuple[str, ...] = ("roof", "wall", "ground")


class WireframeError(ValueError):
    """A building without usable geometry for a wireframe."""


@dataclass(frozen=True)
class EdgeOptions:
    """Parameters of the model wireframe and its per-frame visibility."""

    # vertices closer than this are one vertex; a vertex this close to an edge splits it, metres
    merge_tolerance_m: float = 0.02
    # an edge between two polygons of one class whose normals differ by less than this is a
    # crease of one planar surface (no image edge) and is dropped, degrees
    crease_angle_deg: float = 8.0
    # edges with both ends this close to the building's lowest point count as ground edges, metres
    ground_height_tolerance_m: float = 0.3
    # matching weights per class (roof, wall, ground)
    class_weights: tuple[float, float, float] = (1.0, 1.0, 0.3)
    # a vertex is a corner when two of its edges make an angle in [a, 180 - a], degrees
    corner_min_angle_deg: float = 25.0
    # sample spacing along projected edges, pixels (at the pose given for visibility)
    sample_spacing_px: float = 5.0
    # samples per edge: at least / at most
    min_samples_per_edge: int = 3
    max_samples_per_edge: int = 40
    # samples are moved this far off the surfaces (along the edge's outward normal), metres
    visibility_offset_m: float = 0.05
    # the ray stops this far short of the sample, metres
    visibility_tolerance_m: float = 0.05
    # weight factor of inner edges (both polygons facing the camera) against outline edges
    inner_weight: float = 0.5
    # samples within this many pixels of the frame border are dropped
    image_margin_px: float = 2.0
    # samples closer to the camera than this (along the optical axis) are dropped, metres
    min_depth_m: float = 0.5


@dataclass(frozen=True, eq=False)
class Wireframe:
    """Merged, classified wireframe of one building (world coordinates).

    Attributes:
        building_id: top-level building id.
        vertices: `(V, 3)` float64 merged vertices.
        edges: `(E, 2)` int vertex indices.
        edge_class: `(E,)` int8 `ROOF`, `WALL` or `GROUND`.
        edge_weight: `(E,)` float64 matching weight from the class.
        edge_normals: `(E, 2, 3)` unit outward normals of the (up to two) polygons sharing the edge
            (a second zero row when the edge borders one polygon only).
        corners: `(C,)` int vertex indices of the model corners.
    """

    building_id: str
    vertices: np.ndarray
    edges: np.ndarray
    edge_class: np.ndarray
    edge_weight: np.ndarray
    edge_normals: np.ndarray
    corners: np.ndarray

    @cached_property
    def edge_outward(self) -> np.ndarray:
        """`(E, 3)` unit mean outward normal of each edge's polygons (offset direction)."""
        s = self.edge_normals.sum(axis=1)
        n = np.linalg.norm(s, axis=1, keepdims=True)
        return np.where(n > 1e-9, s / np.maximum(n, 1e-12), 0.0)

    @cached_property
    def vertex_outward(self) -> np.ndarray:
        """`(V, 3)` unit mean outward direction of each vertex's edges (zeros for isolated ones)."""
        acc = np.zeros_like(self.vertices)
        np.add.at(acc, self.edges[:, 0], self.edge_outward)
        np.add.at(acc, self.edges[:, 1], self.edge_outward)
        return acc / np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-12)

    @cached_property
    def edge_vertices(self) -> tuple[np.ndarray, np.ndarray]:
        """The vertices the edges use, `(U,)` indices into `vertices`, and the edges on them
        `(E, 2)` (indices into the first): a part of a scene wireframe (`cull_wireframe`) keeps
        every vertex of the scene, its edges use few."""
        used, inv = np.unique(self.edges, return_inverse=True)
        return used, inv.reshape(self.edges.shape)


@dataclass(frozen=True, eq=False)
class VisibleWireframe:
    """The part of a wireframe one camera sees (world coordinates).

    Attributes:
        points: `(N, 3)` float64 visible sample points on the edges.
        edge: `(N,)` int index into `Wireframe.edges` of each sample.
        direction: `(N, 3)` unit world direction of each sample's edge.
        weight: `(N,)` class weight of each sample.
        corners: `(C,)` int vertex indices of visible corners.
        corner_points: `(C, 3)` their world coordinates.
        n_edges: number of edges with at least one visible sample.
    """

    points: np.ndarray
    edge: np.ndarray
    direction: np.ndarray
    weight: np.ndarray
    corners: np.ndarray
    corner_points: np.ndarray
    n_edges: int


def _merge_vertices(points: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Cluster points `(N, 3)` closer than `tol` -> (merged vertices `(V, 3)`, label `(N,)`)."""
    pairs = cKDTree(points).query_pairs(tol, output_type="ndarray")
    n = len(points)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    k, label = connected_components(graph, directed=False)
    sums = np.zeros((k, 3))
    np.add.at(sums, label, points)
    return sums / np.bincount(label, minlength=k)[:, None], label


def _split_at_vertices(
    verts: np.ndarray, edges: np.ndarray, owner: np.ndarray, tol: float
) -> tuple[np.ndarray, np.ndarray]:
    """Split edges `(E, 2)` at vertices lying on their interior (T-junctions); keep the owner polygon."""
    a, b = verts[edges[:, 0]], verts[edges[:, 1]]
    d = b - a
    L2 = np.maximum(np.einsum("ij,ij->i", d, d), 1e-18)
    # (E, V) parameters and distances of every vertex to every edge's line
    t = np.einsum("evk,ek->ev", verts[None, :, :] - a[:, None, :], d) / L2[:, None]
    foot = a[:, None, :] + t[..., None] * d[:, None, :]
    dist = np.linalg.norm(verts[None, :, :] - foot, axis=2)
    L = np.sqrt(L2)[:, None]
    on = (dist < tol) & (t * L > tol) & ((1 - t) * L > tol)
    if not on.any():
        return edges, owner
    out_e: list[np.ndarray] = []
    out_o: list[np.ndarray] = []
    for e in range(len(edges)):
        inner = np.nonzero(on[e])[0]
        if len(inner) == 0:
            out_e.append(edges[e : e + 1])
            out_o.append(owner[e : e + 1])
            continue
        chain = np.concatenate([[edges[e, 0]], inner[np.argsort(t[e, inner])], [edges[e, 1]]])
        out_e.append(np.stack([chain[:-1], chain[1:]], axis=1))
        out_o.append(np.full(len(chain) - 1, owner[e]))
    return np.concatenate(out_e), np.concatenate(out_o)


def building_wireframe(building: Building, options: EdgeOptions = EdgeOptions()) -> Wireframe:
    """The merged, classified wireframe of `building` (all rings of all polygons, parts included)."""
    ring_pts: list[np.ndarray] = []
    ring_poly: list[int] = []
    normals: list[np.ndarray] = []
    classes: list[str] = []
    for poly in building.iter_polygons():
        plane = fit_plane(poly)
        if plane is None:
            continue
        k = len(normals)
        normals.append(plane.normal)
        classes.append(poly.surface_class)
        for ring in poly.rings:
            p = open_ring(ring.coords)
            if len(p) >= 2:
                ring_pts.append(p)
                ring_poly.append(k)
    if not ring_pts:
        raise WireframeError(f"building {building.id!r} has no polygon with a valid plane")
    pts = np.concatenate(ring_pts)
    starts = np.cumsum([0] + [len(p) for p in ring_pts[:-1]])
    idx = np.concatenate([s + np.arange(len(p)) for s, p in zip(starts, ring_pts, strict=True)])
    nxt = np.concatenate([s + np.roll(np.arange(len(p)), -1) for s, p in zip(starts, ring_pts, strict=True)])
    owner = np.concatenate([np.full(len(p), k) for k, p in zip(ring_poly, ring_pts, strict=True)])
    return _wireframe(building.id, pts, idx, nxt, owner, np.asarray(normals), classes, options)


def mesh_wireframe(
    mesh: SceneMesh, options: EdgeOptions = EdgeOptions(), max_split: int = 2_000_000
) -> Wireframe:
    """The merged wireframe of every polygon in a `SceneMesh` (e.g. a building and its neighbours):
    the polygon outlines recovered from the triangles (edges used once within their polygon).
    Surface classes are unknown: edges of upward-facing polygons count as roof edges. T-junction
    splitting is skipped when edges × vertices exceeds `max_split`."""
    tri = np.asarray(mesh.triangles, dtype=np.int64)
    if len(tri) == 0:
        raise WireframeError("scene mesh has no triangles")
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    poly = np.tile(np.asarray(mesh.triangle_polygon, dtype=np.int64), 3)
    key = np.concatenate([poly[:, None], np.sort(e, axis=1)], axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    once = counts[inv.reshape(-1)] == 1
    e, poly = e[once], poly[once]
    pts = mesh.vertices.astype(np.float64) + mesh.origin
    normals = np.asarray(mesh.polygon_normals, dtype=np.float64)
    classes = ["unclassified"] * len(normals)
    return _wireframe("scene", pts, e[:, 0], e[:, 1], poly, normals, classes, options, max_split)


def _wireframe(
    wid: str,
    pts: np.ndarray,
    idx: np.ndarray,
    nxt: np.ndarray,
    owner: np.ndarray,
    poly_normals: np.ndarray,
    classes: list[str],
    options: EdgeOptions,
    max_split: int | None = None,
) -> Wireframe:
    """Merge segments `pts[idx] - pts[nxt]` of polygons `owner` (normals `(P, 3)`, classes) into a
    classified wireframe (see the module docstring)."""
    verts, label = _merge_vertices(pts, options.merge_tolerance_m)
    edges = np.stack([label[idx], label[nxt]], axis=1)
    keep = edges[:, 0] != edges[:, 1]
    edges, owner = edges[keep], owner[keep]
    if max_split is None or len(edges) * len(verts) <= max_split:
        edges, owner = _split_at_vertices(verts, edges, owner, options.merge_tolerance_m)
    key = np.sort(edges, axis=1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    E = len(uniq)
    edge_normals = np.zeros((E, 2, 3))
    n_adj = np.zeros(E, int)
    adj_classes: list[set[str]] = [set() for _ in range(E)]
    for j, e in enumerate(inv):
        if n_adj[e] < 2:
            edge_normals[e, n_adj[e]] = poly_normals[owner[j]]
        n_adj[e] += 1
        adj_classes[e].add(classes[owner[j]])
    # creases of one planar surface: two polygons, same class, (nearly) parallel normals
    cos_crease = np.cos(np.radians(options.crease_angle_deg))
    parallel = np.einsum("ij,ij->i", edge_normals[:, 0], edge_normals[:, 1]) > cos_crease
    crease = (n_adj == 2) & parallel & np.array([len(c) == 1 for c in adj_classes])
    z_min = verts[:, 2].min()
    low = np.all(verts[uniq][:, :, 2] < z_min + options.ground_height_tolerance_m, axis=1)
    cls = np.full(E, WALL, np.int8)
    for e in range(E):
        c = adj_classes[e]
        ups = edge_normals[e, : min(n_adj[e], 2), 2]
        if "GroundSurface" in c or low[e]:
            cls[e] = GROUND
        elif "RoofSurface" in c or (c <= {"unclassified"} and np.any(ups > 0.3)):
            cls[e] = ROOF
    keep = ~crease
    uniq, cls, edge_normals = uniq[keep], cls[keep], edge_normals[keep]
    weights = np.asarray(options.class_weights, dtype=np.float64)[cls]
    corners = _corners(verts, uniq, options.corner_min_angle_deg)
    return Wireframe(
        building_id=wid,
        vertices=verts,
        edges=uniq,
        edge_class=cls,
        edge_weight=weights,
        edge_normals=edge_normals,
        corners=corners,
    )


def _corners(verts: np.ndarray, edges: np.ndarray, min_angle_deg: float) -> np.ndarray:
    """Vertices where at least two edges meet at an angle in `[a, 180 - a]` -> `(C,)` indices."""
    d = verts[edges[:, 1]] - verts[edges[:, 0]]
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    lim = np.cos(np.radians(min_angle_deg))
    out = []
    for v in np.unique(edges):
        dirs = d[np.any(edges == v, axis=1)]
        if len(dirs) < 2:
            continue
        c = np.abs(dirs @ dirs.T)
        if np.any(c[np.triu_indices(len(dirs), 1)] < lim):
            out.append(v)
    return np.asarray(out, dtype=int)


def visible_wireframe(
    wireframe: Wireframe,
    camera: Camera,
    pose: Pose,
    raycaster: RayCaster,
    options: EdgeOptions = EdgeOptions(),
) -> VisibleWireframe:
    """Sample the edges of `wireframe` and keep the samples `pose` sees (hidden-edge removal).

    A sample is kept when it lies in front of the camera and inside the frame, at least one of
    its edge's polygons faces the camera, and the ray from the projection centre to the sample
    (moved `visibility_offset_m` off the surfaces) hits nothing in the whole scene. A corner is
    visible when the same holds for the vertex itself and one of its edges is visible.
    """
    V, Ed = wireframe.vertices, wireframe.edges
    a, b = V[Ed[:, 0]], V[Ed[:, 1]]
    # every vertex of an edge projected once (point by point: the same as projecting the edges'
    # ends; a scene part's other vertices are not projected)
    used, on_used = wireframe.edge_vertices
    uv_v, z_v = pose.project(camera, V[used])
    uv_a, z_a = uv_v[on_used[:, 0]], z_v[on_used[:, 0]]
    uv_b, z_b = uv_v[on_used[:, 1]], z_v[on_used[:, 1]]
    len_px = np.linalg.norm(np.nan_to_num(uv_b - uv_a, nan=0.0), axis=1)
    n = np.clip(
        np.ceil(len_px / options.sample_spacing_px),
        options.min_samples_per_edge,
        options.max_samples_per_edge,
    ).astype(int)
    # one edge fully behind the camera gets no samples
    n[(z_a <= options.min_depth_m) & (z_b <= options.min_depth_m)] = 0
    edge_of = np.repeat(np.arange(len(Ed)), n)
    first = np.repeat(np.cumsum(n) - n, n)
    t = (np.arange(len(edge_of)) - first + 0.5) / np.repeat(np.maximum(n, 1), n)
    pts = a[edge_of] + t[:, None] * (b - a)[edge_of]
    C = pose.center
    to_cam = C - pts
    normals = wireframe.edge_normals[edge_of]
    # at least one polygon of the edge faces the camera (a missing second polygon has a zero normal)
    toward = np.einsum("nkj,nj->nk", normals, to_cam) > 0
    facing = np.any(toward, axis=1)
    # an edge between two polygons both facing the camera is an inner edge (a ridge, a roof-wall
    # edge seen from above): its image contrast is not certain, unlike an outline
    inner = np.all(toward, axis=1)
    uv, depth = pose.project(camera, pts)
    ok = facing & (depth > options.min_depth_m) & camera.in_image(uv, options.image_margin_px)
    outward = wireframe.edge_outward[edge_of[ok]]
    ok_idx = np.nonzero(ok)[0]
    vis = raycaster.visible(
        pts[ok] + options.visibility_offset_m * outward, C, options.visibility_tolerance_m
    )
    ok[ok_idx[~vis]] = False
    sel = np.nonzero(ok)[0]
    d = (b - a)[edge_of[sel]]
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    # `edge_of` is sorted: its distinct values are where it changes
    seen = edge_of[sel]
    vis_edges = seen[np.concatenate([[True], seen[1:] != seen[:-1]])] if len(seen) else seen
    cor, cp = _visible_corners(wireframe, camera, pose, raycaster, vis_edges, options)
    return VisibleWireframe(
        points=pts[sel],
        edge=edge_of[sel],
        direction=d,
        weight=wireframe.edge_weight[edge_of[sel]] * np.where(inner[sel], options.inner_weight, 1.0),
        corners=cor,
        corner_points=cp,
        n_edges=len(vis_edges),
    )


def _visible_corners(wireframe: Wireframe, camera: Camera, pose: Pose, raycaster: RayCaster,
                     vis_edges: np.ndarray, options: EdgeOptions) -> tuple[np.ndarray, np.ndarray]:
    """The corners `pose` sees: the vertex itself visible (in front, inside the frame, the ray to it
    moved off the surfaces hits nothing) and one of its edges among `vis_edges` seen -> vertex
    indices `(K,)` and points `(K, 3)`."""
    V, Ed, C = wireframe.vertices, wireframe.edges, pose.center
    cor = wireframe.corners
    if len(cor) and len(vis_edges):
        on_seen = np.zeros(len(V), bool)
        on_seen[Ed[vis_edges].ravel()] = True
        cor = cor[on_seen[cor]]
    else:
        cor = cor[:0]
    if len(cor):
        cp = V[cor]
        uvc, zc = pose.project(camera, cp)
        inside = (zc > options.min_depth_m) & camera.in_image(uvc, options.image_margin_px)
        cor, cp = cor[inside], cp[inside]
        if len(cor):
            # offset the vertex along the mean outward normal of its edges
            off = wireframe.vertex_outward[cor]
            vis_c = raycaster.visible(
                cp + options.visibility_offset_m * off, C, options.visibility_tolerance_m
            )
            cor, cp = cor[vis_c], cp[vis_c]
    else:
        cp = np.zeros((0, 3))
    return cor, cp

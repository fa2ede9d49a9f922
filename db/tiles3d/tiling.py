"""Explicit quadtree tiling of buildings and the `tileset.json` of 3D Tiles 1.1.

In: building centres `(N, 2)` in the root's local east-north-up frame (metres), the tiling
options. Out: a quadtree of `TileNode`s whose leaves hold the buildings (each building in exactly
one leaf, by its centre) and, once the leaves' contents are written, the tileset JSON.

Rules (docs/3dtiles.md):
- the root square covers every centre; a node with more than `max_buildings` buildings is split
  into its four quadrants (empty ones dropped) until `max_depth`;
- only leaves have content (one GLB each); the root's `refine` is `ADD` (children add to their
  parent: inner tiles have nothing to replace) and the children inherit it;
- geometric error: 0 for a leaf (the full-resolution model), `side · error_per_side` for an inner
  tile whose square has side `side` metres (what is missing while its children are not drawn
  grows with the area they cover); the tileset's error is twice the root's;
- the root carries `transform` = `ecef_from_enu` at the model's origin; a leaf carries the
  translation to its own centre, so that its content's float32 vertices stay small; bounding
  volumes are boxes in the frame of their tile (inner: the root ENU frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from db.tiles3d.frames import column_major

__all__ = ["TileNode", "quadtree", "tileset_document"]

MIN_HALF_AXIS_M = 0.01


@dataclass(eq=False)
class TileNode:
    """A quadtree node.

    Attributes:
        level, x, y: quadtree address (level 0 = root; x east, y north).
        lo, side: the node's square: south-west corner `(2,)` and side, metres (root ENU).
        members: building indices of a leaf (empty for an inner node).
        children: the non-empty quadrants.
        content: URI of the leaf's GLB, relative to the tileset (set when written).
        centre: `(3,)` origin of the leaf's own frame in the root ENU frame.
        bounds: `(lo (3,), hi (3,))` in the root ENU frame, once known.
    """

    level: int
    x: int
    y: int
    lo: np.ndarray
    side: float
    members: list[int] = field(default_factory=list)
    children: list[TileNode] = field(default_factory=list)
    content: str | None = None
    centre: np.ndarray | None = None
    bounds: tuple[np.ndarray, np.ndarray] | None = None

    def leaves(self) -> list[TileNode]:
        """The leaves under this node (itself when it is one), depth first."""
        if not self.children:
            return [self]
        return [leaf for c in self.children for leaf in c.leaves()]

    @property
    def name(self) -> str:
        """`level/x_y`: the node's address."""
        return f"{self.level}/{self.x}_{self.y}"


def quadtree(centres_xy: np.ndarray, max_buildings: int = 50, max_depth: int = 12) -> TileNode:
    """The quadtree of `(N, 2)` building centres (root ENU, metres), see the module docstring."""
    c = np.asarray(centres_xy, dtype=np.float64).reshape(-1, 2)
    if not len(c):
        return TileNode(0, 0, 0, np.zeros(2), 1.0)
    lo, hi = c.min(axis=0), c.max(axis=0)
    side = float(max(hi - lo)) + 1.0
    root = TileNode(0, 0, 0, lo - 0.5, side)
    _split(root, c, np.arange(len(c)), max(1, max_buildings), max_depth)
    return root


def _split(node: TileNode, c: np.ndarray, idx: np.ndarray, max_buildings: int, max_depth: int) -> None:
    if len(idx) <= max_buildings or node.level >= max_depth:
        node.members = [int(i) for i in idx]
        return
    half = node.side / 2
    qx = (c[idx, 0] >= node.lo[0] + half).astype(int)
    qy = (c[idx, 1] >= node.lo[1] + half).astype(int)
    for dy in (0, 1):
        for dx in (0, 1):
            sel = idx[(qx == dx) & (qy == dy)]
            if len(sel):
                corner = node.lo + half * np.array([dx, dy])
                child = TileNode(node.level + 1, 2 * node.x + dx, 2 * node.y + dy, corner, half)
                node.children.append(child)
                _split(child, c, sel, max_buildings, max_depth)


def _box(lo: np.ndarray, hi: np.ndarray, origin: np.ndarray) -> list[float]:
    """A 3D Tiles `box` (centre, three half-axes) of an axis-aligned box, relative to `origin`."""
    centre = 0.5 * (lo + hi) - origin
    half = np.maximum(0.5 * (hi - lo), MIN_HALF_AXIS_M)
    return [float(v) for v in (*centre, half[0], 0, 0, 0, half[1], 0, 0, 0, half[2])]


def _bounds(node: TileNode) -> tuple[np.ndarray, np.ndarray] | None:
    """Fill `node.bounds` from its leaves' bounds (root ENU); None when nothing is below it."""
    if node.children:
        parts = [b for b in (_bounds(c) for c in node.children) if b is not None]
        if parts:
            node.bounds = (np.min([p[0] for p in parts], axis=0), np.max([p[1] for p in parts], axis=0))
        else:
            node.bounds = None
    return node.bounds


def _tile(node: TileNode, error_per_side: float, root: bool) -> dict[str, Any] | None:
    if node.bounds is None:
        return None
    lo, hi = node.bounds
    out: dict[str, Any] = {}
    if node.children:
        out["boundingVolume"] = {"box": _box(lo, hi, np.zeros(3))}
        out["geometricError"] = node.side * error_per_side
        kids = [t for t in (_tile(c, error_per_side, False) for c in node.children) if t is not None]
        if kids:
            out["children"] = kids
    else:
        centre = node.centre if node.centre is not None else np.zeros(3)
        if not root:  # the root's own transform is ecef_from_enu; a leaf root keeps the ENU origin
            out["transform"] = column_major(_translation(centre))
        out["boundingVolume"] = {"box": _box(lo, hi, centre if not root else np.zeros(3))}
        out["geometricError"] = 0.0
        if node.content is not None:
            out["content"] = {"uri": node.content}
    return out


def _translation(t: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def tileset_document(
    root: TileNode, ecef_from_root: np.ndarray, error_per_side: float, extras: dict[str, Any]
) -> dict[str, Any]:
    """The tileset JSON (3D Tiles 1.1) of a quadtree whose leaves have `content`, `centre` and
    `bounds` set; `ecef_from_root` (4×4) is the root's transform, `extras` go to `asset.extras`."""
    _bounds(root)
    tile = _tile(root, error_per_side, True)
    if tile is None:
        raise ValueError("no tile has content: nothing to export")
    tile["transform"] = column_major(ecef_from_root)
    tile["refine"] = "ADD"
    root_error = max(float(tile["geometricError"]), root.side * error_per_side)
    return {
        "asset": {"version": "1.1", "generator": "citytherm", "extras": extras},
        "geometricError": 2.0 * root_error,
        "root": tile,
    }

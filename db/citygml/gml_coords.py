"""GML coordinates -> numpy: `gml:LinearRing` (`posList`, `pos` or `coordinates`) -> `(N, 3)`.

In: lxml elements of a parsed CityGML file (GML 3.1 or 3.2), the dimension in force
(`srsDimension` of an ancestor, else 3). Out: float64 arrays `(N, 3)` in the file's CRS, exactly
as written (2D input gets z = 0). Bad numbers or dimensions raise `CityGMLError` with the line.
"""

from __future__ import annotations

import numpy as np
from lxml import etree

from db.citygml.names import GML32_NS, GML_NS, CityGMLError, local

__all__ = ["ring_coords"]

_POSLIST_TAGS = frozenset({f"{{{GML_NS}}}posList", f"{{{GML32_NS}}}posList"})


def _coords(values: np.ndarray, dim: int, el: etree._Element) -> np.ndarray:
    """Flat coordinate values -> `(N, 3)` float64 (2D input gets z = 0)."""
    if dim not in (2, 3) or len(values) % dim:
        raise CityGMLError(
            f"<{local(el.tag)}>: {len(values)} values do not form points of dimension {dim}",
            line=el.sourceline,
        )
    pts = values.reshape(-1, dim)
    if dim == 2:
        pts = np.column_stack([pts, np.zeros(len(pts))])
    return pts


def _numbers(text: str | None, el: etree._Element) -> np.ndarray:
    """Whitespace-separated numbers -> `(K,)` float64; `CityGMLError` naming `el`'s line if not."""
    try:
        return np.array((text or "").split(), dtype=np.float64)
    except ValueError as exc:
        raise CityGMLError(f"<{local(el.tag)}>: not a list of numbers", line=el.sourceline) from exc


def ring_coords(ring: etree._Element, dim: int) -> np.ndarray:
    """`gml:LinearRing` -> `(N, 3)` float64 from `posList`, `pos` or `coordinates`."""
    if len(ring) == 1:  # fast path: one posList of 3D points
        pl = ring[0]
        if pl.tag in _POSLIST_TAGS:
            d = pl.get("srsDimension") or ring.get("srsDimension")
            if d == "3" or (not d and dim == 3):
                tokens = (pl.text or "").split()
                if len(tokens) % 3 == 0:
                    try:
                        return np.array(tokens, dtype=np.float64).reshape(-1, 3)
                    except ValueError:
                        pass  # the general path below names the element and line
    d = ring.get("srsDimension")
    dim = int(d) if d else dim
    parts: list[np.ndarray] = []
    for ch in ring:
        ln = local(ch.tag)
        if ln == "posList":
            d = ch.get("srsDimension") or ch.get("dimension")
            return _coords(_numbers(ch.text, ch), int(d) if d else dim, ch)
        if ln == "pos":
            d = ch.get("srsDimension") or ch.get("dimension")
            vals = _numbers(ch.text, ch)
            parts.append(_coords(vals, int(d) if d else len(vals) if len(vals) in (2, 3) else dim, ch))
        elif ln == "coordinates":
            cs, ts, dec = ch.get("cs", ","), ch.get("ts", " "), ch.get("decimal", ".")
            text = ch.text or ""
            if dec != ".":
                text = text.replace(dec, ".")
            tuples = [t for t in (text.split() if ts.isspace() else text.split(ts)) if t.strip()]
            rows = [_numbers(t.replace(cs, " "), ch) for t in tuples]
            if rows:
                width = {len(r) for r in rows}
                if len(width) != 1:
                    raise CityGMLError("<coordinates>: tuples of different dimension", line=ch.sourceline)
                parts.append(_coords(np.concatenate(rows), width.pop(), ch))
    if not parts:
        raise CityGMLError(f"<{local(ring.tag)}> without coordinates", line=ring.sourceline)
    return np.concatenate(parts, axis=0)

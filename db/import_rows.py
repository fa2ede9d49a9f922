"""A batch of buildings -> COPY text for `building` and `surface`, without database access.

In: top-level `Building`s (parts nested), the model SRID, the checks mode. Out: `BatchLines`:
per building and per surface the COPY text of every column but the row ids (those are reserved
by the writer, which prefixes them), plus the local parent/root/owner indices to link them, and
the buildings' own appearances. Pure computation, so it can run in the reader process: what
crosses the process boundary is strings and small integer lists, which pickle cheaply.

Column order: `building` = (id, city_model_id, parent_id, root_id, ordinal, *BUILDING_TAIL),
`surface` = (id, city_model_id, building_id, *SURFACE_TAIL).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import chain
from operator import attrgetter
from typing import TYPE_CHECKING, Any

import numpy as np

from db.compiled import fmt as _fmt  # `repr` of floats in C (Ryu), None: Python's `repr`
from db.geomcodec import EncodedPolygons, encode_envelope, encode_footprints, encode_polygons
from db.ops import copy_field, pg_bool_array, pg_text_array
from db.surface_checks import jsonable, surface_checks
from workers.pipeline.geometry.citymodel import Appearance, Building, Polygon

if TYPE_CHECKING:  # imported where used: the reader process of a model in the database SRID needs no PROJ
    from workers.pipeline.geometry.transform import CrsTransform

__all__ = ["BUILDING_TAIL", "SURFACE_TAIL", "BatchLines", "batch_lines"]

BUILDING_TAIL = (
    "gml_id",
    "is_part",
    "name",
    "srs_name",
    "generated_id",
    "attributes",
    "footprint",
    "envelope",
)
SURFACE_TAIL = (
    "ordinal",
    "gml_id",
    "generated_id",
    "ring_ids",
    "ring_generated",
    "ring_closed",
    "surface_class",
    "surface_gml_id",
    "lod",
    "in_solid",
    "collection_id",
    "geometry",
    "raw_rings",
    "plane_normal",
    "plane_offset",
    "area_m2",
    "checks",
)


@dataclass(frozen=True)
class BatchLines:
    """COPY text of one batch, ids left to the writer.

    Attributes:
        building_tails: per building (document order, parts after their parent) the tab-joined
            fields of `BUILDING_TAIL`.
        parent: local index of the parent building (-1 for a top-level one).
        root: local index of the top-level building.
        is_part: per building.
        surface_tails: per surface the tab-joined fields of `SURFACE_TAIL`.
        owner: local index of the building owning each surface.
        appearances: (local building index, its appearances) for buildings that have any.
        polygon_ids: per surface its polygon id (only filled when there are appearances).
    """

    building_tails: list[str]
    parent: list[int]
    root: list[int]
    is_part: list[bool]
    surface_tails: list[str]
    owner: list[int]
    appearances: list[tuple[int, tuple[Appearance, ...]]]
    polygon_ids: list[str]


def _flatten(tops: Sequence[Building]) -> tuple[list[Building], list[int], list[int], list[tuple[int, int]]]:
    """Buildings of `tops` in DFS order (parts after their parent) with the local parent index
    (-1 for a top-level one), root index and the polygon index range `[p0, p1)` of each
    building's subtree (its own polygons and its parts', contiguous in DFS order)."""
    flat: list[Building] = []
    parent: list[int] = []
    root: list[int] = []
    sub: list[tuple[int, int]] = []
    n_polys = 0

    def walk(b: Building, r: int, p: int) -> None:
        nonlocal n_polys
        k = len(flat)
        flat.append(b)
        parent.append(p)
        root.append(k if r < 0 else r)
        sub.append((n_polys, 0))
        n_polys += len(b.polygons)
        for c in b.parts:
            walk(c, root[k], k)
        sub[k] = (sub[k][0], n_polys)

    for t in tops:
        walk(t, -1, -1)
    return flat, parent, root, sub


def _envelopes(enc: EncodedPolygons, sub: Sequence[tuple[int, int]], srid: int) -> list[str | None]:
    """Hex EWKB envelope (`encode_envelope`) of each building from the bounds of the polygons of
    its subtree (`sub`: polygon index ranges, nested); None where there is no finite vertex."""
    n = len(sub)
    out: list[str | None] = [None] * n
    ranges = np.array(sub, dtype=np.int64).reshape(-1, 2)
    keep = np.flatnonzero(ranges[:, 1] > ranges[:, 0])
    if len(keep) == 0:
        return out
    # reduceat over interleaved [p0, p1] pairs reduces each range; the odd results are discarded.
    # A NaN row is appended so that p1 == P is a valid index (fmin/fmax ignore NaN).
    pad = np.full((1, 3), np.nan)
    idx = ranges[keep].reshape(-1)
    lo = np.fmin.reduceat(np.vstack([enc.lo, pad]), idx, axis=0)[::2]
    hi = np.fmax.reduceat(np.vstack([enc.hi, pad]), idx, axis=0)[::2]
    ok = np.all(np.isfinite(lo), axis=1)
    keep, lo, hi = keep[ok], lo[ok], hi[ok]
    x0, y0, z0 = lo.T
    x1, y1, z1 = hi.T
    # the ring of `encode_envelope`: (x0 y0 z0, x1 y0 z0, x1 y1 z1, x0 y1 z1, x0 y0 z0)
    ring = np.stack(
        [np.stack(c, axis=1) for c in ((x0, y0, z0), (x1, y0, z0), (x1, y1, z1), (x0, y1, z1), (x0, y0, z0))],
        axis=1,
    )
    hexcat = np.ascontiguousarray(ring, dtype="<f8").tobytes().hex()
    head = encode_envelope(np.zeros(3), np.zeros(3), srid)[: -5 * 3 * 16]
    w = 5 * 3 * 16
    for j, i in enumerate(keep.tolist()):
        out[i] = head + hexcat[w * j : w * (j + 1)]
    return out


def _attributes_json(attrs: Mapping[str, Any]) -> str:
    """JSON text of a building's attributes (`jsonable`: NaN/inf to null, numpy to Python); plain
    str/int/finite float values (the usual case) go to `json.dumps` directly (same text)."""
    if not attrs:
        return "{}"
    for k, v in attrs.items():
        t = type(v)
        if type(k) is not str or not (t is str or t is int or (t is float and math.isfinite(v))):
            return json.dumps(jsonable(dict(attrs)))
    return json.dumps(dict(attrs))


def _building_tails(
    flat: Sequence[Building], footprints: Sequence[str | None], envs: Sequence[str | None]
) -> list[str]:
    """Tab-joined `BUILDING_TAIL` fields per building."""
    f = copy_field
    return [
        "\t".join(
            (
                f(b.id),
                "t" if b.is_part else "f",
                f(b.name),
                f(b.srs_name),
                "t" if b.generated_id else "f",
                f(_attributes_json(b.attributes)),
                f(fp),
                f(env),
            )
        )
        for b, fp, env in zip(flat, footprints, envs, strict=True)
    ]


def _ordinals(owner: Sequence[int]) -> list[str]:
    """Per polygon its position among its owner's polygons (owners are contiguous), as text."""
    o = np.asarray(owner, dtype=np.int64)
    if len(o) == 0:
        return []
    first = np.flatnonzero(np.concatenate([[True], o[1:] != o[:-1]]))
    run_start = np.repeat(first, np.diff(np.append(first, len(o))))
    return [str(v) for v in (np.arange(len(o)) - run_start).tolist()]


def _floats(values: np.ndarray) -> list[str]:
    """Float COPY fields: shortest round-trip decimals (`repr`), NULL for NaN."""
    null = "\\N"
    if _fmt is not None:
        return _fmt.float_texts(values, null)
    return [repr(v) if v == v else null for v in values.tolist()]


#: characters that need escaping in COPY text or quoting in an array literal
_SPECIAL = re.compile(r'[\\\t\n\r"]')


def _plain(polys: Sequence[Polygon]) -> bool:
    """True when no id or class text of `polys` needs COPY escaping or array quoting (the reader's
    ids are NCNames: always), so that their fields can be written as they are."""
    get = attrgetter("id", "exterior.id", "surface_class", "surface_id", "collection_id")
    # None (no surface or collection id) joins as "None": plain, like an absent id
    return not _SPECIAL.search("\x00".join(map(str, chain.from_iterable(map(get, polys)))))


def _surface_fields(p: Polygon, ring_closed: Sequence[bool], ewkb: str | None) -> tuple[str, ...]:
    """The id, ring and class fields of a polygon (`SURFACE_TAIL` `gml_id` .. `raw_rings`), escaped."""
    f, null = copy_field, "\\N"
    rings = p.rings
    raw = null if ewkb is not None else f(json.dumps([r.coords.tolist() for r in rings]))
    return (
        f(p.id),
        "t" if p.generated_id else "f",
        f(pg_text_array([r.id for r in rings])),
        pg_bool_array([r.generated_id for r in rings]),
        pg_bool_array(ring_closed),
        f(p.surface_class),
        f(p.surface_id),
        str(p.lod),
        "t" if p.in_solid else "f",
        f(p.collection_id),
        ewkb if ewkb is not None else null,
        raw,
    )


def _surface_tails(
    polys: Sequence[Polygon],
    owner: Sequence[int],
    enc: EncodedPolygons,
    checks_json: Sequence[str | None],
    area_s: Sequence[str],
) -> list[str]:
    """Tab-joined `SURFACE_TAIL` fields per polygon (`area_s`: `_floats(enc.area)`); the usual
    polygon (one ring, plain ids, a geometry) is formatted inline, any other through
    `_surface_fields`."""
    null = "\\N"
    if _fmt is not None:
        normal_s = _fmt.vector_texts(enc.normal, null)
    else:
        normal_s = [
            f"{{{a!r},{b!r},{c!r}}}" if a == a and b == b and c == c else null
            for a, b, c in enc.normal.tolist()
        ]
    offset_s = _floats(enc.offset)
    ordinal_s = _ordinals(owner)
    checks_s = [copy_field(c) for c in checks_json]
    plain = _plain(polys)
    tails = []
    for k, p in enumerate(polys):
        ewkb, closed = enc.ewkb[k], enc.ring_closed[k]
        if not plain or p.interiors or ewkb is None:
            mid = "\t".join(_surface_fields(p, closed, ewkb))
        else:
            ext, sid, coll = p.exterior, p.surface_id, p.collection_id
            mid = "\t".join(
                (
                    p.id,
                    "t" if p.generated_id else "f",
                    '{"' + ext.id + '"}',
                    "{t}" if ext.generated_id else "{f}",
                    "{t}" if closed[0] else "{f}",
                    p.surface_class,
                    null if sid is None else sid,
                    str(p.lod),
                    "t" if p.in_solid else "f",
                    null if coll is None else coll,
                    ewkb,
                    null,
                )
            )
        tails.append("\t".join((ordinal_s[k], mid, normal_s[k], offset_s[k], area_s[k], checks_s[k])))
    return tails


def batch_lines(
    tops: Sequence[Building], srid: int, checks: str, to_db: CrsTransform | None = None
) -> BatchLines:
    """COPY text of a batch of top-level buildings (see the module docstring); `to_db`
    transforms the buildings from the model's CRS into the database SRID `srid` first (the
    buildings keep their `srs_name` as read)."""
    if to_db is not None and not to_db.identity:
        from workers.pipeline.geometry.transform import transform_building

        tops = [transform_building(t, to_db, set_srs=False) for t in tops]
    flat, parent, root, sub = _flatten(tops)
    polys: list[Polygon] = [p for b in flat for p in b.polygons]
    owner = [i for i, b in enumerate(flat) for _ in b.polygons]
    enc = encode_polygons(polys, srid)
    owner_ids = [flat[i].id for i in owner] if checks == "full" else []
    # the areas' decimals are written twice (area_m2 and the checks' JSON): formatted once
    area_s = _floats(enc.area)
    checks_json = surface_checks(checks, enc, polys, owner_ids, tops, area_text=area_s)
    footprints = encode_footprints(flat, dict(zip([p.id for p in polys], enc.normal, strict=True)), srid)
    apps = [(i, b.appearances) for i, b in enumerate(flat) if b.appearances]
    return BatchLines(
        building_tails=_building_tails(flat, footprints, _envelopes(enc, sub, srid)),
        parent=parent,
        root=root,
        is_part=[b.is_part for b in flat],
        surface_tails=_surface_tails(polys, owner, enc, checks_json, area_s),
        owner=owner,
        appearances=apps,
        polygon_ids=[p.id for p in polys] if apps else [],
    )

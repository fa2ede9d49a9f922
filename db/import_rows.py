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
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from db.geomcodec import encode_envelope, encode_footprints, encode_polygons
from db.ops import copy_field, pg_bool_array, pg_text_array
from db.surface_checks import jsonable, surface_checks
from workers.pipeline.geometry.citymodel import Appearance, Building, Polygon
from workers.pipeline.geometry.transform import CrsTransform, transform_building

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


def batch_lines(
    tops: Sequence[Building], srid: int, checks: str, to_db: CrsTransform | None = None
) -> BatchLines:
    """COPY text of a batch of top-level buildings (see the module docstring); `to_db`
    transforms the buildings from the model's CRS into the database SRID `srid` first (the
    buildings keep their `srs_name` as read)."""
    if to_db is not None and not to_db.identity:
        tops = [transform_building(t, to_db, set_srs=False) for t in tops]
    flat: list[Building] = []
    parent: list[int] = []
    root: list[int] = []
    sub: list[tuple[int, int]] = []  # polygon index range of each building's subtree (DFS order)
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
    polys: list[Polygon] = [p for b in flat for p in b.polygons]
    owner = [i for i, b in enumerate(flat) for _ in b.polygons]
    enc = encode_polygons(polys, srid)
    checks_json = surface_checks(checks, enc, polys, [flat[i].id for i in owner], tops)
    normals = {p.id: enc.normal[k] for k, p in enumerate(polys)}
    footprints = encode_footprints(flat, normals, srid)
    f = copy_field
    b_tails = []
    for b, fp, (p0, p1) in zip(flat, footprints, sub, strict=True):
        env = None
        if p1 > p0:
            lo, hi = np.fmin.reduce(enc.lo[p0:p1], axis=0), np.fmax.reduce(enc.hi[p0:p1], axis=0)
            env = encode_envelope(lo, hi, srid) if np.all(np.isfinite(lo)) else None
        attrs = json.dumps(jsonable(dict(b.attributes))) if b.attributes else "{}"
        b_tails.append(
            "\t".join(
                (
                    f(b.id),
                    "t" if b.is_part else "f",
                    f(b.name),
                    f(b.srs_name),
                    "t" if b.generated_id else "f",
                    f(attrs),
                    f(fp),
                    f(env),
                )
            )
        )
    null = "\\N"
    normal_s = [
        f"{{{a!r},{b!r},{c!r}}}" if a == a and b == b and c == c else null for a, b, c in enc.normal.tolist()
    ]
    offset_s = [repr(v) if v == v else null for v in enc.offset.tolist()]
    area_s = [repr(v) if v == v else null for v in enc.area.tolist()]
    s_tails = []
    ordinal = 0
    last_owner = -1
    for k, p in enumerate(polys):
        if owner[k] != last_owner:
            ordinal, last_owner = 0, owner[k]
        ewkb = enc.ewkb[k]
        raw = None if ewkb is not None else json.dumps([r.coords.tolist() for r in p.rings])
        rings = p.rings
        s_tails.append(
            "\t".join(
                (
                    str(ordinal),
                    f(p.id),
                    "t" if p.generated_id else "f",
                    f(pg_text_array([r.id for r in rings])),
                    pg_bool_array([r.generated_id for r in rings]),
                    pg_bool_array(enc.ring_closed[k]),
                    f(p.surface_class),
                    f(p.surface_id),
                    str(p.lod),
                    "t" if p.in_solid else "f",
                    f(p.collection_id),
                    ewkb if ewkb is not None else null,
                    f(raw),
                    normal_s[k],
                    offset_s[k],
                    area_s[k],
                    f(checks_json[k]),
                )
            )
        )
        ordinal += 1
    apps = [(i, b.appearances) for i, b in enumerate(flat) if b.appearances]
    return BatchLines(
        building_tails=b_tails,
        parent=parent,
        root=root,
        is_part=[b.is_part for b in flat],
        surface_tails=s_tails,
        owner=owner,
        appearances=apps,
        polygon_ids=[p.id for p in polys] if apps else [],
    )

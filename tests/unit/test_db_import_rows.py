"""COPY text of an import batch (`db.import_rows.batch_lines`): every field against a plain
per-field formatting (`copy_field`, array literals), for polygons the fast path writes inline and
for those it hands to the general path (ids needing escapes, holes, open or degenerate rings,
missing ids); building envelopes over nested parts against `encode_envelope`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from db.geomcodec import encode_envelope, encode_polygons
from db.import_rows import batch_lines
from db.ops import copy_field, pg_bool_array, pg_text_array
from db.surface_checks import fast_checks
from workers.pipeline.geometry.citymodel import Building, Polygon, Ring


def _square(x0: float, z: float = 0.0, size: float = 10.0) -> np.ndarray:
    """A closed square ring `(5, 3)` in the plane z = `z`, metres (UTM-like offsets)."""
    x0 += 280000.0
    y0, y1, x1 = 5.6e6, 5.6e6 + size, x0 + size
    return np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z], [x0, y0, z]])


def _polygons(tag: str) -> list[Polygon]:
    """Plain polygons and polygons the fast path must not take (`tag` keeps ids unique)."""
    hole = _square(2.0, size=2.0)[::-1]
    return [
        Polygon(f"{tag}p", Ring(f"{tag}r", _square(0)), surface_class="GroundSurface", lod=2),
        Polygon(f"{tag}q", Ring(f"{tag}s", _square(0, 3.0)), surface_class="RoofSurface", surface_id="srf"),
        Polygon(f'{tag}odd\t"id\\', Ring(f"{tag}odd\nring", _square(20)), collection_id="c\tx"),
        Polygon(f"{tag}h", Ring(f"{tag}h0", _square(40)), (Ring(f"{tag}h1", hole, True),), in_solid=True),
        Polygon(f"{tag}open", Ring(f"{tag}o0", _square(60)[:-1]), generated_id=True),
        Polygon(f"{tag}deg", Ring(f"{tag}d0", np.array([[0.0, 0, 0], [1, 0, 0], [0, 0, 0]]))),
    ]


def _expected_tail(k: int, ordinal: int, p: Polygon, enc: object, checks: str) -> str:
    """The `SURFACE_TAIL` text of polygon k, formatted field by field."""
    null = "\\N"
    ewkb = enc.ewkb[k]
    n, off, area = enc.normal[k].tolist(), float(enc.offset[k]), float(enc.area[k])
    raw = None if ewkb is not None else json.dumps([r.coords.tolist() for r in p.rings])
    return "\t".join(
        (
            str(ordinal),
            copy_field(p.id),
            "t" if p.generated_id else "f",
            copy_field(pg_text_array([r.id for r in p.rings])),
            pg_bool_array([r.generated_id for r in p.rings]),
            pg_bool_array(enc.ring_closed[k]),
            copy_field(p.surface_class),
            copy_field(p.surface_id),
            str(p.lod),
            "t" if p.in_solid else "f",
            copy_field(p.collection_id),
            ewkb if ewkb is not None else null,
            copy_field(raw),
            "{" + ",".join(repr(v) for v in n) + "}" if all(v == v for v in n) else null,
            repr(off) if off == off else null,
            repr(area) if area == area else null,
            copy_field(checks),
        )
    )


@pytest.mark.parametrize("plain_only", [True, False])
def test_surface_fields_match_plain_formatting(plain_only: bool) -> None:
    polys = _polygons("a")[:2] if plain_only else _polygons("a")
    part = Building("part", tuple(_polygons("b")[:2]), is_part=True, parent_id="top")
    top = Building("top", tuple(polys), parts=(part,), attributes={"h": 4.5, "f": "x\ty", "n": float("nan")})
    lines = batch_lines([top], srid=25832, checks="fast")
    all_polys = [*polys, *part.polygons]
    enc = encode_polygons(all_polys, 25832)
    checks = fast_checks(enc, all_polys)
    ordinals = [*range(len(polys)), *range(len(part.polygons))]
    expected = [_expected_tail(k, ordinals[k], p, enc, checks[k]) for k, p in enumerate(all_polys)]
    assert lines.surface_tails == expected
    assert lines.owner == [0] * len(polys) + [1] * len(part.polygons)
    assert lines.parent == [-1, 0] and lines.root == [0, 0] and lines.is_part == [False, True]
    attrs = lines.building_tails[0].split("\t")[5]
    assert json.loads(attrs.replace("\\\\", "\\")) == {"h": 4.5, "f": "x\ty", "n": None}  # COPY unescaped


def test_envelopes_cover_parts_and_skip_buildings_without_vertices() -> None:
    inner = Building("inner", (Polygon("i", Ring("i0", _square(100, 30.0))),), is_part=True, parent_id="mid")
    mid = Building("mid", (), parts=(inner,), is_part=True, parent_id="top")
    top = Building("top", (Polygon("t", Ring("t0", _square(0))),), parts=(mid,))
    empty = Building("empty", ())
    lines = batch_lines([top, empty], srid=25832, checks="none")
    env = [t.split("\t")[7] for t in lines.building_tails]

    def box(*bs: Building) -> str:
        pts = np.concatenate([r.coords for b in bs for p in b.iter_polygons() for r in p.rings])
        return encode_envelope(pts.min(axis=0), pts.max(axis=0), 25832)

    assert env == [box(top), box(inner), box(inner), "\\N"]
    assert [t.split("\t")[0] for t in lines.building_tails] == ["top", "mid", "inner", "empty"]


def test_checks_numbers_from_the_area_fields() -> None:
    """The checks' JSON numbers made from the area's COPY fields (`_floats`: NULL for NaN,
    `inf` kept) are those made from the values, over NaN, infinities, -0.0, subnormals and random
    decimals (fixed seed)."""
    from db.import_rows import _floats
    from db.surface_checks import _nums

    rng = np.random.default_rng(20261126)
    special = [np.nan, np.inf, -np.inf, -0.0, 0.0, 5e-324, 1e308, 3.0, -7.25, 0.1, 1 / 3]
    values = np.concatenate([special, rng.normal(0, 1e3, 300)])
    rng.shuffle(values)
    expect = [repr(v) if np.isfinite(v) else "null" for v in values.tolist()]
    assert _nums(values) == expect
    assert _nums(values, _floats(values)) == expect
    assert expect.count("null") == 3

"""Writer/reader round trip of random synthetic buildings (fixed seed): every combination of
class, LoD, solid membership, holes, parts, missing surface ids and attribute types."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from db.citygml import read_model, validate_citygml2, write_citygml
from workers.pipeline.geometry.citymodel import SURFACE_CLASSES, Building, Polygon, Ring

RNG_SEED = 20261121


def _ring(rng: np.random.Generator, rid: str, centre: np.ndarray, radius: float) -> Ring:
    n = int(rng.integers(3, 9))
    ang = np.sort(rng.uniform(0, 2 * np.pi, n))
    pts = np.column_stack(
        [centre[0] + radius * np.cos(ang), centre[1] + radius * np.sin(ang), np.full(n, centre[2])]
    )
    pts = pts + rng.normal(0, 1e-3, pts.shape) * 1e3  # arbitrary decimals, not round numbers
    pts = np.round(pts, int(rng.integers(0, 12)))
    return Ring(rid, np.vstack([pts, pts[:1]]))


def _building(rng: np.random.Generator, bid: str, part: str | None = None) -> Building:
    polys = []
    surfaces: dict[str, str | None] = {}  # a thematic surface has one class: reuse per class
    for k in range(int(rng.integers(1, 12))):
        cls = str(rng.choice(SURFACE_CLASSES))
        lod = int(rng.integers(0, 5))
        if cls != "unclassified" and lod < 2:
            lod = 2  # CityGML 2.0 has thematic surfaces from LoD 2 on
        if rng.random() < 0.5 or cls not in surfaces:
            surfaces[cls] = f"{bid}_s{k}" if rng.random() < 0.7 else None
        surface = surfaces[cls]
        centre = rng.uniform([280000, 5650000, 0], [281000, 5651000, 100])
        pid = f"{bid}_p{k}"
        holes = tuple(_ring(rng, f"{pid}_h{j}", centre, 0.5) for j in range(int(rng.integers(0, 3))))
        polys.append(
            Polygon(
                id=pid,
                exterior=_ring(rng, f"{pid}_e", centre, 5.0),
                interiors=holes,
                surface_class=cls,
                lod=lod,
                surface_id=surface if cls != "unclassified" else None,
                in_solid=bool(lod >= 1 and rng.random() < 0.5),
            )
        )
    attrs = {
        "measuredHeight": float(rng.uniform(3, 40)),
        "storeysAboveGround": int(rng.integers(0, 9)),
        "roofType": str(rng.integers(1000, 3000)),
        "function": ("31001_1000", "31001_2000") if rng.random() < 0.5 else "31001_1000",
        "note": 'x < y & "quoted"',
        "count": int(rng.integers(-5, 5)),
        "ratio": float(rng.normal()),
    }
    parts = ()
    if part is None and rng.random() < 0.4:
        parts = tuple(_building(rng, f"{bid}_bp{j}", part=bid) for j in range(int(rng.integers(1, 3))))
    return Building(
        id=bid,
        polygons=tuple(polys),
        parts=parts,
        attributes=attrs,
        is_part=part is not None,
        parent_id=part,
        srs_name="EPSG:25832",
        name=f"name of {bid}" if rng.random() < 0.5 else None,
    )


def test_random_buildings_roundtrip(tmp_path: Path) -> None:
    rng = np.random.default_rng(RNG_SEED)
    buildings = [_building(rng, f"B{i}") for i in range(25)]
    out = tmp_path / "random.gml"
    write_citygml(out, buildings, srs_name="EPSG:25832")
    assert validate_citygml2(out) == []
    _, again = read_model(out)
    assert len(again) == len(buildings)
    for a, b in zip(buildings, again, strict=True):
        for x, y in zip(a.iter_buildings(), b.iter_buildings(), strict=True):
            assert (x.id, x.is_part, x.parent_id, x.name) == (y.id, y.is_part, y.parent_id, y.name)
            assert dict(x.attributes) == dict(y.attributes)
            assert len(x.polygons) == len(y.polygons)
            by_id = {p.id: p for p in y.polygons}
            for p in x.polygons:
                q = by_id[p.id]
                assert (p.surface_class, p.lod, p.in_solid) == (q.surface_class, q.lod, q.in_solid), p.id
                if p.surface_id is not None:
                    assert q.surface_id == p.surface_id
                assert [r.id for r in p.rings] == [r.id for r in q.rings]
                for r, s in zip(p.rings, q.rings, strict=True):
                    np.testing.assert_array_equal(r.coords, s.coords)

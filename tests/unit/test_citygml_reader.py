"""CityGML reader: every real sample, independent XPath counts, hand-written edge cases."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from lxml import etree

from db.citygml import iter_buildings, read_header, read_model
from db.citygml.names import is_ncname
from tests.conftest import DATA, SAMPLE_FILES, sample
from tests.unit.citygml_docs import boundary, building, polygon, square, write_doc

# Expected counts per sample, established independently of the reader with lxml XPath on the
# whole document (local-name() tests, so independent of namespaces and versions):
#   buildings = count(//cityObjectMember/Building), parts = count(//BuildingPart),
#   <Class>   = count(//<Class>//Polygon) for each boundary surface class,
#   unclassified = count(//Polygon[not(ancestor::<any boundary class>)]),
#   interiors = count(//Polygon/interior), solid = polygons inside a Solid or referenced from one.
# and the srsName spellings with sorted(set(//@srsName)).
SAMPLES: dict[str, dict] = {
    "bavaria-1-building-citygml2-lod2.gml": dict(
        version="2.0", srs="EPSG:25832", buildings=1, parts=0,
        classes={"WallSurface": 63, "RoofSurface": 20, "GroundSurface": 1}, interiors=6, solid=0,
    ),
    "berlin-61-buildings-citygml1-lod2.gml": dict(
        version="1.0", srs="EPSG:25833", buildings=61, parts=0,
        classes={"WallSurface": 793, "RoofSurface": 249, "GroundSurface": 83}, interiors=5, solid=0,
    ),
    "berlin-moabit-textured-citygml2-lod2.gml": dict(
        version="2.0", srs="urn:ogc:def:crs,crs:EPSG:6.12:25833,crs:EPSG:6.12:5783", buildings=1, parts=0,
        classes={"WallSurface": 4, "RoofSurface": 1, "GroundSurface": 1}, interiors=0, solid=0,
    ),
    "fzk-haus-citygml3-lod2.gml": dict(
        version="3.0", srs="urn:adv:crs:ETRS89_UTM32*DE_DHHN92_NH", buildings=1, parts=0,
        classes={"WallSurface": 4, "RoofSurface": 2, "GroundSurface": 1}, interiors=0, solid=7,
    ),
    "nrw-tile-5659-citygml1-lod2.gml": dict(
        version="1.0", srs="urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH*GCG2016", buildings=109, parts=55,
        classes={"WallSurface": 951, "RoofSurface": 217, "GroundSurface": 147, "ClosureSurface": 126},
        interiors=0, solid=1441,
    ),
    "potsdam-97-buildings-citygml1-lod1.gml": dict(
        version="1.0", srs="urn:ogc:def:crs,crs:EPSG:6.12:25833,crs:EPSG:6.12:5783", buildings=97, parts=0,
        classes={"unclassified": 1547}, interiors=0, solid=1547,
    ),
}  # fmt: skip

_BOUNDARY = ("WallSurface", "RoofSurface", "GroundSurface", "ClosureSurface", "OuterCeilingSurface",
             "OuterFloorSurface")  # fmt: skip


def _summary(buildings: list) -> tuple[int, Counter, int, int]:
    parts = sum(1 for b in buildings for x in b.iter_buildings() if x.is_part)
    classes = Counter(p.surface_class for b in buildings for p in b.iter_polygons())
    interiors = sum(len(p.interiors) for b in buildings for p in b.iter_polygons())
    solid = sum(p.in_solid for b in buildings for p in b.iter_polygons())
    return parts, classes, interiors, solid


def test_every_sample_is_covered() -> None:
    assert sorted(p.name for p in SAMPLE_FILES) == sorted(SAMPLES)


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_sample_counts(name: str) -> None:
    exp = SAMPLES[name]
    header, buildings = read_model(sample(name))
    assert header.version == exp["version"]
    assert header.srs_name == exp["srs"]
    assert len(buildings) == exp["buildings"]
    parts, classes, interiors, solid = _summary(buildings)
    assert parts == exp["parts"]
    assert dict(classes) == exp["classes"]
    assert interiors == exp["interiors"]
    assert solid == exp["solid"]
    for b in buildings:
        for x in b.iter_buildings():
            assert x.srs_name == exp["srs"]
        for p in b.iter_polygons():
            for r in p.rings:
                assert r.coords.dtype == np.float64 and r.coords.ndim == 2 and r.coords.shape[1] == 3
                assert is_ncname(r.id)
            assert is_ncname(p.id)


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_reader_matches_xpath(name: str) -> None:
    """The reader against a second, naive XPath reading of the whole document."""
    doc = etree.parse(str(sample(name)))

    def ln(n: str) -> str:
        return f"*[local-name()='{n}']"

    any_boundary = " or ".join(f"local-name()='{c}'" for c in _BOUNDARY)
    _, buildings = read_model(sample(name))
    parts, classes, _, _ = _summary(buildings)
    assert len(buildings) == int(doc.xpath(f"count(//{ln('cityObjectMember')}/{ln('Building')})"))
    assert parts == int(doc.xpath(f"count(//{ln('BuildingPart')})"))
    for cls in _BOUNDARY:
        assert classes.get(cls, 0) == int(doc.xpath(f"count(//{ln(cls)}//{ln('Polygon')})")), cls
    assert classes.get("unclassified", 0) == int(
        doc.xpath(f"count(//{ln('Polygon')}[not(ancestor::*[{any_boundary}])])")
    )
    # ids and coordinates of polygons that carry a gml:id, in document order
    polys = {p.id: p for b in buildings for p in b.iter_polygons()}
    for el in doc.xpath(f"//{ln('Polygon')}[@*[local-name()='id']]")[:200]:
        pid = next(v for k, v in el.attrib.items() if k.endswith("}id"))
        ring = el.xpath(f"{ln('exterior')}/{ln('LinearRing')}")[0]
        pos = ring.xpath(f"{ln('posList')}")
        text = pos[0].text if pos else " ".join(p.text for p in ring.xpath(ln("pos")))
        expected = np.array(text.split(), float).reshape(-1, 3)
        np.testing.assert_array_equal(polys[pid].exterior.coords, expected)


def test_crs_names_resolve() -> None:
    from workers.pipeline.geometry.crs import horizontal_epsg

    epsg = {name: horizontal_epsg(exp["srs"]) for name, exp in SAMPLES.items()}
    assert epsg["nrw-tile-5659-citygml1-lod2.gml"] == 25832
    assert epsg["fzk-haus-citygml3-lod2.gml"] == 25832
    assert epsg["potsdam-97-buildings-citygml1-lod1.gml"] == 25833
    assert epsg["berlin-moabit-textured-citygml2-lod2.gml"] == 25833
    assert epsg["berlin-61-buildings-citygml1-lod2.gml"] == 25833
    assert epsg["bavaria-1-building-citygml2-lod2.gml"] == 25832


def test_header_and_attributes() -> None:
    h = read_header(DATA / "nrw-tile-5659-citygml1-lod2.gml")
    assert h.name == "LoD2_32_280_5659_1_NW"
    np.testing.assert_allclose(h.envelope[0], [280000.0, 5659000.0, 33.814])
    b = next(iter_buildings(DATA / "bavaria-1-building-citygml2-lod2.gml"))
    assert b.attributes["measuredHeight"] == pytest.approx(37.54)
    assert b.attributes["storeysAboveGround"] == 6
    assert b.attributes["roofType"] == "3200"
    assert b.name == "DEBY_LOD2_4959457"
    moabit = next(iter_buildings(DATA / "berlin-moabit-textured-citygml2-lod2.gml"))
    assert moabit.attributes["EIG_KL_PV"] == 3 and moabit.attributes["H_First_Min"] == pytest.approx(37.13551)
    assert moabit.attributes["FOLIE"] == "011"
    potsdam = next(iter_buildings(DATA / "potsdam-97-buildings-citygml1-lod1.gml"))
    fzk = next(iter_buildings(DATA / "fzk-haus-citygml3-lod2.gml"))
    assert fzk.attributes["GrossPlannedArea"] == pytest.approx(120.0)
    assert fzk.attributes["storeysAboveGround"] == 2
    assert isinstance(potsdam.attributes["function"], str)
    multi = [b for b in iter_buildings(DATA / "potsdam-97-buildings-citygml1-lod1.gml")
             if isinstance(b.attributes.get("function"), tuple)]  # fmt: skip
    assert multi and multi[0].attributes["function"] == ("Wohnhaus", "(allgemein)")


def test_nrw_parts_and_solid_xlinks() -> None:
    _, buildings = read_model(DATA / "nrw-tile-5659-citygml1-lod2.gml")
    with_parts = [b for b in buildings if b.parts]
    assert with_parts
    for b in with_parts:
        for part in b.parts:
            assert part.is_part and part.parent_id == b.id
    # every polygon is referenced from its (part's) solid: one polygon, not two
    ids = [p.id for b in buildings for p in b.iter_polygons()]
    assert len(ids) == len(set(ids)) == 1441
    # rings without gml:id get stable generated ids
    gen = [r for b in buildings for p in b.iter_polygons() for r in p.rings if r.generated_id]
    assert len(gen) == 248


def test_moabit_appearances() -> None:
    b = next(iter_buildings(DATA / "berlin-moabit-textured-citygml2-lod2.gml"))
    themes = [a.theme for a in b.appearances]
    assert themes == ["Eignung Solarthermie", "Eignung Photovoltaik", "rgbTexture"]
    solar, pv, rgb = b.appearances
    assert len(solar.surface_data) == 5 and len(pv.surface_data) == 5 and len(rgb.surface_data) == 5
    # shared surface data (xlink:href between themes) are the same objects
    shared = {sd.id for sd in pv.surface_data} & {sd.id for sd in solar.surface_data}
    assert len(shared) == 4
    by_id = {sd.id: sd for sd in solar.surface_data}
    for sd in pv.surface_data:
        if sd.id in by_id:
            assert sd is by_id[sd.id]
    tex = by_id["UUID_60ccf25e-f370-4df4-a1d0-62414138f95a"]
    assert tex.image_uri == "appearance/tex5284715.jpg" and tex.mime_type == "image/jpeg"
    (target,) = tex.targets
    assert target.polygon_id == "GEOM_6946743"
    st = target.ring_coords["GEOM_6946743_0_"]
    assert st.shape == (5, 2)
    np.testing.assert_allclose(st[0], [0.999851, 0.988286])
    mat = by_id["UUID_94aaa1d4-b227-436e-abc6-04bb6588b8e1"]
    assert mat.diffuse_color == pytest.approx((0.83921569, 0.30588235, 0.21176471))
    assert mat.targets == ("UUID_32dfd94a-14ee-466a-b680-b64ccd787c6e",)


# ---- hand-written documents -----------------------------------------------------------------


def test_xlink_forward_and_backward(tmp_path: Path) -> None:
    """Solid members referencing polygons defined before and after it: one polygon each."""
    solid = (
        "<bldg:lod2Solid><gml:Solid><gml:exterior><gml:CompositeSurface>"
        '<gml:surfaceMember xlink:href="#P1"/><gml:surfaceMember xlink:href="#P2"/>'
        "</gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod2Solid>"
    )
    body = building(
        "B1",
        solid,
        boundary("WallSurface", "W1", polygon("P1", square(0, 0, 0))),
        boundary("RoofSurface", "R1", polygon("P2", square(0, 0, 3))),
        boundary("GroundSurface", "G1", polygon("P3", square(0, 0, 0, reverse=True))),
    )
    (b,) = read_model(write_doc(tmp_path, body))[1]
    assert [p.id for p in b.polygons] == ["P1", "P2", "P3"]
    assert [p.in_solid for p in b.polygons] == [True, True, False]
    assert [p.surface_class for p in b.polygons] == ["WallSurface", "RoofSurface", "GroundSurface"]
    assert [p.surface_id for p in b.polygons] == ["W1", "R1", "G1"]


def test_ids_that_are_not_ncnames_are_mapped_everywhere(tmp_path: Path) -> None:
    """A building with ids that are not NCNames (read again with each id mapped as it is read,
    `read_building`) gets the ids a plain building would, its references resolved through the
    mapped ids; the next building (plain ids) is read as usual."""
    solid = (
        "<bldg:lod2Solid><gml:Solid><gml:exterior><gml:CompositeSurface>"
        '<gml:surfaceMember xlink:href="#9P1"/><gml:surfaceMember xlink:href="#P2"/>'
        "</gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod2Solid>"
    )
    odd = building(
        "1st",
        solid,
        boundary("WallSurface", "W:1", polygon("9P1", square(0, 0, 0), ring_id="r 1")),
        boundary("RoofSurface", "R1", polygon("P2", square(0, 0, 3))),
    )
    plain = building("B2", boundary("WallSurface", "W2", polygon("Q1", square(5, 0, 0), ring_id="q1r")))
    a, b = read_model(write_doc(tmp_path, odd + plain))[1]
    assert a.id == "_1st" and [p.id for p in a.polygons] == ["_9P1", "P2"]
    assert [p.in_solid for p in a.polygons] == [True, True]
    assert a.polygons[0].surface_id == "W_1" and a.polygons[0].exterior.id == "r_1"
    assert b.id == "B2" and [(p.id, p.exterior.id, p.surface_id) for p in b.polygons] == [("Q1", "q1r", "W2")]


def test_xlink_to_missing_polygon_is_dropped(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    body = building(
        "B1",
        '<bldg:lod2MultiSurface><gml:MultiSurface><gml:surfaceMember xlink:href="#nowhere"/>'
        f"<gml:surfaceMember>{polygon('P1', square(0, 0, 0))}</gml:surfaceMember>"
        "</gml:MultiSurface></bldg:lod2MultiSurface>",
    )
    (b,) = read_model(write_doc(tmp_path, body))[1]
    assert [p.id for p in b.polygons] == ["P1"]
    assert "nowhere" in caplog.text


def test_orientable_surface_reverses(tmp_path: Path) -> None:
    ring = square(0, 0, 0)
    body = building(
        "B1",
        "<bldg:lod2MultiSurface><gml:MultiSurface>"
        f"<gml:surfaceMember>{polygon('PLUS', ring)}</gml:surfaceMember>"
        '<gml:surfaceMember><gml:OrientableSurface orientation="-"><gml:baseSurface>'
        f"{polygon('MINUS', ring)}</gml:baseSurface></gml:OrientableSurface></gml:surfaceMember>"
        "</gml:MultiSurface></bldg:lod2MultiSurface>",
    )
    (b,) = read_model(write_doc(tmp_path, body))[1]
    plus, minus = b.polygons
    np.testing.assert_array_equal(minus.exterior.coords, plus.exterior.coords[::-1])
    assert minus.exterior.coords[0].tolist() == minus.exterior.coords[-1].tolist()


def test_interior_rings_pos_and_coordinates(tmp_path: Path) -> None:
    outer = "0 0 5 10 0 5 10 10 5 0 10 5 0 0 5"
    hole = "2 2 5 2 4 5 4 4 5 4 2 5 2 2 5"
    pos_ring = "".join(f"<gml:pos>{x} {y}</gml:pos>" for x, y in [(0, 0), (1, 0), (1, 1), (0, 0)])
    body = building(
        "B1",
        "<bldg:lod1MultiSurface><gml:MultiSurface>"
        f"<gml:surfaceMember>{polygon('H', outer, 'H_ext', interiors=(hole,))}</gml:surfaceMember>"
        '<gml:surfaceMember><gml:Polygon gml:id="POS"><gml:exterior><gml:LinearRing srsDimension="2">'
        f"{pos_ring}</gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember>"
        '<gml:surfaceMember><gml:Polygon gml:id="CO"><gml:exterior><gml:LinearRing>'
        "<gml:coordinates>0,0,1 1,0,1 1,1,1 0,0,1</gml:coordinates>"
        "</gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember>"
        "</gml:MultiSurface></bldg:lod1MultiSurface>",
    )
    (b,) = read_model(write_doc(tmp_path, body))[1]
    h, pos, co = b.polygons
    assert h.lod == 1 and h.surface_class == "unclassified" and not h.in_solid
    assert h.exterior.id == "H_ext" and len(h.interiors) == 1
    np.testing.assert_array_equal(h.interiors[0].coords, np.array(hole.split(), float).reshape(-1, 3))
    assert h.interiors[0].generated_id and h.interiors[0].id == "H_ring1"
    np.testing.assert_array_equal(pos.exterior.coords[:, 2], 0.0)  # 2D input: z = 0
    assert pos.exterior.coords.shape == (4, 3)
    np.testing.assert_array_equal(co.exterior.coords[:, 2], 1.0)


def test_generated_ids_are_stable_and_ncnames(tmp_path: Path) -> None:
    body = building(
        "B1",
        boundary("WallSurface", "W1", polygon(None, square(0, 0, 0)), polygon("P9", square(5, 5, 0))),
        boundary("RoofSurface", "R1", polygon(None, square(0, 0, 3))),
    ) + building(None, boundary("RoofSurface", "R2", polygon(None, square(0, 0, 3))))
    path = write_doc(tmp_path, body)
    first = read_model(path)[1]
    second = read_model(path)[1]
    ids = [(p.id, p.exterior.id) for b in first for p in b.iter_polygons()]
    assert ids == [(p.id, p.exterior.id) for b in second for p in b.iter_polygons()]
    assert ids == [
        ("B1_poly0", "B1_poly0_ring0"),
        ("P9", "P9_ring0"),
        ("B1_poly2", "B1_poly2_ring0"),
        ("building2_poly0", "building2_poly0_ring0"),
    ]
    assert first[1].generated_id and first[1].id == "building2"
    assert [p.generated_id for p in first[0].polygons] == [True, False, True]
    assert all(is_ncname(i) for pair in ids for i in pair)
    # a generated id never collides with an existing one
    clash = building("B1", boundary("WallSurface", "B1_poly1", polygon(None, square(0, 0, 0)),
                                    polygon(None, square(1, 1, 0))))  # fmt: skip
    (b,) = read_model(write_doc(tmp_path, clash, name="clash.gml"))[1]
    assert [p.id for p in b.polygons] == ["B1_poly0", "B1_poly1_g"]


def test_srs_from_ancestor_and_parts(tmp_path: Path) -> None:
    body = building(
        "B1",
        '<bldg:consistsOfBuildingPart><bldg:BuildingPart gml:id="BP1">'
        '<bldg:lod2MultiSurface><gml:MultiSurface srsName="EPSG:25833" srsDimension="3">'
        f"<gml:surfaceMember>{polygon('P1', square(0, 0, 0))}</gml:surfaceMember>"
        "</gml:MultiSurface></bldg:lod2MultiSurface></bldg:BuildingPart></bldg:consistsOfBuildingPart>"
        "<bldg:consistsOfBuildingPart><bldg:BuildingPart>"
        f"{boundary('WallSurface', 'W2', polygon('P2', square(0, 0, 0)))}"
        "</bldg:BuildingPart></bldg:consistsOfBuildingPart>",
    )
    header, (b,) = read_model(write_doc(tmp_path, body, envelope_srs=None))
    assert [p.id for p in b.parts] == ["BP1", "B1_part2"]
    assert b.parts[1].generated_id
    assert b.parts[0].srs_name == "EPSG:25833"
    assert header.srs_name is None or header.srs_name == b.srs_name


def test_xlink_to_a_composite_surface(tmp_path: Path) -> None:
    """A solid member referencing a CompositeSurface: all its polygons are solid members."""
    composite = (
        '<gml:CompositeSurface gml:id="CS1">'
        f"<gml:surfaceMember>{polygon('A', square(0, 0, 0))}</gml:surfaceMember>"
        f"<gml:surfaceMember>{polygon('B', square(1, 0, 0))}</gml:surfaceMember>"
        "</gml:CompositeSurface>"
    )
    body = building(
        "B1",
        "<bldg:lod2Solid><gml:Solid><gml:exterior><gml:CompositeSurface>"
        '<gml:surfaceMember xlink:href="#CS1"/>'
        "</gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod2Solid>",
        boundary("WallSurface", "W1", composite),
        boundary("RoofSurface", "R1", polygon("C", square(0, 0, 3))),
    )
    (b,) = read_model(write_doc(tmp_path, body))[1]
    assert [(p.id, p.in_solid, p.collection_id) for p in b.polygons] == [
        ("A", True, "CS1"),
        ("B", True, "CS1"),
        ("C", False, None),
    ]


def test_solid_member_through_reversed_orientable_surface(tmp_path: Path) -> None:
    """`OrientableSurface orientation="-"` around an xlink: one polygon, rings as defined,
    marked `solid_reversed`; written back the same way."""
    from db.citygml import validate_citygml2, write_citygml

    solid = (
        "<bldg:lod2Solid><gml:Solid><gml:exterior><gml:CompositeSurface>"
        '<gml:surfaceMember><gml:OrientableSurface orientation="-">'
        '<gml:baseSurface xlink:href="#P1"/></gml:OrientableSurface></gml:surfaceMember>'
        '<gml:surfaceMember xlink:href="#P2"/><gml:surfaceMember xlink:href="#U1"/>'
        '<gml:surfaceMember><gml:OrientableSurface orientation="-">'
        '<gml:baseSurface xlink:href="#U2"/></gml:OrientableSurface></gml:surfaceMember>'
        "</gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod2Solid>"
    )
    loose = (
        "<bldg:lod2MultiSurface><gml:MultiSurface>"
        f"<gml:surfaceMember>{polygon('U1', square(0, 0, 5))}</gml:surfaceMember>"
        f"<gml:surfaceMember>{polygon('U2', square(0, 0, 6))}</gml:surfaceMember>"
        "</gml:MultiSurface></bldg:lod2MultiSurface>"
    )
    ring = square(0, 0, 0)
    body = building(
        "B1",
        solid,
        loose,
        boundary("WallSurface", "W1", polygon("P1", ring)),
        boundary("RoofSurface", "R1", polygon("P2", square(0, 0, 3))),
    )
    (b,) = read_model(write_doc(tmp_path, body))[1]
    flags = {p.id: (p.in_solid, p.solid_reversed) for p in b.polygons}
    assert flags == {"U1": (True, False), "U2": (True, True), "P1": (True, True), "P2": (True, False)}
    p1 = next(p for p in b.polygons if p.id == "P1")
    np.testing.assert_array_equal(p1.exterior.coords, np.array(ring.split(), float).reshape(-1, 3))
    out = tmp_path / "out.gml"
    write_citygml(out, [b], srs_name="EPSG:25832")
    assert validate_citygml2(out) == []
    (again,) = read_model(out)[1]
    assert {p.id: (p.in_solid, p.solid_reversed) for p in again.polygons} == flags
    for p in again.polygons:
        q = next(x for x in b.polygons if x.id == p.id)
        np.testing.assert_array_equal(p.exterior.coords, q.exterior.coords)


def test_ncname_fast_check_agrees_with_the_pattern() -> None:
    """`is_ncname` (a string-method check, then the pattern) says what the NCName pattern says."""
    import random

    from db.citygml.names import _NCNAME

    cases = {"a-b.c_1": True, "_x": True, "-a": False, ".a": False, "1a": False, "é": False, "": False}
    assert {c: is_ncname(c) for c in cases} == cases
    rng = random.Random(7)
    alphabet = "aZ_09.-:é \n#"
    for _ in range(20000):
        v = "".join(rng.choice(alphabet) for _ in range(rng.randint(0, 5)))
        assert is_ncname(v) == bool(_NCNAME.match(v)), repr(v)

"""CityGML 2.0 writer: round trips of every sample, schema validity, appearances as specified."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from lxml import etree

from db.citygml import read_model, validate_citygml2, write_citygml
from tests.conftest import DATA, SAMPLE_FILES, sample
from tests.unit.citygml_docs import boundary, building, polygon, square, write_doc
from workers.pipeline.geometry.citymodel import Appearance, ParameterizedTexture, TextureTarget

SAMPLES = [p.name for p in SAMPLE_FILES]
APP = "http://www.opengis.net/citygml/appearance/2.0"


def _roundtrip(src: Path, dst: Path, **kw: object) -> tuple:
    header, buildings = read_model(src)
    n = write_citygml(
        dst,
        buildings,
        srs_name=header.srs_name,
        envelope=header.envelope,
        model_appearances=header.appearances,
        name=header.name,
        **kw,
    )
    assert n == len(buildings)
    return header, buildings, *read_model(dst)


def _polygon_key(p: object) -> tuple:
    return (p.id, p.surface_class, p.lod, p.in_solid, p.surface_id, p.collection_id,
            tuple(r.id for r in p.rings))  # fmt: skip


@pytest.mark.parametrize("name", SAMPLES)
def test_roundtrip_ids_coordinates_validity(name: str, tmp_path: Path) -> None:
    out = tmp_path / f"rt-{name}"
    header, before, header2, after = _roundtrip(sample(name), out)
    assert validate_citygml2(out) == []
    assert header2.version == "2.0"
    assert header2.srs_name == header.srs_name
    assert [b.id for b in before] == [b.id for b in after]
    for a, b in zip(before, after, strict=True):
        assert [x.id for x in a.iter_buildings()] == [x.id for x in b.iter_buildings()]
        pa, pb = list(a.iter_polygons()), list(b.iter_polygons())
        assert [_polygon_key(p) for p in pa] == [_polygon_key(p) for p in pb]
        for p, q in zip(pa, pb, strict=True):
            for r, s in zip(p.rings, q.rings, strict=True):
                assert r.coords.shape == s.coords.shape
                assert np.max(np.abs(r.coords - s.coords)) <= 1e-9
        assert a.name == b.name
        for k, v in a.attributes.items():
            if k in ("creationDate", "terminationDate"):
                assert str(b.attributes[k]) == str(v)[:10]
            elif isinstance(v, float):
                assert b.attributes[k] == pytest.approx(v)
            else:
                assert b.attributes[k] == v, k
    # writing what was read back gives the same document
    again = tmp_path / "again.gml"
    write_citygml(again, after, srs_name=header2.srs_name, envelope=header2.envelope,
                  model_appearances=header2.appearances, name=header2.name)  # fmt: skip
    assert again.read_bytes() == out.read_bytes()


def test_moabit_keeps_three_themes(tmp_path: Path) -> None:
    out = tmp_path / "moabit.gml"
    _, (before,), _, (after,) = _roundtrip(DATA / "berlin-moabit-textured-citygml2-lod2.gml", out)
    assert [a.theme for a in after.appearances] == [
        "Eignung Solarthermie",
        "Eignung Photovoltaik",
        "rgbTexture",
    ]
    for a, b in zip(before.appearances, after.appearances, strict=True):
        assert a.id == b.id
        assert [s.id for s in a.surface_data] == [s.id for s in b.surface_data]
    tex_a = {s.id: s for app in before.appearances for s in app.surface_data}
    tex_b = {s.id: s for app in after.appearances for s in app.surface_data}
    for sid, sa in tex_a.items():
        sb = tex_b[sid]
        assert type(sa) is type(sb)
        if isinstance(sa, ParameterizedTexture):
            assert (sa.image_uri, sa.mime_type, sa.wrap_mode, sa.border_color) == (
                sb.image_uri, sb.mime_type, sb.wrap_mode, sb.border_color)  # fmt: skip
            for ta, tb in zip(sa.targets, sb.targets, strict=True):
                assert ta.polygon_id == tb.polygon_id
                for rid, st in ta.ring_coords.items():
                    np.testing.assert_array_equal(st, tb.ring_coords[rid])
    # shared surface data are written once and referenced afterwards (valid: unique gml:ids)
    doc = etree.parse(str(out))
    ids = doc.xpath("//@gml:id", namespaces={"gml": "http://www.opengis.net/gml"})
    assert len(ids) == len(set(ids))
    assert len(doc.xpath("//app:surfaceDataMember[@xlink:href]", namespaces={
        "app": APP, "xlink": "http://www.w3.org/1999/xlink"})) == 8  # fmt: skip


def test_extra_appearances_as_results_format(tmp_path: Path) -> None:
    """The job's appearance: app:appearance/app:Appearance inside the bldg:Building."""
    src = DATA / "nrw-tile-5659-citygml1-lod2.gml"
    header, buildings = read_model(src)
    b = buildings[0]
    p = b.polygons[0]
    n = len(p.exterior.coords)
    st = np.column_stack([np.linspace(0, 1, n), np.linspace(1, 0, n)])
    st[-1] = st[0]
    tex = ParameterizedTexture(
        id="tex_0", image_uri="textures/atlas_0.png",
        targets=(TextureTarget(polygon_id=p.id, ring_coords={p.exterior.id: st}),),
    )  # fmt: skip
    extra = {b.id: [Appearance(theme="thermal-ir", surface_data=(tex,), id="app_thermal")]}
    out = tmp_path / "textured.gml"
    write_citygml(out, buildings[:3], srs_name=header.srs_name, extra_appearances=extra)
    assert validate_citygml2(out) == []
    doc = etree.parse(str(out))
    ns = {
        "app": APP,
        "bldg": "http://www.opengis.net/citygml/building/2.0",
        "gml": "http://www.opengis.net/gml",
    }
    (app_el,) = doc.xpath("//bldg:Building/app:appearance/app:Appearance", namespaces=ns)
    assert app_el.getparent().getparent().get("{http://www.opengis.net/gml}id") == b.id
    assert app_el.findtext(f"{{{APP}}}theme") == "thermal-ir"
    assert not doc.xpath("//bldg:Building//app:appearanceMember", namespaces=ns)
    ptex = app_el.find(f".//{{{APP}}}ParameterizedTexture")
    assert ptex.findtext(f"{{{APP}}}imageURI") == "textures/atlas_0.png"
    assert ptex.findtext(f"{{{APP}}}mimeType") == "image/png"
    target = ptex.find(f"{{{APP}}}target")
    assert target.get("uri") == f"#{p.id}"
    tc = target.find(f"{{{APP}}}TexCoordList/{{{APP}}}textureCoordinates")
    assert tc.get("ring") == f"#{p.exterior.id}"
    np.testing.assert_array_equal(np.array(tc.text.split(), float).reshape(-1, 2), st)
    # and it reads back
    _, again = read_model(out)
    (got,) = again[0].appearances
    np.testing.assert_array_equal(got.surface_data[0].targets[0].ring_coords[p.exterior.id], st)


def test_generated_ids_written_and_stable(tmp_path: Path) -> None:
    body = building(
        "B1", boundary("WallSurface", "W1", polygon(None, square(0, 0, 0)), polygon(None, square(0, 0, 1)))
    )
    src = write_doc(tmp_path, body)
    out = tmp_path / "out.gml"
    _, before, _, after = _roundtrip(src, out)
    assert validate_citygml2(out) == []
    assert [p.id for p in after[0].polygons] == ["B1_poly0", "B1_poly1"]
    assert not any(p.generated_id for p in after[0].polygons)  # written: now real ids
    assert [p.id for p in before[0].polygons] == [p.id for p in after[0].polygons]


def test_invalid_input_ids_become_ncnames(tmp_path: Path) -> None:
    body = building("1st:building", boundary("WallSurface", "W1", polygon("9poly", square(0, 0, 0))))
    src = write_doc(tmp_path, body)
    out = tmp_path / "out.gml"
    _, buildings = read_model(src)
    write_citygml(out, buildings, srs_name="EPSG:25832")
    assert validate_citygml2(out) == []
    _, again = read_model(out)
    assert again[0].id == "_1st_building" and again[0].polygons[0].id == "_9poly"


def test_validator_reports_errors(tmp_path: Path) -> None:
    bad = write_doc(
        tmp_path, "<cityObjectMember><bldg:Building><bldg:noSuchThing/></bldg:Building></cityObjectMember>"
    )
    errors = validate_citygml2(bad)
    assert errors and "noSuchThing" in errors[0] and errors[0].startswith("line ")


def test_model_appearances_and_georeferenced_texture(tmp_path: Path) -> None:
    """CityModel-level appearances (before the buildings), shared by href from a local one."""
    model_app = (
        '<app:appearanceMember><app:Appearance gml:id="A0"><app:theme>ortho</app:theme>'
        '<app:surfaceDataMember><app:GeoreferencedTexture gml:id="GT1"><app:imageURI>ortho.tif</app:imageURI>'
        "<app:preferWorldFile>false</app:preferWorldFile>"
        "<app:referencePoint><gml:Point><gml:pos>10 20</gml:pos></gml:Point></app:referencePoint>"
        "<app:orientation>0.1 0 0 -0.1</app:orientation><app:target>#P1</app:target>"
        "</app:GeoreferencedTexture></app:surfaceDataMember>"
        '<app:surfaceDataMember><app:X3DMaterial gml:id="M1"><app:diffuseColor>1 0 0</app:diffuseColor>'
        "<app:isSmooth>true</app:isSmooth><app:target>#P1</app:target></app:X3DMaterial></app:surfaceDataMember>"
        "</app:Appearance></app:appearanceMember>"
    )
    local = (
        "<app:appearance><app:Appearance><app:theme>shared</app:theme>"
        '<app:surfaceDataMember xlink:href="#M1"/></app:Appearance></app:appearance>'
    )
    body = model_app + building("B1", local, boundary("RoofSurface", "R1", polygon("P1", square(0, 0, 3))))
    src = write_doc(tmp_path, body)
    header, (b,) = read_model(src)
    (app,) = header.appearances
    gt, mat = app.surface_data
    assert gt.reference_point == (10.0, 20.0) and gt.orientation == (0.1, 0.0, 0.0, -0.1)
    assert gt.prefer_world_file is False and gt.targets == ("P1",)
    assert b.appearances[0].surface_data[0] is mat and mat.is_smooth is True
    out = tmp_path / "out.gml"
    write_citygml(out, [b], srs_name=header.srs_name, model_appearances=header.appearances)
    assert validate_citygml2(out) == []
    header2, (b2,) = read_model(out)
    (app2,) = header2.appearances
    assert app2.theme == "ortho" and [s.id for s in app2.surface_data] == ["GT1", "M1"]
    assert app2.surface_data[0].orientation == gt.orientation
    # the model-level appearance is written first; the local one refers to its material by href
    assert b2.appearances[0].surface_data[0].diffuse_color == (1.0, 0.0, 0.0)


def test_feature_member_buildings(tmp_path: Path) -> None:
    body = (
        '<gml:featureMember><bldg:Building gml:id="FM1">'
        + boundary("WallSurface", "W1", polygon("P1", square(0, 0, 0)))
        + "</bldg:Building></gml:featureMember>"
    )
    inner = [boundary("WallSurface", f"WS{k}", polygon(f"PS{k}", square(0, 0, 0))) for k in range(3)]
    many = "".join(f'<bldg:Building gml:id="FMS{k}">{x}</bldg:Building>' for k, x in enumerate(inner))
    many = f"<gml:featureMembers>{many}</gml:featureMembers>"
    _, buildings = read_model(write_doc(tmp_path, body + many))
    assert [b.id for b in buildings] == ["FM1", "FMS0", "FMS1", "FMS2"]
    assert [p.id for b in buildings for p in b.polygons] == ["P1", "PS0", "PS1", "PS2"]


def test_non_finite_numbers_stay_valid(tmp_path: Path) -> None:
    from workers.pipeline.geometry.citymodel import Building, Polygon, Ring

    ring = Ring("R1", np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 0, 0]], float))
    b = Building(
        id="B1",
        polygons=(Polygon("P1", ring, surface_class="RoofSurface"),),
        attributes={"measuredHeight": float("nan"), "ratio": float("inf"), "storeysAboveGround": -1},
    )
    out = tmp_path / "nan.gml"
    write_citygml(out, [b], srs_name="EPSG:25832")
    assert validate_citygml2(out) == []
    (got,) = read_model(out)[1]
    assert np.isnan(got.attributes["measuredHeight"]) and got.attributes["ratio"] == float("inf")
    assert got.attributes["storeysAboveGround"] == -1  # invalid as standard: kept as generic int


def test_envelope_of(tmp_path: Path) -> None:
    from db.citygml import envelope_of

    _, buildings = read_model(DATA / "nrw-tile-5659-citygml1-lod2.gml")
    lo, hi = envelope_of(buildings)
    pts = np.concatenate([r.coords for b in buildings for p in b.iter_polygons() for r in p.rings])
    np.testing.assert_array_equal(lo, pts.min(axis=0))
    np.testing.assert_array_equal(hi, pts.max(axis=0))
    assert envelope_of([]) is None
    out = tmp_path / "env.gml"
    write_citygml(out, buildings[:2], srs_name="EPSG:25832", envelope=envelope_of(buildings[:2]))
    assert validate_citygml2(out) == []
    header, _ = read_model(out)
    np.testing.assert_array_equal(header.envelope[0], envelope_of(buildings[:2])[0])

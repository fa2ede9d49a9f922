"""The compiled geometry walk (`db/citygml/_walk.pyx`) against the Python walk of
`building_read`: the same buildings (ids, classes, flags, coordinates bit for bit), the same
COPY rows of the import, the same errors and warnings, on the bundled files and on synthetic
documents with every construct the compiled walk handles or hands back to Python.

The compiled walk must be built (`make install` builds it; CI installs a C compiler): these tests
fail, not skip, when it is missing."""

# ruff: noqa: E501  (the synthetic documents below are one XML snippet a line)

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from db.citygml import building_read
from db.citygml.names import CityGMLError
from db.citygml.reader import _Stream
from db.import_rows import batch_lines
from tests.unit.citygml_docs import boundary, building, polygon, square, write_doc
from workers.pipeline.geometry.citymodel import Building

DATA = Path(__file__).resolve().parents[1] / "data"
FILES = sorted(DATA.glob("*.gml"))


def _key(b: Building) -> list:
    """Everything a Building holds, coordinates as their bytes (bit-exact comparison)."""
    out: list = [
        b.id, b.is_part, b.parent_id, b.srs_name, b.name, b.generated_id,
        repr(sorted(b.attributes.items())), repr(b.appearances),
    ]  # fmt: skip
    for p in b.polygons:
        out.append(
            (p.id, p.surface_class, p.lod, p.surface_id, p.in_solid, p.generated_id, p.collection_id,
             p.solid_reversed)
        )  # fmt: skip
        for r in p.rings:
            out.append((r.id, r.generated_id, r.coords.dtype.str, r.coords.shape, r.coords.tobytes()))
    out.extend(_key(c) for c in b.parts)
    return out


def _read(path: Path, compiled: bool, monkeypatch: pytest.MonkeyPatch) -> list[Building]:
    monkeypatch.setattr(building_read, "COMPILED_WALK", compiled)
    return [obj for kind, obj in _Stream(path, False).events() if kind == "building"]  # type: ignore[misc]


def _outcome(path: Path, compiled: bool, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture):
    """(buildings' keys or the error's text, warnings logged) of reading `path`."""
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="db.citygml.building_read"):
        try:
            result: object = [_key(b) for b in _read(path, compiled, monkeypatch)]
        except CityGMLError as exc:
            result = f"CityGMLError: {exc}"
    return result, [r.getMessage() for r in caplog.records]


def test_compiled_walk_is_built() -> None:
    assert building_read._walk is not None, "db/citygml/_walk.pyx is not built: run `make install`"
    assert building_read._walk.selftest()


@pytest.mark.parametrize("path", FILES, ids=[f.stem for f in FILES])
def test_bundled_files_same_buildings_and_rows(path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    compiled = _read(path, True, monkeypatch)
    python = _read(path, False, monkeypatch)
    assert len(compiled) == len(python) > 0
    assert [_key(b) for b in compiled] == [_key(b) for b in python]
    for checks in ("fast", "full"):
        a, b = batch_lines(compiled, 25832, checks), batch_lines(python, 25832, checks)
        assert a.building_tails == b.building_tails
        assert a.surface_tails == b.surface_tails
        assert (a.parent, a.root, a.owner) == (b.parent, b.root, b.owner)


@pytest.mark.parametrize("name", ["nrw-tile-5659-citygml1-lod2", "berlin-moabit-textured-citygml2-lod2"])
def test_compiled_walk_reads_the_bundled_files_itself(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The usual files never fall back to the Python walk (its polygon reader is disabled here)."""

    def refuse(*args: object) -> None:
        raise AssertionError("the Python walk was used")

    monkeypatch.setattr(building_read._BuildingReader, "_polygon", refuse)
    buildings = _read(DATA / f"{name}.gml", True, monkeypatch)
    assert sum(len(list(b.iter_polygons())) for b in buildings) >= 6


def _ring(text: str, rid: str | None = None, dim: str | None = None) -> str:
    rid_attr = f' gml:id="{rid}"' if rid else ""
    dim_attr = f' srsDimension="{dim}"' if dim else ""
    return f"<gml:LinearRing{rid_attr}><gml:posList{dim_attr}>{text}</gml:posList></gml:LinearRing>"


def _poly(pid: str, ext: str, attrs: str = "", holes: tuple[str, ...] = (), tag: str = "Polygon") -> str:
    inner = "".join(f"<gml:interior>{h}</gml:interior>" for h in holes)
    return f'<gml:{tag} gml:id="{pid}"{attrs}><gml:exterior>{ext}</gml:exterior>{inner}</gml:{tag}>'


def _surface(cls: str, sid: str, geometry: str, prop: str = "lod2MultiSurface") -> str:
    return f'<bldg:boundedBy><bldg:{cls} gml:id="{sid}"><bldg:{prop}>{geometry}</bldg:{prop}></bldg:{cls}></bldg:boundedBy>'


def _members(*polys: str, gid: str = "ms", tag: str = "MultiSurface") -> str:
    body = "".join(f"<gml:surfaceMember>{p}</gml:surfaceMember>" for p in polys)
    return f'<gml:{tag} gml:id="{gid}">{body}</gml:{tag}>'


RNG_SEED = 20261126


def _random_ring(rng: np.random.Generator, closed: bool = True) -> str:
    """posList text of a random ring: decimals of 0-12 digits, some in exponent form."""
    n = int(rng.integers(3, 8))
    pts = rng.uniform([280000, 5650000, 0], [281000, 5651000, 100], (n, 3))
    pts = np.round(pts, int(rng.integers(0, 13)))
    if closed:
        pts = np.vstack([pts, pts[:1]])
    words = [repr(float(v)) if rng.random() < 0.8 else f"{v:.17e}" for v in pts.ravel()]
    return " ".join(words)


#: (name, building content) pairs; each is read by both walks and must give the same outcome
CASES: list[tuple[str, str]] = [
    ("plain", boundary("WallSurface", "s1", polygon("p1", square(0, 0, 0), "r1"))),
    ("no ids", boundary("RoofSurface", "s1", polygon(None, square(0, 0, 0)))),
    ("holes", boundary("GroundSurface", "s1", polygon("p1", square(0, 0, 0, 5), "r1", (square(1, 1, 0),)))),
    (
        "solid with references, one unresolved",
        boundary("WallSurface", "s1", polygon("p1", square(0, 0, 0), "r1"), polygon("p2", square(2, 0, 0)))
        + '<bldg:lod2Solid><gml:Solid><gml:exterior><gml:CompositeSurface gml:id="cs">'
        '<gml:surfaceMember xlink:href="#p1"/><gml:surfaceMember xlink:href="#nowhere"/>'
        '<gml:surfaceMember><gml:OrientableSurface orientation=" - "><gml:baseSurface xlink:href="#p2"/>'
        "</gml:OrientableSurface></gml:surfaceMember></gml:CompositeSurface></gml:exterior></gml:Solid>"
        "</bldg:lod2Solid>",
    ),
    (
        "reference to a collection",
        _surface("RoofSurface", "s1", _members(polygon("p1", square(0, 0, 1)), gid="roofs"))
        + '<bldg:lod2Solid><gml:Solid><gml:exterior><gml:CompositeSurface><gml:surfaceMember xlink:href="#roofs"/>'
        "</gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod2Solid>",
    ),
    (
        "orientable surface reverses its rings",
        _surface(
            "WallSurface",
            "s1",
            '<gml:OrientableSurface orientation="-"><gml:baseSurface>'
            + _poly("p1", _ring(square(0, 0, 0)), holes=(_ring(square(0.2, 0.2, 0, 0.1)),))
            + "</gml:baseSurface></gml:OrientableSurface>",
        ),
    ),
    ("srsDimension 3 on the posList", _surface("WallSurface", "s1", _members(_poly("p1", _ring(square(0, 0, 0), dim="3"))))),
    ("srsDimension 2 on the polygon", _surface("WallSurface", "s1", _members(_poly("p1", _ring("0 0 1 0 1 1 0 0"), ' srsDimension="2"')))),
    ("srsDimension 2 on the collection", _surface("WallSurface", "s1", '<gml:MultiSurface srsDimension="2"><gml:surfaceMember>' + _poly("p1", _ring("0 0 1 0 1 1 0 0")) + "</gml:surfaceMember></gml:MultiSurface>")),
    ("srsName on the geometry", _surface("WallSurface", "s1", '<gml:MultiSurface srsName="EPSG:25833"><gml:surfaceMember>' + _poly("p1", _ring(square(0, 0, 0))) + "</gml:surfaceMember></gml:MultiSurface>")),
    ("srsName on a member polygon", _surface("WallSurface", "s1", _members(_poly("p1", _ring(square(0, 0, 0)), ' srsName="EPSG:4979"')))),
    ("gml:pos rings", _surface("WallSurface", "s1", _members(_poly("p1", "<gml:LinearRing><gml:pos>0 0 0</gml:pos><gml:pos>1 0 0</gml:pos><gml:pos>1 1 0</gml:pos><gml:pos>0 0 0</gml:pos></gml:LinearRing>")))),
    ("gml:coordinates ring", _surface("WallSurface", "s1", _members(_poly("p1", "<gml:LinearRing><gml:coordinates>0,0,0 1,0,0 1,1,0 0,0,0</gml:coordinates></gml:LinearRing>")))),
    ("numbers in every spelling", _surface("WallSurface", "s1", _members(_poly("p1", _ring("+0.5 -0 5. 1e1 1E-1 .25 \t\n 3.000000000000000000001 2 -1.5e+2 +.5 0 0.5"))))),
    ("underscores and infinities (Python's float)", _surface("WallSurface", "s1", _members(_poly("p1", _ring("1_0 2 3 inf -Infinity nan 1 2 3 1_0 2 3"))))),
    ("a token longer than 63 characters", _surface("WallSurface", "s1", _members(_poly("p1", _ring("0." + "1" * 80 + " 2 3 4 5 6 7 8 9 0." + "1" * 80 + " 2 3"))))),
    ("non-ASCII digits", _surface("WallSurface", "s1", _members(_poly("p1", _ring("\u0661 2 3 4 5 6 7 8 9 \u0661 2 3"))))),
    ("overflowing number", _surface("WallSurface", "s1", _members(_poly("p1", _ring("1e999 2 3 4 5 6 7 8 9 1e999 2 3"))))),
    ("CDATA posList", _surface("WallSurface", "s1", _members(_poly("p1", "<gml:LinearRing><gml:posList><![CDATA[0 0 0 1 0 0 1 1 0 0 0 0]]></gml:posList></gml:LinearRing>")))),
    ("empty posList", _surface("WallSurface", "s1", _members(_poly("p1", "<gml:LinearRing><gml:posList/></gml:LinearRing>")))),
    ("Triangle and PolygonPatch", _surface("WallSurface", "s1", '<gml:TriangulatedSurface gml:id="ts"><gml:trianglePatches><gml:Triangle><gml:exterior>' + _ring("0 0 0 1 0 0 1 1 0 0 0 0") + '</gml:exterior></gml:Triangle></gml:trianglePatches></gml:TriangulatedSurface><gml:Surface><gml:patches><gml:PolygonPatch><gml:exterior>' + _ring(square(3, 3, 3)) + "</gml:exterior></gml:PolygonPatch></gml:patches></gml:Surface>", prop="lod3MultiSurface")),
    ("curves are skipped", _surface("WallSurface", "s1", '<gml:MultiCurve><gml:curveMember><gml:LineString><gml:posList>0 0 0 1 1 1</gml:posList></gml:LineString></gml:curveMember></gml:MultiCurve>') + '<bldg:lod2TerrainIntersection><gml:MultiCurve><gml:curveMember><gml:LineString><gml:posList>0 0 0 1 1 1</gml:posList></gml:LineString></gml:curveMember></gml:MultiCurve></bldg:lod2TerrainIntersection>'),
    ("geometry properties of the building", '<bldg:lod1Solid><gml:Solid><gml:exterior><gml:CompositeSurface>' + "".join(f"<gml:surfaceMember>{polygon(f'q{k}', square(k, 0, 0))}</gml:surfaceMember>" for k in range(3)) + '</gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod1Solid><bldg:lod0FootPrint><gml:MultiSurface><gml:surfaceMember>' + polygon("fp", square(0, 0, 0)) + "</gml:surfaceMember></gml:MultiSurface></bldg:lod0FootPrint>"),
    ("property with a reference", boundary("WallSurface", "s1", polygon("p1", square(0, 0, 0))) + '<bldg:lod2MultiSurface xlink:href="#p1"/>'),
    ("building part and installation", boundary("WallSurface", "s1", polygon("p1", square(0, 0, 0))) + '<bldg:consistsOfBuildingPart><bldg:BuildingPart gml:id="bp">' + boundary("RoofSurface", "s2", polygon("p2", square(0, 0, 3))) + '</bldg:BuildingPart></bldg:consistsOfBuildingPart><bldg:outerBuildingInstallation><bldg:BuildingInstallation><bldg:boundedBy><bldg:WallSurface gml:id="iw"><bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember>' + polygon("p3", square(5, 5, 0)) + "</gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface></bldg:WallSurface></bldg:boundedBy><bldg:lod3Geometry><gml:MultiSurface><gml:surfaceMember>" + polygon("p4", square(6, 6, 0)) + "</gml:surfaceMember></gml:MultiSurface></bldg:lod3Geometry></bldg:BuildingInstallation></bldg:outerBuildingInstallation>"),
    ("ids that are not NCNames", boundary("WallSurface", "1s", polygon("p&amp;1", square(0, 0, 0), "9r")) + '<bldg:lod2Solid><gml:Solid><gml:exterior><gml:CompositeSurface><gml:surfaceMember xlink:href="#p&amp;1"/></gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod2Solid>'),
    ("character reference in an id", boundary("WallSurface", "s&#x41;1", polygon("p&#65;", square(0, 0, 0)))),
    ("unknown thematic surface", boundary("StrangeSurface", "s1", polygon("p1", square(0, 0, 0)))),
    ("comments and processing instructions", _surface("WallSurface", "s1", '<gml:MultiSurface><!-- c --><?pi x?><gml:surfaceMember><!-- c -->' + _poly("p1", "<gml:LinearRing><!-- c --><gml:posList>0 0 0 1 0 0 1 1 0 0 0 0</gml:posList></gml:LinearRing>") + "</gml:surfaceMember></gml:MultiSurface>")),
    ("ring of another type (error)", _surface("WallSurface", "s1", _members('<gml:Polygon><gml:exterior><gml:Ring><gml:curveMember/></gml:Ring></gml:exterior></gml:Polygon>'))),
    ("polygon without exterior (error)", _surface("WallSurface", "s1", _members('<gml:Polygon gml:id="p1"><gml:interior>' + _ring(square(0, 0, 0)) + "</gml:interior></gml:Polygon>"))),
    ("bad number (error)", _surface("WallSurface", "s1", _members(_poly("p1", _ring("0 0 0 1 x 0 1 1 0 0 0 0"))))),
    ("numbers not a multiple of 3 (error)", _surface("WallSurface", "s1", _members(_poly("p1", _ring("0 0 0 1 0 0 1 1 0 0 0"))))),
    ("srsDimension 4 (error)", _surface("WallSurface", "s1", '<gml:MultiSurface srsDimension="4"><gml:surfaceMember>' + _poly("p1", _ring(square(0, 0, 0))) + "</gml:surfaceMember></gml:MultiSurface>")),
]  # fmt: skip


@pytest.mark.parametrize("name,content", CASES, ids=[c[0] for c in CASES])
def test_synthetic_same_outcome(
    name: str, content: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    path = write_doc(tmp_path, building("B1", content) + building(None, content))
    compiled = _outcome(path, True, monkeypatch, caplog)
    python = _outcome(path, False, monkeypatch, caplog)
    assert compiled == python
    if "(error)" in name:
        assert isinstance(python[0], str) and python[0].startswith("CityGMLError")
    else:
        assert isinstance(python[0], list) and len(python[0]) == 2


def test_random_rings_same_coordinates(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Random decimals (0-17 digits, plain and exponent form) parse to the same doubles."""
    rng = np.random.default_rng(RNG_SEED)
    polys = [polygon(f"p{k}", _random_ring(rng, closed=k % 7 != 0)) for k in range(400)]
    path = write_doc(tmp_path, building("B1", boundary("WallSurface", "s1", *polys)))
    compiled = _read(path, True, monkeypatch)
    python = _read(path, False, monkeypatch)
    assert [_key(b) for b in compiled] == [_key(b) for b in python]
    coords = np.concatenate([r.coords for p in compiled[0].polygons for r in p.rings])
    assert coords.shape[0] > 1600 and np.all(coords[:, 0] > 279999)


def test_warning_lines_beyond_65535(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """libxml2 keeps line numbers above 65,535 elsewhere (lxml then reports 65535, its cap): an
    unresolved reference there is reported with the same line by both walks."""
    content = (
        boundary("WallSurface", "s1", polygon("p1", square(0, 0, 0)))
        + "<bldg:lod2Solid><gml:Solid><gml:exterior><gml:CompositeSurface>\n"
        '<gml:surfaceMember xlink:href="#missing"/></gml:CompositeSurface></gml:exterior></gml:Solid>'
        "</bldg:lod2Solid>"
    )
    path = write_doc(tmp_path, "\n" * 70000 + building("B1", content))
    compiled = _outcome(path, True, monkeypatch, caplog)
    python = _outcome(path, False, monkeypatch, caplog)
    assert compiled == python
    assert len(python[1]) == 1 and "#missing" in python[1][0]


def test_number_tokens_read_as_float_reads_them() -> None:
    """The walk's number reader (its exact fast path for plain decimals, CPython's parser for the
    rest) against `float()`, bit for bit, over random tokens of 1-20 digits with or without a
    point and sign (fixed seed) and the edges of the fast path (2**53, 22 decimals, no digit)."""
    rng = np.random.default_rng(RNG_SEED)
    tokens = []
    for _ in range(100_000):
        digits = "".join(rng.choice(list("0123456789"), int(rng.integers(1, 21))))
        cut = int(rng.integers(-1, len(digits) + 1))
        body = digits if cut < 0 else f"{digits[:cut]}.{digits[cut:]}"
        tokens.append(str(rng.choice(["", "-", "+"])) + body)
    tokens += ["0", "-0", "-0.0", ".5", "5.", ".", "-", "+.", "1." + "0" * 30, "9007199254740991"]
    tokens += ["9007199254740992", "9007199254740993", "0." + "0" * 21 + "1", "0." + "0" * 22 + "1"]
    tokens += ["00000000000000000001.5", "123456789012345678", "1e5", "-1.5E-3", "1e400", "e5", "1e"]
    for token in tokens:
        try:
            expect: float | None = float(token)
        except ValueError:
            expect = None
        got = building_read._walk.parse_decimal(token.encode())
        assert (got is None) == (expect is None), token
        if expect is not None:
            assert np.float64(got).tobytes() == np.float64(expect).tobytes(), token

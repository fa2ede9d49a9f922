"""Refused input: entity tricks, DTDs, truncated and non-CityGML documents, broken geometry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from db.citygml import CityGMLError, iter_buildings, read_header, read_model
from tests.conftest import DATA
from tests.unit.citygml_docs import NS2, boundary, building, polygon, square, write_doc

BILLION_LAUGHS = """<?xml version="1.0"?>
<!DOCTYPE CityModel [
  <!ENTITY lol "lol">
  <!ENTITY lol2 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">
  <!ENTITY lol3 "&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;">
  <!ENTITY lol4 "&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;">
  <!ENTITY lol9 "&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;&lol4;">
]>
<CityModel {ns}><gml:name>&lol9;</gml:name></CityModel>
"""
XXE = """<?xml version="1.0"?>
<!DOCTYPE CityModel [<!ENTITY xxe SYSTEM "file:///etc/passwd">]>
<CityModel {ns}><gml:name>&xxe;</gml:name></CityModel>
"""
EXTERNAL_DTD = """<?xml version="1.0"?>
<!-- a comment first -->
<!DOCTYPE CityModel SYSTEM "http://example.invalid/citygml.dtd">
<CityModel {ns}><gml:name>x</gml:name></CityModel>
"""


@pytest.mark.parametrize(
    ("text", "line"), [(BILLION_LAUGHS, 2), (XXE, 2), (EXTERNAL_DTD, 3)], ids=["billion-laughs", "xxe", "dtd"]
)
def test_doctype_refused(tmp_path: Path, text: str, line: int) -> None:
    path = tmp_path / "evil.gml"
    path.write_text(text.format(ns=NS2))
    for fn in (read_header, read_model, lambda p: list(iter_buildings(p))):
        with pytest.raises(CityGMLError, match="DOCTYPE") as err:
            fn(path)
        assert err.value.line == line
        assert "passwd" not in str(err.value) and "lollol" not in str(err.value)


def test_truncated_file_names_line(tmp_path: Path) -> None:
    text = (DATA / "bavaria-1-building-citygml2-lod2.gml").read_text()
    cut = text[: len(text) // 2]
    path = tmp_path / "truncated.gml"
    path.write_text(cut)
    with pytest.raises(CityGMLError) as err:
        read_model(path)
    assert err.value.line is not None and err.value.line >= cut.count("\n")
    assert "truncated.gml" in str(err.value)


def test_not_citygml(tmp_path: Path) -> None:
    path = tmp_path / "other.xml"
    path.write_text('<?xml version="1.0"?>\n\n<kml xmlns="http://www.opengis.net/kml/2.2"><Document/></kml>\n')
    with pytest.raises(CityGMLError, match="not a CityGML document") as err:
        read_model(path)
    assert err.value.line == 3
    garbage = tmp_path / "garbage.gml"
    garbage.write_text("this is not XML at all")
    with pytest.raises(CityGMLError, match="XML error") as err:
        read_header(garbage)
    assert err.value.line == 1
    with pytest.raises(CityGMLError, match="no such file"):
        read_header(tmp_path / "missing.gml")


def test_bad_coordinates_name_the_line(tmp_path: Path) -> None:
    body = building("B1", boundary("WallSurface", "W1", polygon("P1", "0 0 0 1 0 0 1 1")))
    with pytest.raises(CityGMLError, match="dimension 3") as err:
        read_model(write_doc(tmp_path, body))
    assert err.value.line == 4  # the body is on line 4 of the document
    body = building("B1", boundary("WallSurface", "W1", polygon("P1", "0 0 0 1 zero 0 1 1 0 0 0 0")))
    with pytest.raises(CityGMLError, match="not a list of numbers"):
        read_model(write_doc(tmp_path, body, name="b.gml"))


def test_is_a_value_error(tmp_path: Path) -> None:
    assert issubclass(CityGMLError, ValueError)
    ok = write_doc(tmp_path, building("B1", boundary("RoofSurface", "R1", polygon("P1", square(0, 0, 1)))))
    assert len(read_model(ok)[1]) == 1


@pytest.mark.slow
def test_huge_text_node_needs_huge_tree(tmp_path: Path) -> None:
    """libxml2's 10 MB text-node limit stays on by default; `huge_tree=True` lifts it."""
    n = 400_000
    t = np.linspace(0.0, 2.0 * np.pi, n)
    pts = np.column_stack([10.0 * np.cos(t), 10.0 * np.sin(t), np.zeros(n)])
    pts[-1] = pts[0]
    poslist = " ".join(f"{v:.7f}" for v in pts.ravel())
    assert len(poslist) > 10_000_000
    path = write_doc(tmp_path, building("B1", boundary("RoofSurface", "R1", polygon("P1", poslist))))
    with pytest.raises(CityGMLError, match="huge_tree=True") as err:
        read_model(path)
    assert err.value.line == 4
    (b,) = read_model(path, huge_tree=True)[1]
    np.testing.assert_allclose(b.polygons[0].exterior.coords, pts, atol=1e-7)

"""Small hand-written CityGML documents for the CityGML reader/writer tests."""

from __future__ import annotations

from pathlib import Path

NS2 = (
    'xmlns="http://www.opengis.net/citygml/2.0" xmlns:core="http://www.opengis.net/citygml/2.0" '
    'xmlns:bldg="http://www.opengis.net/citygml/building/2.0" '
    'xmlns:app="http://www.opengis.net/citygml/appearance/2.0" '
    'xmlns:gen="http://www.opengis.net/citygml/generics/2.0" '
    'xmlns:gml="http://www.opengis.net/gml" xmlns:xlink="http://www.w3.org/1999/xlink"'
)


def write_doc(
    tmp_path: Path, body: str, name: str = "doc.gml", envelope_srs: str | None = "EPSG:25832"
) -> Path:
    """A CityGML 2.0 document with `body` as the CityModel's content after the envelope."""
    env = ""
    if envelope_srs:
        env = (
            f'<gml:boundedBy><gml:Envelope srsName="{envelope_srs}" srsDimension="3">'
            "<gml:lowerCorner>0 0 0</gml:lowerCorner><gml:upperCorner>10 10 10</gml:upperCorner>"
            "</gml:Envelope></gml:boundedBy>"
        )
    path = tmp_path / name
    path.write_text(
        f'<?xml version="1.0" encoding="UTF-8"?>\n<CityModel {NS2}>\n{env}\n{body}\n</CityModel>\n'
    )
    return path


def square(x0: float, y0: float, z: float, size: float = 1.0, reverse: bool = False) -> str:
    """posList text of a closed horizontal square (counter-clockwise seen from above)."""
    pts = [(x0, y0), (x0 + size, y0), (x0 + size, y0 + size), (x0, y0 + size), (x0, y0)]
    if reverse:
        pts = pts[::-1]
    return " ".join(f"{x} {y} {z}" for x, y in pts)


def polygon(
    pid: str | None, poslist: str, ring_id: str | None = None, interiors: tuple[str, ...] = ()
) -> str:
    """A gml:Polygon with an exterior (and interior) rings from posList texts."""
    pid_attr = f' gml:id="{pid}"' if pid else ""
    rid_attr = f' gml:id="{ring_id}"' if ring_id else ""
    inner = "".join(
        f"<gml:interior><gml:LinearRing><gml:posList>{p}</gml:posList></gml:LinearRing></gml:interior>"
        for p in interiors
    )
    return (
        f"<gml:Polygon{pid_attr}><gml:exterior><gml:LinearRing{rid_attr}><gml:posList>{poslist}"
        f"</gml:posList></gml:LinearRing></gml:exterior>{inner}</gml:Polygon>"
    )


def boundary(cls: str, sid: str, *polys: str, lod: int = 2) -> str:
    """A bldg:boundedBy with one thematic surface holding the polygons."""
    members = "".join(f"<gml:surfaceMember>{p}</gml:surfaceMember>" for p in polys)
    return (
        f'<bldg:boundedBy><bldg:{cls} gml:id="{sid}"><bldg:lod{lod}MultiSurface><gml:MultiSurface>'
        f"{members}</gml:MultiSurface></bldg:lod{lod}MultiSurface></bldg:{cls}></bldg:boundedBy>"
    )


def building(bid: str | None, *content: str) -> str:
    """A cityObjectMember with one bldg:Building."""
    attr = f' gml:id="{bid}"' if bid else ""
    return f"<cityObjectMember><bldg:Building{attr}>{''.join(content)}</bldg:Building></cityObjectMember>"

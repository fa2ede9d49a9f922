"""CRS names as written in CityGML files and sequence manifests -> pyproj CRS objects.

In: an `srsName` string in any of the spellings met in the wild:

- `EPSG:25832`, bare `25832`, `EPSG:25832+7837`;
- OGC URNs `urn:ogc:def:crs:EPSG::25832`, `urn:ogc:def:crs:EPSG:6.12:25832`;
- OGC compound URNs `urn:ogc:def:crs,crs:EPSG:6.12:25833,crs:EPSG:6.12:5783`;
- OGC http URIs `http://www.opengis.net/def/crs/EPSG/0/25832` and the old GML
  `http://www.opengis.net/gml/srs/epsg.xml#25832`;
- the German surveying authorities' (AdV) URNs `urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH*GCG2016`,
  which PROJ does not know: horizontal part `*` height system `*` (ignored) quasigeoid model.

Out: `pyproj.CRS` (compound when a height system is named), the horizontal part, its EPSG code
(the SRID the database uses), and a "same horizontal CRS" test. Unknown names raise
`UnknownCRSError` (a `ValueError`) naming the string.

Pure pyproj: no database, no network (PROJ's database is local).
"""

from __future__ import annotations

import re
from functools import lru_cache

import pyproj
from pyproj.exceptions import CRSError

__all__ = [
    "ADV_HORIZONTAL",
    "ADV_VERTICAL",
    "UnknownCRSError",
    "horizontal_crs",
    "horizontal_epsg",
    "resolve_crs",
    "same_horizontal",
    "vertical_epsg",
]

#: AdV horizontal CRS identifiers -> EPSG codes.
ADV_HORIZONTAL: dict[str, int] = {
    "ETRS89_UTM31": 25831,
    "ETRS89_UTM32": 25832,
    "ETRS89_UTM33": 25833,
    "ETRS89_LAT-LON": 4258,
    "ETRS89_LAT-LON-H": 4937,
    "DE_DHDN_3GK2": 31466,
    "DE_DHDN_3GK3": 31467,
    "DE_DHDN_3GK4": 31468,
    "DE_DHDN_3GK5": 31469,
}
#: AdV height system identifiers -> EPSG codes of the vertical CRS.
ADV_VERTICAL: dict[str, int] = {
    "DE_DHHN2016_NH": 7837,
    "DE_DHHN92_NH": 5783,
    "DE_DHHN12_NOH": 5784,
}

_OGC_COMPONENT = re.compile(r"^crs:([A-Za-z]+):([^:]*):([0-9]+)$")
_GML_EPSG_XML = re.compile(r"^https?://www\.opengis\.net/gml/srs/epsg\.xml#([0-9]+)$", re.IGNORECASE)


class UnknownCRSError(ValueError):
    """A CRS name that cannot be resolved; `.srs_name` holds the offending string."""

    def __init__(self, srs_name: str, reason: str = "") -> None:
        self.srs_name = srs_name
        msg = f"unknown CRS name {srs_name!r}"
        if reason:
            msg += f": {reason}"
        super().__init__(msg)


def _compound(codes: list[tuple[str, int]]) -> pyproj.CRS:
    """`[(authority, code), ...]` -> a single or compound CRS."""
    if len(codes) == 1:
        return pyproj.CRS.from_user_input(f"{codes[0][0]}:{codes[0][1]}")
    return pyproj.CRS.from_user_input("+".join(f"{a}:{c}" for a, c in codes))


def _adv(srs_name: str) -> pyproj.CRS:
    """Resolve an AdV URN `urn:adv:crs:<horizontal>[*<height system>[*<geoid model>]]`."""
    parts = srs_name[len("urn:adv:crs:") :].split("*")
    horizontal = parts[0].strip().upper()
    if horizontal not in ADV_HORIZONTAL:
        raise UnknownCRSError(
            srs_name, f"AdV horizontal system {parts[0]!r} not one of {sorted(ADV_HORIZONTAL)}"
        )
    codes = [("EPSG", ADV_HORIZONTAL[horizontal])]
    if len(parts) > 1 and parts[1].strip():
        vertical = parts[1].strip().upper()
        if vertical not in ADV_VERTICAL:
            raise UnknownCRSError(
                srs_name, f"AdV height system {parts[1]!r} not one of {sorted(ADV_VERTICAL)}"
            )
        codes.append(("EPSG", ADV_VERTICAL[vertical]))
    # parts[2] (e.g. GCG2016) names the quasigeoid model: no CRS of its own.
    return _compound(codes)


def _ogc_compound(srs_name: str) -> pyproj.CRS:
    """Resolve `urn:ogc:def:crs,crs:EPSG:6.12:25833,crs:EPSG:6.12:5783`."""
    components = srs_name.split(",")[1:]
    codes: list[tuple[str, int]] = []
    for comp in components:
        m = _OGC_COMPONENT.match(comp.strip())
        if not m:
            raise UnknownCRSError(srs_name, f"compound component {comp!r} is not 'crs:AUTH:version:code'")
        codes.append((m.group(1).upper(), int(m.group(3))))
    if not codes:
        raise UnknownCRSError(srs_name, "compound URN without components")
    return _compound(codes)


@lru_cache(maxsize=256)
def _resolve(name: str) -> pyproj.CRS:
    if not name:
        raise UnknownCRSError(name, "empty CRS name")
    low = name.lower()
    try:
        if low.startswith("urn:adv:crs:"):
            return _adv(name)
        if low.startswith("urn:ogc:def:crs,"):
            return _ogc_compound(name)
        m = _GML_EPSG_XML.match(name)
        if m:
            return pyproj.CRS.from_epsg(int(m.group(1)))
        if name.isdigit():
            return pyproj.CRS.from_epsg(int(name))
        return pyproj.CRS.from_user_input(name)
    except CRSError as exc:
        raise UnknownCRSError(name, str(exc).splitlines()[0]) from exc


def resolve_crs(srs_name: str | pyproj.CRS) -> pyproj.CRS:
    """Any supported CRS spelling (or a `pyproj.CRS`, returned unchanged) -> `pyproj.CRS`.

    A name with a height system gives a compound CRS (e.g. EPSG:25833 + EPSG:5783).

    >>> resolve_crs("urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH*GCG2016").sub_crs_list[0].to_epsg()
    25832
    """
    if isinstance(srs_name, pyproj.CRS):
        return srs_name
    if not isinstance(srs_name, str):
        raise UnknownCRSError(repr(srs_name), "a CRS name must be a string")
    return _resolve(srs_name.strip())


def horizontal_crs(srs_name: str | pyproj.CRS) -> pyproj.CRS:
    """The horizontal (2D) part of a CRS: the first component of a compound CRS, the 2D
    version of a 3D geographic/projected CRS. A purely vertical CRS raises `UnknownCRSError`."""
    crs = resolve_crs(srs_name)
    if crs.is_compound:
        crs = crs.sub_crs_list[0]
    if crs.is_vertical:
        raise UnknownCRSError(str(srs_name), "a vertical CRS has no horizontal part")
    if len(crs.axis_info) == 3:
        crs = crs.to_2d()
    return crs


def horizontal_epsg(srs_name: str | pyproj.CRS) -> int | None:
    """EPSG code of the horizontal CRS (the SRID geometries get in the database), or None
    when the horizontal CRS has no EPSG code (e.g. a local engineering grid given as WKT)."""
    h = horizontal_crs(srs_name)
    code = h.to_epsg()
    if code is None:
        code = h.to_epsg(min_confidence=90)
    return code


def vertical_epsg(srs_name: str | pyproj.CRS) -> int | None:
    """EPSG code of the height system when the name carries one (compound CRS), else None."""
    crs = resolve_crs(srs_name)
    if crs.is_compound:
        for sub in crs.sub_crs_list[1:]:
            if sub.is_vertical:
                return sub.to_epsg()
    return None


def same_horizontal(a: str | pyproj.CRS, b: str | pyproj.CRS) -> bool:
    """True when both names denote the same horizontal CRS (e.g. the AdV URN
    `urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH` and `EPSG:25832`)."""
    ha, hb = horizontal_crs(a), horizontal_crs(b)
    ea, eb = ha.to_epsg(), hb.to_epsg()
    if ea is not None and eb is not None:
        return ea == eb
    return bool(ha.equals(hb, ignore_axis_order=True))

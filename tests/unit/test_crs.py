"""CRS names: every srsName spelling of the real samples, and the other known spellings."""

from __future__ import annotations

import re
from pathlib import Path

import pyproj
import pytest

from tests.conftest import SAMPLE_FILES
from workers.pipeline.geometry.crs import (
    UnknownCRSError,
    horizontal_crs,
    horizontal_epsg,
    resolve_crs,
    same_horizontal,
    vertical_epsg,
)

# spelling -> (horizontal EPSG, vertical EPSG or None)
KNOWN = {
    "EPSG:25832": (25832, None),
    "EPSG:25833": (25833, None),
    "urn:ogc:def:crs:EPSG::25832": (25832, None),
    "urn:ogc:def:crs:EPSG:6.12:25833": (25833, None),
    "urn:ogc:def:crs,crs:EPSG:6.12:25833,crs:EPSG:6.12:5783": (25833, 5783),
    "urn:ogc:def:crs,crs:EPSG::25832,crs:EPSG::7837": (25832, 7837),
    "urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH*GCG2016": (25832, 7837),
    "urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH": (25832, 7837),
    "urn:adv:crs:ETRS89_UTM32*DE_DHHN92_NH": (25832, 5783),
    "urn:adv:crs:ETRS89_UTM33*DE_DHHN2016_NH*GCG2016": (25833, 7837),
    "urn:adv:crs:ETRS89_UTM33*DE_DHHN92_NH": (25833, 5783),
    "urn:adv:crs:ETRS89_UTM32": (25832, None),
    "http://www.opengis.net/def/crs/EPSG/0/25832": (25832, None),
    "https://www.opengis.net/def/crs/EPSG/0/25833": (25833, None),
    "http://www.opengis.net/gml/srs/epsg.xml#25832": (25832, None),
    "EPSG:25832+7837": (25832, 7837),
    "25832": (25832, None),
    " EPSG:25832 ": (25832, None),
    "EPSG:4979": (4326, None),
}


def sample_srs_names(files: list[Path]) -> set[str]:
    names: set[str] = set()
    for f in files:
        with open(f, encoding="utf-8", errors="replace") as fh:
            names.update(re.findall(r'srsName="([^"]+)"', fh.read()))
    return names


def test_every_spelling_in_the_samples_resolves() -> None:
    names = sample_srs_names(SAMPLE_FILES)
    assert len(names) >= 5, names  # the samples carry at least five different spellings
    for name in names:
        crs = resolve_crs(name)
        assert isinstance(crs, pyproj.CRS)
        assert horizontal_epsg(name) in (25832, 25833), name
        assert horizontal_crs(name).is_projected
        assert name in KNOWN, f"spelling {name!r} from the samples missing from KNOWN: add it"


@pytest.mark.parametrize("name", sorted(KNOWN))
def test_known_spellings(name: str) -> None:
    h, v = KNOWN[name]
    assert horizontal_epsg(name) == h
    assert vertical_epsg(name) == v
    assert len(horizontal_crs(name).axis_info) == 2
    if v is not None:
        assert resolve_crs(name).is_compound


def test_same_horizontal() -> None:
    assert same_horizontal("urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH", "EPSG:25832")
    assert same_horizontal("urn:ogc:def:crs,crs:EPSG:6.12:25833,crs:EPSG:6.12:5783", "EPSG:25833")
    assert same_horizontal(pyproj.CRS("EPSG:25833"), "urn:adv:crs:ETRS89_UTM33*DE_DHHN92_NH")
    assert not same_horizontal("EPSG:25832", "EPSG:25833")
    assert not same_horizontal("urn:adv:crs:ETRS89_UTM32*DE_DHHN92_NH", "EPSG:25833")


def test_crs_without_epsg_code() -> None:
    local = pyproj.CRS.from_proj4("+proj=tmerc +lat_0=0 +lon_0=10.3 +k=1 +x_0=0 +y_0=0 +ellps=GRS80 +units=m")
    assert horizontal_epsg(local) is None
    assert same_horizontal(local, local.to_wkt())
    assert not same_horizontal(local, "EPSG:25832")


@pytest.mark.parametrize(
    "name, words",
    [
        ("EPSG:999999", ["EPSG:999999"]),
        ("urn:adv:crs:ETRS89_UTM99*DE_DHHN2016_NH", ["ETRS89_UTM99", "AdV horizontal"]),
        ("urn:adv:crs:ETRS89_UTM32*XX_HEIGHT", ["XX_HEIGHT", "height system"]),
        ("urn:ogc:def:crs,crs:EPSG:6.12:25833,bogus", ["bogus"]),
        ("", ["empty"]),
        ("no such crs", ["no such crs"]),
    ],
)
def test_unknown_names_raise_clear_error(name: str, words: list[str]) -> None:
    with pytest.raises(UnknownCRSError) as exc:
        resolve_crs(name)
    assert isinstance(exc.value, ValueError)
    for w in words:
        assert w in str(exc.value)


def test_vertical_only_has_no_horizontal_part() -> None:
    with pytest.raises(UnknownCRSError, match="vertical"):
        horizontal_crs("EPSG:5783")

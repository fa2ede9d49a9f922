"""A first look at an uploaded CityGML document: its first bytes must be XML whose root element is
a CityGML 1.0/2.0/3.0 `CityModel`, read with the reader's safe settings (no DTD, no entity
resolution, no network). The full document is read later by the worker's import; this only
lets the API refuse a body that is plainly not CityGML (400) before queueing it.
"""

from __future__ import annotations

from lxml import etree

from db.citygml.names import CORE_VERSIONS
from db.service_records import UploadError

_CITY_MODEL_TAGS = frozenset(f"{{{ns}}}CityModel" for ns in CORE_VERSIONS)


def check_citygml_head(head: bytes) -> str:
    """Raise `UploadError` unless `head` (the document's first bytes, or all of it) opens a
    CityGML `CityModel`; returns the CityGML version (`"1.0"`, `"2.0"`, `"3.0"`)."""
    if not head.strip():
        raise UploadError("the body is empty: expected a CityGML document")
    parser = etree.XMLPullParser(
        events=("start",),
        resolve_entities=False,
        no_network=True,
        load_dtd=False,
        dtd_validation=False,
        huge_tree=False,
        remove_comments=True,
        remove_pis=True,
    )
    try:
        parser.feed(head)
        for _event, el in parser.read_events():
            if el.getroottree().docinfo.doctype:
                raise UploadError("not CityGML: DOCTYPE declarations are refused")
            if el.tag not in _CITY_MODEL_TAGS:
                raise UploadError(
                    f"not CityGML: the root element is <{el.tag}>, expected a CityGML 1.0/2.0/3.0 CityModel"
                )
            return CORE_VERSIONS[el.tag[1:].split("}", 1)[0]]
    except etree.XMLSyntaxError as exc:
        raise UploadError(f"not CityGML: not well-formed XML ({exc})") from None
    if b"<!DOCTYPE" in head:
        raise UploadError("not CityGML: DOCTYPE declarations are refused")
    raise UploadError(f"not CityGML: no root element in the first {len(head)} bytes")

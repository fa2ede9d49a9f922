"""Validation of CityGML 2.0 documents against the offline schemas.

In: a file path. Out: a list of error messages with line numbers (empty = valid).

The schema is a small wrapper importing `citygml/2.0/building.xsd`, `appearance.xsd` and
`generics.xsd` from the schemas folder: `$CITYTHERM_SCHEMAS`, else the copy shipped with the
package (`db/citygml/schemas`, package data; see its README). It is parsed once per folder and
cached; no network access.
"""

from __future__ import annotations

import os
from functools import lru_cache
from importlib import resources
from os import PathLike
from pathlib import Path

from lxml import etree

from db.citygml.names import CityGMLError

__all__ = ["citygml2_schema", "schemas_dir", "validate_citygml2"]


def schemas_dir() -> Path:
    """The folder holding `citygml/2.0/*.xsd` (see module docstring)."""
    env = os.environ.get("CITYTHERM_SCHEMAS")
    if env:
        return Path(env)
    folder = resources.files("db.citygml") / "schemas"
    if not isinstance(folder, Path):  # e.g. installed as a zip: lxml needs real files
        raise CityGMLError("the bundled CityGML schemas are not plain files here (set CITYTHERM_SCHEMAS)")
    return folder


@lru_cache(maxsize=4)
def _schema(folder: str) -> etree.XMLSchema:
    base = Path(folder) / "citygml" / "2.0"
    for name in ("building.xsd", "appearance.xsd", "generics.xsd"):
        if not (base / name).is_file():
            raise CityGMLError(f"CityGML 2.0 schema {name} not found in {base} (set CITYTHERM_SCHEMAS)")
    imports = "".join(
        f'<xs:import namespace="http://www.opengis.net/citygml/{ns}" schemaLocation="{(base / f).as_uri()}"/>'
        for ns, f in (
            ("building/2.0", "building.xsd"),
            ("appearance/2.0", "appearance.xsd"),
            ("generics/2.0", "generics.xsd"),
        )
    )
    wrapper = (
        '<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema" '
        'targetNamespace="urn:citytherm:wrapper" elementFormDefault="qualified">' + imports + "</xs:schema>"
    )
    parser = etree.XMLParser(no_network=True, resolve_entities=False, load_dtd=False)
    doc = etree.fromstring(wrapper.encode(), parser, base_url=(base / "wrapper.xsd").as_uri())
    return etree.XMLSchema(doc)


def citygml2_schema() -> etree.XMLSchema:
    """The parsed (cached) CityGML 2.0 wrapper schema."""
    return _schema(str(schemas_dir().resolve()))


def validate_citygml2(path: str | PathLike[str]) -> list[str]:
    """Validate a CityGML 2.0 file; returns `"line N: message"` strings, empty when valid.

    The file is parsed whole (fine for results files; for files of hundreds of MB expect memory
    of a few times the file size)."""
    schema = citygml2_schema()
    parser = etree.XMLParser(no_network=True, resolve_entities=False, load_dtd=False, huge_tree=True)
    try:
        doc = etree.parse(str(path), parser)
    except etree.XMLSyntaxError as exc:
        return [f"line {exc.lineno}: {exc.msg}"]
    if schema.validate(doc):
        return []
    return [f"line {e.line}: {e.message}" for e in schema.error_log]

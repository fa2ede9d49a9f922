"""CityGML / GML namespaces, tag names, the module's exception and id helpers.

In: nothing. Out: namespace URIs per CityGML version, Clark-notation tag sets the reader
dispatches on, `CityGMLError`, and the NCName / stable-id helpers shared by reader and writer.
"""

from __future__ import annotations

import re

GML_NS = "http://www.opengis.net/gml"
GML32_NS = "http://www.opengis.net/gml/3.2"
XLINK_NS = "http://www.w3.org/1999/xlink"
XLINK_HREF = f"{{{XLINK_NS}}}href"

#: CityGML core namespace -> version.
CORE_VERSIONS: dict[str, str] = {
    "http://www.opengis.net/citygml/1.0": "1.0",
    "http://www.opengis.net/citygml/2.0": "2.0",
    "http://www.opengis.net/citygml/3.0": "3.0",
}
VERSIONS = ("1.0", "2.0", "3.0")


def bldg_ns(version: str) -> str:
    """Building module namespace of a CityGML version."""
    return f"http://www.opengis.net/citygml/building/{version}"


def core_ns(version: str) -> str:
    """Core module namespace of a CityGML version."""
    return f"http://www.opengis.net/citygml/{version}"


def app_ns(version: str) -> str:
    """Appearance module namespace of a CityGML version."""
    return f"http://www.opengis.net/citygml/appearance/{version}"


def gen_ns(version: str) -> str:
    """Generics module namespace of a CityGML version."""
    return f"http://www.opengis.net/citygml/generics/{version}"


def gml_id_attr(version: str) -> str:
    """Clark name of the `gml:id` attribute (GML 3.2 for CityGML 3.0)."""
    return f"{{{GML32_NS if version == '3.0' else GML_NS}}}id"


#: Clark names of (top-level) buildings in every version.
BUILDING_TAGS: frozenset[str] = frozenset(f"{{{bldg_ns(v)}}}Building" for v in VERSIONS)
BUILDING_PART_TAGS: frozenset[str] = frozenset(f"{{{bldg_ns(v)}}}BuildingPart" for v in VERSIONS)
APPEARANCE_MEMBER_TAGS: frozenset[str] = frozenset(
    f"{{{core_ns(v)}}}appearanceMember" for v in VERSIONS
) | frozenset(f"{{{app_ns(v)}}}appearanceMember" for v in VERSIONS)
#: Members of a CityModel that hold city objects (`gml:featureMember` in some older files).
CITY_OBJECT_MEMBER_TAGS: frozenset[str] = frozenset(
    f"{{{core_ns(v)}}}cityObjectMember" for v in VERSIONS
) | frozenset({f"{{{GML_NS}}}featureMember", f"{{{GML32_NS}}}featureMember"})
ENVELOPE_TAGS: frozenset[str] = frozenset({f"{{{GML_NS}}}Envelope", f"{{{GML32_NS}}}Envelope"})

#: Boundary surface element local names -> semantic class (`citymodel.SURFACE_CLASSES`).
BOUNDARY_CLASSES: dict[str, str] = {
    "WallSurface": "WallSurface",
    "RoofSurface": "RoofSurface",
    "GroundSurface": "GroundSurface",
    "ClosureSurface": "ClosureSurface",
    "OuterCeilingSurface": "OuterCeilingSurface",
    "OuterFloorSurface": "OuterFloorSurface",
}

#: Standard building attributes (local names) and how their text is converted.
STANDARD_ATTRIBUTES: dict[str, type] = {
    "class": str,
    "function": str,
    "usage": str,
    "yearOfConstruction": str,
    "yearOfDemolition": str,
    "roofType": str,
    "measuredHeight": float,
    "storeysAboveGround": int,
    "storeysBelowGround": int,
    "storeyHeightsAboveGround": str,
    "storeyHeightsBelowGround": str,
}
#: Core city object attributes kept (local names).
CORE_ATTRIBUTES: tuple[str, ...] = ("creationDate", "terminationDate", "relativeToTerrain", "relativeToWater")
#: Standard attributes that may repeat (kept as a tuple of str when they do).
MULTI_ATTRIBUTES: frozenset[str] = frozenset({"function", "usage"})


class CityGMLError(ValueError):
    """A CityGML file that cannot be read (or a model that cannot be written).

    Attributes:
        message: the problem, without file and line.
        path: the file, when known.
        line: 1-based line number of the offending element, when known.
    """

    def __init__(self, message: str, *, path: object = None, line: int | None = None) -> None:
        self.message = message
        self.path = None if path is None else str(path)
        self.line = line
        where = ""
        if self.path is not None:
            where = self.path
        if line is not None:
            where = f"{where}:{line}" if where else f"line {line}"
        super().__init__(f"{where}: {message}" if where else message)


_NCNAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_BAD_CHARS = re.compile(r"[^A-Za-z0-9_.\-]")


def _plain_ncname(value: str) -> bool:
    """True for an NCName of the ASCII subset, without the regular expression (half the time; ids
    are read by the hundred thousand). False says nothing: `_NCNAME` decides then."""
    return (
        value.isascii() and value.replace("-", "_").replace(".", "_").isidentifier() and value[0] not in "-."
    )


def is_ncname(value: str) -> bool:
    """True for an XML NCName (ASCII subset: letter or `_` first, then letters, digits, `_.-`)."""
    return _plain_ncname(value) or bool(_NCNAME.match(value))


def to_ncname(value: str) -> str:
    """A valid NCName for `value`: unchanged when already valid, otherwise invalid characters
    replaced by `_` and a leading `_` added when it starts with a digit, `.` or `-`.

    >>> to_ncname("12:ab#c")
    '_12_ab_c'
    """
    if is_ncname(value):
        return value
    out = _BAD_CHARS.sub("_", value) or "_"
    if not (out[0].isalpha() or out[0] == "_"):
        out = "_" + out
    return out


def get_id(el: object, id_attr: str) -> str | None:
    """The element's `gml:id` as the model keeps it: a valid NCName (`to_ncname`), None if absent.

    Input ids that are not NCNames (e.g. starting with a digit, invalid in GML) are mapped the
    same way everywhere (definitions, `xlink:href`, texture targets), so references still match
    and every written file validates."""
    value = el.get(id_attr)  # type: ignore[attr-defined]
    if not value:
        return None
    if _plain_ncname(value) or _NCNAME.match(value):
        return value
    return to_ncname(value.strip())


def ref_id(uri: str | None) -> str:
    """`'#abc'` (a local reference) -> `'abc'`, mapped like `get_id`; other URIs unchanged."""
    uri = (uri or "").strip()
    if uri.startswith("#"):
        return to_ncname(uri[1:])
    return uri


_LOCAL: dict[object, str] = {}


def local(tag: object) -> str:
    """Local name of a Clark-notation tag (`'{ns}Name'` -> `'Name'`); '' for comments/PIs."""
    try:
        return _LOCAL[tag]
    except (KeyError, TypeError):
        pass
    if not isinstance(tag, str):
        return ""
    name = tag[tag.rfind("}") + 1 :]
    if len(_LOCAL) < 4096:
        _LOCAL[tag] = name
    return name


def namespace(tag: object) -> str:
    """Namespace URI of a Clark-notation tag ('' when none)."""
    if not isinstance(tag, str) or not tag.startswith("{"):
        return ""
    return tag[1 : tag.find("}")]

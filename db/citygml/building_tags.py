"""Tag tables and draft records of the CityGML building reader (`building_read`): which child
element of a building is what (`_draft_kind`), the LoD of a geometry property (`_prop_lod`), the
GML tags the geometry walk dispatches on, and the records a building is collected into while it is
read (`_PolyRec`, `_Scope`, `_Draft`). No reading here; shared by the Python walk and the compiled
one (`_walk.pyx`, which takes `_PolyRec` from `building_read`).

In: Clark-notation tags. Out: small ints, LoDs, and the dataclasses below.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from db.citygml.appearance_read import AppearanceDraft
from db.citygml.names import CORE_ATTRIBUTES, GML32_NS, GML_NS, STANDARD_ATTRIBUTES, local

_GEOM_SUFFIXES = ("Solid", "MultiSurface", "Geometry", "FootPrint", "RoofEdge")
_SKIP_GEOM = frozenset({"LineString", "MultiCurve", "Curve", "CompositeCurve", "Point", "MultiPoint"})
_GENERIC_KINDS: dict[str, type] = {
    "stringAttribute": str,
    "intAttribute": int,
    "doubleAttribute": float,
    "dateAttribute": str,
    "uriAttribute": str,
    "measureAttribute": float,
    "StringAttribute": str,
    "IntAttribute": int,
    "DoubleAttribute": float,
    "DateAttribute": str,
    "UriAttribute": str,
    "MeasureAttribute": float,
    "CodeAttribute": str,
}


@dataclass
class _PolyRec:
    """A polygon definition while its building is being read."""

    id: str | None
    rings: list[tuple[str | None, np.ndarray]]
    surface_class: str
    lod: int
    surface_id: str | None
    in_solid: bool
    collection_id: str | None
    solid_reversed: bool = False


@dataclass
class _Scope:
    """Per top-level building: definitions and references, for xlink resolution."""

    polys: dict[str, _PolyRec] = field(default_factory=dict)
    collections: dict[str, list[_PolyRec]] = field(default_factory=dict)
    refs: list[tuple[str, bool, int, int | None]] = field(default_factory=list)
    ids: set[str] = field(default_factory=set)


@dataclass
class _Draft:
    """A building or part while it is being read."""

    id: str
    generated_id: bool
    is_part: bool
    parent_id: str | None
    polys: list[_PolyRec] = field(default_factory=list)
    parts: list[_Draft] = field(default_factory=list)
    attributes: dict[str, Any] = field(default_factory=dict)
    appearances: list[AppearanceDraft] = field(default_factory=list)
    name: str | None = None
    srs: str | None = None
    envelope_srs: str | None = None


#: one or more plain NCNames (`get_id` keeps them as they are), one a line
_PLAIN_IDS = re.compile(r"[A-Za-z_][A-Za-z0-9_.\-]*(?:\n[A-Za-z_][A-Za-z0-9_.\-]*)*")
_MEMBER_TAGS = frozenset({f"{{{GML_NS}}}surfaceMember", f"{{{GML32_NS}}}surfaceMember"})
_POLYGON_TAGS = frozenset({f"{{{GML_NS}}}Polygon", f"{{{GML32_NS}}}Polygon"})
_LINEAR_RING_TAGS = frozenset({f"{{{GML_NS}}}LinearRing", f"{{{GML32_NS}}}LinearRing"})
#: Ring property tags -> True for the exterior, False for an interior (GML 3 and GML 2 names).
_RING_ROLES: dict[str, bool] = {
    f"{{{ns}}}{name}": role
    for ns in (GML_NS, GML32_NS)
    for name, role in (
        ("exterior", True),
        ("interior", False),
        ("outerBoundaryIs", True),
        ("innerBoundaryIs", False),
    )
}
_PROP_LOD: dict[object, int] = {}


def _prop_lod(tag: object) -> int:
    """LoD of a geometry property tag (`lod2Solid`, `lod1MultiSurface`, `lod3Geometry`, ...), -1
    for any other tag (cached per tag)."""
    lod = _PROP_LOD.get(tag)
    if lod is None:
        ln = local(tag)
        ok = len(ln) > 4 and ln.startswith("lod") and ln[3].isdigit() and ln[4:] in _GEOM_SUFFIXES
        lod = int(ln[3]) if ok else -1
        if len(_PROP_LOD) < 4096:
            _PROP_LOD[tag] = lod
    return lod


def _is_gml(tag: str) -> bool:
    """True for a tag in a GML namespace (3.1 or 3.2)."""
    return tag.startswith("{http://www.opengis.net/gml")


#: what a child element of a building is, for `_BuildingReader.draft` (cached per tag)
(
    _D_OTHER,
    _D_GEOMETRY,
    _D_BOUNDARY,
    _D_ENVELOPE,
    _D_NAME,
    _D_STANDARD,
    _D_CORE,
    _D_APPEARANCE,
    _D_PARTS,
    _D_INSTALLATION,
    _D_GENERIC,
) = range(11)
_DRAFT_KIND: dict[str, int] = {}


def _draft_kind(tag: str) -> int:
    """`_D_*` kind of the child element tag `tag` of a building (cached per tag)."""
    kind = _DRAFT_KIND.get(tag)
    if kind is not None:
        return kind
    ln, is_gml = local(tag), _is_gml(tag)
    if _prop_lod(tag) >= 0:
        kind = _D_GEOMETRY
    elif ln in ("boundedBy", "boundary") and not is_gml:
        kind = _D_BOUNDARY
    elif ln == "boundedBy":
        kind = _D_ENVELOPE
    elif ln == "name" and is_gml:
        kind = _D_NAME
    elif ln in STANDARD_ATTRIBUTES and not is_gml:
        kind = _D_STANDARD
    elif ln in CORE_ATTRIBUTES:
        kind = _D_CORE
    elif ln == "appearance":
        kind = _D_APPEARANCE
    elif ln in ("consistsOfBuildingPart", "buildingPart"):
        kind = _D_PARTS
    elif ln == "outerBuildingInstallation":
        kind = _D_INSTALLATION
    elif ln in _GENERIC_KINDS or ln in ("genericAttribute", "genericAttributeSet"):
        kind = _D_GENERIC
    else:
        kind = _D_OTHER
    if len(_DRAFT_KIND) < 4096:
        _DRAFT_KIND[tag] = kind
    return kind

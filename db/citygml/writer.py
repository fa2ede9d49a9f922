"""Streaming CityGML 2.0 writer.

In: `citymodel.Building`s (from any input version), the model CRS name, and appearances: each
building's own (kept from the input) plus the job's results (`extra_appearances`, keyed by the id
of the building or building part that carries them). Out: a CityGML 2.0 file, written building by
building with lxml `xmlfile` (memory independent of the number of buildings), valid against the
CityGML 2.0 schemas (`validate.validate_citygml2`).

Structure written per building (CityGML 2.0 element order): `gml:name`, `core:creationDate`, ...,
generic attributes, `app:appearance/app:Appearance` (local appearances, as `results-format.md`
requires: never `app:appearanceMember` inside a building), standard attributes, then geometry:
unclassified polygons in `lodXMultiSurface` (`lod0FootPrint` for LoD 0) or inline in
`lodXSolid` when they are solid members; classified polygons (LoD 2-4) in
`bldg:boundedBy/bldg:<Class>Surface/bldg:lodXMultiSurface`, referenced from the solid with
`xlink:href` when `in_solid` (through `gml:OrientableSurface orientation="-"` when
`solid_reversed`); then `consistsOfBuildingPart`. Ids (building, part, surface,
polygon, ring, MultiSurface) are kept; an input id that is not a valid NCName is written through
`names.to_ncname` (also in texture targets). Coordinates are written as shortest round-trip
decimals, so reading the file back gives the same float64 values.

Not written (not held by `citymodel`): addresses, external references, terrain intersection
curves, openings, installations as such (their polygons are the building's), uom and codeSpace.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from os import PathLike
from typing import Any

import numpy as np
from lxml import etree

from db.citygml.appearance_write import SurfaceDataWriter, fmt, xsd_double
from db.citygml.names import (
    CORE_ATTRIBUTES,
    GML_NS,
    STANDARD_ATTRIBUTES,
    XLINK_HREF,
    XLINK_NS,
    CityGMLError,
    app_ns,
    bldg_ns,
    core_ns,
    gen_ns,
    to_ncname,
)
from workers.pipeline.geometry.citymodel import SURFACE_CLASSES, Appearance, Building, Polygon

__all__ = ["NSMAP", "envelope_of", "write_citygml"]

CORE, BLDG, APP, GEN = core_ns("2.0"), bldg_ns("2.0"), app_ns("2.0"), gen_ns("2.0")
NSMAP = {"core": CORE, "bldg": BLDG, "app": APP, "gen": GEN, "gml": GML_NS, "xlink": XLINK_NS}
_GML_ID = f"{{{GML_NS}}}id"
_G = f"{{{GML_NS}}}"
_B = f"{{{BLDG}}}"
_DATE = re.compile(r"^\d{4}-\d{2}-\d{2}")
_YEAR = re.compile(r"^-?\d{4}$")
_TERRAIN = frozenset(
    {
        "entirelyAboveTerrain",
        "substantiallyAboveTerrain",
        "substantiallyAboveAndBelowTerrain",
        "substantiallyBelowTerrain",
        "entirelyBelowTerrain",
    }
)
_WATER = frozenset(
    {
        "entirelyAboveWaterSurface",
        "substantiallyAboveWaterSurface",
        "substantiallyAboveAndBelowWaterSurface",
        "substantiallyBelowWaterSurface",
        "entirelyBelowWaterSurface",
        "temporarilyAboveAndBelowWaterSurface",
    }
)
_BOUNDARY_CLASSES = frozenset(SURFACE_CLASSES) - {"unclassified"}


def _sub(parent: etree._Element, tag: str, text: str | None = None) -> etree._Element:
    el = etree.SubElement(parent, tag)
    if text is not None:
        el.text = text
    return el


class _BuildingWriter:
    """Builds the lxml element of one building (parts included)."""

    def __init__(
        self,
        srs_name: str | None,
        extra: Mapping[str, Sequence[Appearance]],
        sdw: SurfaceDataWriter,
        surface_attributes: Mapping[str, Mapping[str, Any]] | None = None,
    ):
        self.srs_name = srs_name
        self.extra = extra
        self.sdw = sdw
        self.surface_attributes = surface_attributes if surface_attributes is not None else {}
        self.ids: set[str] = set()

    def _surface_generics(self, surf: etree._Element, polys: Sequence[Polygon]) -> None:
        """Generic attributes of a thematic surface from its polygons' `surface_attributes`:
        integers summed over the polygons, other values from the first polygon that has them."""
        merged: dict[str, Any] = {}
        for p in polys:
            for k, v in self.surface_attributes.get(p.id, {}).items():
                if isinstance(v, int) and not isinstance(v, bool) and k in merged:
                    merged[k] += v
                else:
                    merged.setdefault(k, v)
        for k, v in merged.items():
            self._generic(surf, k, v)

    def _id(self, value: str | None) -> str | None:
        """Id as written; None when missing or already used in this building."""
        if not value:
            return None
        out = to_ncname(value)
        if out in self.ids:
            return None
        self.ids.add(out)
        return out

    # ---- geometry ------------------------------------------------------------------------------
    def _geom_root(self, prop: etree._Element, tag: str, srs: str | None, gid: str | None) -> etree._Element:
        el = etree.SubElement(prop, _G + tag)
        if gid:
            el.set(_GML_ID, gid)
        if srs:
            el.set("srsName", srs)
            el.set("srsDimension", "3")
        return el

    def _polygon(self, parent: etree._Element, p: Polygon) -> None:
        member = etree.SubElement(parent, _G + "surfaceMember")
        poly = etree.SubElement(member, _G + "Polygon")
        pid = self._id(p.id)
        if pid:
            poly.set(_GML_ID, pid)
        for k, ring in enumerate(p.rings):
            wrap = etree.SubElement(poly, _G + ("exterior" if k == 0 else "interior"))
            lr = etree.SubElement(wrap, _G + "LinearRing")
            rid = self._id(ring.id)
            if rid:
                lr.set(_GML_ID, rid)
            coords = np.asarray(ring.coords, dtype=np.float64)
            if coords.ndim != 2 or coords.shape[1] != 3 or len(coords) < 4:
                raise CityGMLError(f"ring {ring.id!r} of polygon {p.id!r}: need (N>=4, 3) coordinates")
            _sub(lr, _G + "posList", fmt(coords.ravel().tolist()))

    def _multisurface(self, prop: etree._Element, polys: list[Polygon], srs: str | None) -> None:
        coll = next((p.collection_id for p in polys if p.collection_id), None)
        ms = self._geom_root(prop, "MultiSurface", srs, self._id(coll))
        for p in polys:
            self._polygon(ms, p)

    def _solid(
        self, prop: etree._Element, inline: list[Polygon], refs: list[Polygon], srs: str | None
    ) -> None:
        solid = self._geom_root(prop, "Solid", srs, None)
        ext = etree.SubElement(solid, _G + "exterior")
        coll = next((p.collection_id for p in inline if p.collection_id), None)
        cs = etree.SubElement(ext, _G + "CompositeSurface")
        gid = self._id(coll)
        if gid:
            cs.set(_GML_ID, gid)
        for p in inline:
            self._polygon(cs, p)
        for p in refs:
            if p.solid_reversed:
                member = etree.SubElement(cs, _G + "surfaceMember")
                orient = etree.SubElement(member, _G + "OrientableSurface", orientation="-")
                etree.SubElement(orient, _G + "baseSurface", {XLINK_HREF: f"#{to_ncname(p.id)}"})
            else:
                etree.SubElement(cs, _G + "surfaceMember", {XLINK_HREF: f"#{to_ncname(p.id)}"})

    # ---- attributes ----------------------------------------------------------------------------
    @staticmethod
    def _generic(parent: etree._Element, name: str, value: Any) -> None:
        if isinstance(value, bool) or not isinstance(value, int | float):
            kind = "stringAttribute"
            text = " ".join(map(str, value)) if isinstance(value, tuple | list) else str(value)
        elif isinstance(value, int):
            kind, text = "intAttribute", str(value)
        else:
            kind, text = "doubleAttribute", xsd_double(float(value))
        el = etree.SubElement(parent, f"{{{GEN}}}{kind}", name=name)
        _sub(el, f"{{{GEN}}}value", text)

    @staticmethod
    def _standard_ok(name: str, value: Any) -> bool:
        if name in ("measuredHeight",):
            return isinstance(value, int | float) and not isinstance(value, bool)
        if name in ("storeysAboveGround", "storeysBelowGround"):
            return isinstance(value, int) and not isinstance(value, bool) and value >= 0
        if name in ("yearOfConstruction", "yearOfDemolition"):
            return isinstance(value, str) and bool(_YEAR.match(value))
        if name in ("storeyHeightsAboveGround", "storeyHeightsBelowGround"):
            return isinstance(value, str) and all(
                t.replace(".", "", 1).replace("-", "", 1).isdigit() for t in value.split()
            )
        return isinstance(value, str | tuple)

    # ---- building ------------------------------------------------------------------------------
    def building(self, b: Building, srs: str | None) -> etree._Element:
        el = etree.Element(_B + ("BuildingPart" if b.is_part else "Building"))
        bid = self._id(b.id)
        if bid:
            el.set(_GML_ID, bid)
        srs = b.srs_name or srs
        if b.name is not None:
            _sub(el, _G + "name", b.name)
        attrs = dict(b.attributes)
        core_vals = {k: attrs.pop(k) for k in CORE_ATTRIBUTES if k in attrs}
        for k in ("creationDate", "terminationDate"):
            v = str(core_vals.get(k, ""))
            if _DATE.match(v):
                _sub(el, f"{{{CORE}}}{k}", v[:10])
        for k, allowed in (("relativeToTerrain", _TERRAIN), ("relativeToWater", _WATER)):
            if core_vals.get(k) in allowed:
                _sub(el, f"{{{CORE}}}{k}", str(core_vals[k]))
        standard = {k: attrs.pop(k) for k in list(attrs) if k in STANDARD_ATTRIBUTES}
        for k, v in list(standard.items()):
            if not self._standard_ok(k, v):
                attrs[k] = standard.pop(k)  # kept as a generic attribute rather than lost
        for k, v in attrs.items():
            self._generic(el, k, v)
        for app in (*b.appearances, *self.extra.get(b.id, ())):
            self.sdw.appearance(el, app)
        for k in STANDARD_ATTRIBUTES:
            if k not in standard:
                continue
            v = standard[k]
            for item in v if isinstance(v, tuple) else (v,):
                if k == "measuredHeight":
                    _sub(el, _B + k, xsd_double(float(item))).set("uom", "m")
                elif k.startswith("storeyHeights"):
                    _sub(el, _B + k, str(item)).set("uom", "m")
                else:
                    _sub(el, _B + k, str(item))
        self._geometry(el, b, srs)
        for part in b.parts:
            prop = etree.SubElement(el, _B + "consistsOfBuildingPart")
            prop.append(self.building(part, srs))
        return el

    def _geometry(self, el: etree._Element, b: Building, srs: str | None) -> None:
        by_lod_ms: dict[int, list[Polygon]] = {}
        by_lod_inline: dict[int, list[Polygon]] = {}
        by_lod_refs: dict[int, list[Polygon]] = {}
        surfaces: dict[tuple, list[Polygon]] = {}
        run = 0
        prev_key: tuple | None = None
        for p in b.polygons:
            classified = p.surface_class in _BOUNDARY_CLASSES and 2 <= p.lod <= 4
            if classified:
                key: tuple = (p.surface_class, p.surface_id) if p.surface_id else (p.surface_class, None, run)
                if p.surface_id is None and prev_key != key:
                    run += 1
                    key = (p.surface_class, None, run)
                prev_key = key
                surfaces.setdefault(key, []).append(p)
                if p.in_solid:
                    by_lod_refs.setdefault(p.lod, []).append(p)
            else:
                prev_key = None
                if p.in_solid and 1 <= p.lod <= 4 and not p.solid_reversed:
                    by_lod_inline.setdefault(p.lod, []).append(p)
                else:
                    by_lod_ms.setdefault(max(0, min(p.lod, 4)), []).append(p)
                    if p.in_solid and 1 <= p.lod <= 4:  # used reversed: referenced, not inline
                        by_lod_refs.setdefault(p.lod, []).append(p)
        if 0 in by_lod_ms:
            self._multisurface(etree.SubElement(el, _B + "lod0FootPrint"), by_lod_ms[0], srs)

        def lod_block(lod: int) -> None:
            if lod in by_lod_inline or lod in by_lod_refs:
                prop = etree.SubElement(el, f"{_B}lod{lod}Solid")
                self._solid(prop, by_lod_inline.get(lod, []), by_lod_refs.get(lod, []), srs)
            if lod in by_lod_ms:
                self._multisurface(etree.SubElement(el, f"{_B}lod{lod}MultiSurface"), by_lod_ms[lod], srs)

        lod_block(1)
        lod_block(2)
        for key, polys in surfaces.items():
            prop = etree.SubElement(el, _B + "boundedBy")
            surf = etree.SubElement(prop, _B + key[0])
            sid = self._id(key[1]) if key[1] else None
            if sid:
                surf.set(_GML_ID, sid)
            if self.surface_attributes:
                self._surface_generics(surf, polys)
            for lod in (2, 3, 4):
                sel = [p for p in polys if p.lod == lod]
                if sel:
                    self._multisurface(etree.SubElement(surf, f"{_B}lod{lod}MultiSurface"), sel, srs)
        lod_block(3)
        lod_block(4)


def envelope_of(buildings: Iterable[Building]) -> tuple[np.ndarray, np.ndarray] | None:
    """3D bounds `(lower (3,), upper (3,))` of all polygons of the buildings (parts included), for
    `write_citygml(envelope=...)`; None when there is no polygon."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for b in buildings:
        if next(b.iter_polygons(), None) is None:
            continue
        blo, bhi = b.bounds()
        lo, hi = np.minimum(lo, blo), np.maximum(hi, bhi)
    return (lo, hi) if np.all(np.isfinite(lo)) else None


def write_citygml(
    path: str | PathLike[str],
    buildings: Iterable[Building],
    *,
    srs_name: str | None,
    extra_appearances: Mapping[str, Sequence[Appearance]] | None = None,
    envelope: tuple[np.ndarray, np.ndarray] | None = None,
    model_appearances: Sequence[Appearance] = (),
    name: str | None = None,
    trailing_appearances: Iterable[Appearance] = (),
    surface_attributes: Mapping[str, Mapping[str, Any]] | None = None,
) -> int:
    """Write buildings as a CityGML 2.0 file, streamed; returns the number of buildings written.

    Args:
        path: output file.
        buildings: top-level buildings (parts nested), any input version; consumed once.
        srs_name: the model CRS as it should be written (`srsName` of the envelope and of every
            building's geometry that has no `srs_name` of its own).
        extra_appearances: appearances to add (e.g. the job's `thermal-ir` theme), keyed by the id
            of the building or building part they are written into (normally the top-level one).
        envelope: `(lower (3,), upper (3,))` for the CityModel's `gml:boundedBy`, optional.
        model_appearances: CityModel-level appearances (`app:appearanceMember`), e.g.
            `ModelHeader.appearances` of the input, written before the buildings (so buildings'
            appearances may share their surface data by `xlink:href`).
        name: `gml:name` of the CityModel.
        trailing_appearances: CityModel-level appearances written after the buildings, iterated
            only once the buildings are written: the `late_appearances` list of
            `reader.open_model`, filled while `buildings` is consumed. Surface data they share
            with a building's appearance are written there and referenced by `xlink:href`.
        surface_attributes: generic attributes (`gen:*Attribute`, name -> int, float or string)
            of thematic surfaces (`bldg:WallSurface`, ...), keyed by the id of a polygon they
            hold (e.g. a job's facade figures); a surface of several polygons sums integers and
            takes other values from its first polygon that has them.
    """
    extra = extra_appearances or {}
    sdw = SurfaceDataWriter()
    n = 0
    with etree.xmlfile(str(path), encoding="utf-8") as xf:
        xf.write_declaration()
        with xf.element(f"{{{CORE}}}CityModel", nsmap=NSMAP):
            xf.write("\n")
            if name is not None:
                gname = etree.Element(_G + "name", nsmap=NSMAP)
                gname.text = name
                xf.write(gname, pretty_print=True)
            if envelope is not None:
                lo, hi = (np.asarray(v, dtype=np.float64).ravel() for v in envelope)
                bb = etree.Element(_G + "boundedBy", nsmap=NSMAP)
                env = etree.SubElement(bb, _G + "Envelope")
                if srs_name:
                    env.set("srsName", srs_name)
                env.set("srsDimension", str(len(lo)))
                _sub(env, _G + "lowerCorner", fmt(lo.tolist()))
                _sub(env, _G + "upperCorner", fmt(hi.tolist()))
                xf.write(bb, pretty_print=True)
            for app in model_appearances:
                member = etree.Element(f"{{{APP}}}appearanceMember", nsmap=NSMAP)
                sdw.appearance_element(member, app)
                xf.write(member, pretty_print=True)
            for b in buildings:
                member = etree.Element(f"{{{CORE}}}cityObjectMember", nsmap=NSMAP)
                member.append(_BuildingWriter(srs_name, extra, sdw, surface_attributes).building(b, srs_name))
                xf.write(member, pretty_print=True)
                n += 1
            for app in trailing_appearances:
                member = etree.Element(f"{{{APP}}}appearanceMember", nsmap=NSMAP)
                sdw.appearance_element(member, app)
                xf.write(member, pretty_print=True)
    return n

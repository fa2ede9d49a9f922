"""One CityGML building element (with its parts) -> `citymodel.Building`.

In: a complete `bldg:Building` lxml element (CityGML 1.0, 2.0 or 3.0), as handed over by the
streaming reader once its end tag has been parsed. Out: a frozen `Building` with its parts,
attributes, appearances and polygons (rings `(N, 3)` float64 in the model CRS, as written).

Geometry is collected from `lodXSolid`, `lodXMultiSurface`, `lodXGeometry`, `lod0FootPrint` /
`lod0RoofEdge`, boundary surfaces (`bldg:boundedBy` in 1.0/2.0, `core:boundary` in 3.0) and outer
building installations, through `MultiSurface`, `CompositeSurface`, `Solid`/`Shell`,
`OrientableSurface` (orientation `-` reverses the rings of a polygon defined inside it) and
`Surface`/`PolygonPatch`. `xlink:href` references are resolved after the whole building has been
read (forward references included): a polygon defined in a boundary surface and referenced from
a solid is one polygon with `in_solid=True`. References to polygons outside the building are
logged and dropped.

Ids: a polygon without `gml:id` gets `<building id>_poly<k>` (k = its position among the
building's polygons in document order), a ring without one `<polygon id>_ring<j>` (j = 0 for the
exterior, 1.. for the interiors); `_g` is appended until the id is unused in the building.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, MutableMapping
from typing import Any

import numpy as np
from lxml import etree

from db.citygml.appearance_read import finish_appearance, parse_appearance
from db.citygml.building_tags import (
    _D_APPEARANCE,
    _D_BOUNDARY,
    _D_CORE,
    _D_ENVELOPE,
    _D_GENERIC,
    _D_GEOMETRY,
    _D_INSTALLATION,
    _D_NAME,
    _D_OTHER,
    _D_PARTS,
    _D_STANDARD,
    _DRAFT_KIND,
    _GENERIC_KINDS,
    _LINEAR_RING_TAGS,
    _MEMBER_TAGS,
    _PLAIN_IDS,
    _POLYGON_TAGS,
    _PROP_LOD,
    _RING_ROLES,
    _SKIP_GEOM,
    _Draft,
    _draft_kind,
    _is_gml,
    _PolyRec,
    _prop_lod,
    _Scope,
)
from db.citygml.gml_coords import ring_coords
from db.citygml.names import (
    BOUNDARY_CLASSES,
    MULTI_ATTRIBUTES,
    STANDARD_ATTRIBUTES,
    XLINK_HREF,
    CityGMLError,
    get_id,
    local,
    ref_id,
    to_ncname,
)
from db.compiled import OFF as _COMPILED_OFF
from workers.pipeline.geometry.citymodel import Building, Polygon, Ring, SurfaceData

log = logging.getLogger(__name__)

# the compiled geometry walk (setup.py builds it); without it the Python walk below is used
try:
    from db.citygml import _walk
except ImportError:  # not built (or for another Python)
    _walk = None  # type: ignore[assignment]
if _COMPILED_OFF:
    _walk = None  # type: ignore[assignment]
if _walk is not None and not _walk.selftest():  # built against other lxml headers: not used
    _walk = None
#: False when the compiled walk is not built or `CITYTHERM_NO_COMPILED=1` turns it off
COMPILED_WALK = _walk is not None


class _BuildingReader:
    """Reads one top-level building element (and its parts) into a `Building`."""

    def __init__(
        self,
        id_attr: str,
        default_srs: str | None,
        surface_registry: Mapping[str, SurfaceData],
        unchecked_ids: bool = False,
    ):
        self.id_attr = id_attr
        self.default_srs = default_srs
        self.global_sd = surface_registry
        self.scope = _Scope()
        self.local_sd: dict[str, SurfaceData] = {}
        #: `unchecked_ids`: ids and local references are taken as written and collected here, to
        #: be checked at once (`ids_plain`) before they are used; None: each mapped as it is read
        self.raw_ids: list[str] | None = [] if unchecked_ids else None

    def _id(self, el: etree._Element) -> str | None:
        """`get_id` of `el`, or (unchecked mode) its `gml:id` as written, collected in `raw_ids`."""
        raw = self.raw_ids
        if raw is None:
            return get_id(el, self.id_attr)
        value = el.get(self.id_attr)
        if not value:
            return None
        raw.append(value)
        return value

    def _ref(self, href: str) -> str:
        """`ref_id` of an `xlink:href`, or (unchecked mode) a local reference's id as written."""
        raw = self.raw_ids
        if raw is None or href[:1] != "#":
            return ref_id(href)
        value = href[1:]
        raw.append(value)
        return value

    def ids_plain(self) -> bool:
        """True when every id taken unchecked is a plain NCName (ASCII letters, digits, `_.-`, not
        starting with a digit, `.` or `-`): `get_id` and `ref_id` return such an id unchanged, so
        the building read is the one a checked read gives."""
        raw = self.raw_ids
        return not raw or _PLAIN_IDS.fullmatch("\n".join(raw)) is not None

    # ---- geometry -------------------------------------------------------------------------
    def _polygon(self, el: etree._Element, d: _Draft, ctx: tuple, dim: int) -> None:
        """Record a `gml:Polygon` (or patch) `el`: its rings `(N, 3)` (exterior first; reversed
        when `ctx`'s sign is -1), ids and context (`_geometry`); `dim`: the srsDimension in force."""
        cls, sid, lod, in_solid, coll, sign = ctx
        scope = self.scope
        rings: list[tuple[str | None, np.ndarray]] = []
        interiors: list[tuple[str | None, np.ndarray]] = []
        for ch in el[:]:
            role = _RING_ROLES.get(ch.tag)
            if role is None:
                continue
            for ring in ch[:]:
                tag = ring.tag
                if tag not in _LINEAR_RING_TAGS:
                    if isinstance(tag, str):
                        raise CityGMLError(f"unsupported ring type <{local(tag)}>", line=ring.sourceline)
                    continue
                coords = ring_coords(ring, dim)
                if sign < 0:
                    coords = coords[::-1].copy()
                rid = self._id(ring)
                if rid:
                    scope.ids.add(rid)
                (rings if role else interiors).append((rid, coords))
        if len(rings) != 1:
            raise CityGMLError(f"<{local(el.tag)}> needs exactly one exterior ring", line=el.sourceline)
        pid = self._id(el)
        rec = _PolyRec(pid, rings + interiors if interiors else rings, cls, lod, sid, in_solid, coll)
        d.polys.append(rec)
        if pid:
            scope.ids.add(pid)
            scope.polys[pid] = rec
        if coll:
            scope.collections.setdefault(coll, []).append(rec)

    def _geometry(self, el: etree._Element, d: _Draft, ctx: tuple, dim: int) -> None:
        """Walk a geometry subtree; `ctx` = (class, surface id, lod, in_solid, collection id, sign)."""
        href = el.get(XLINK_HREF)
        if href is not None:
            self.scope.refs.append((self._ref(href), ctx[3], ctx[5], el.sourceline))
            return
        ln = local(el.tag)
        if not ln or ln in _SKIP_GEOM:
            return
        sdim = el.get("srsDimension")
        if sdim:
            dim = int(sdim)
        srs = el.get("srsName")
        if srs and d.srs is None:
            d.srs = srs
        if ln in ("Polygon", "PolygonPatch", "Triangle", "Rectangle"):
            self._polygon(el, d, ctx, dim)
            return
        cls, sid, lod, in_solid, coll, sign = ctx
        if ln == "OrientableSurface" and el.get("orientation", "+").strip() == "-":
            sign = -sign
        elif ln == "Solid":
            in_solid = True
        elif ln in ("MultiSurface", "CompositeSurface", "Shell", "Surface", "TriangulatedSurface"):
            gid = self._id(el)
            if gid:
                coll = gid
                self.scope.ids.add(gid)
        ctx = (cls, sid, lod, in_solid, coll, sign)
        for ch in el[:]:
            tag = ch.tag
            if tag in _MEMBER_TAGS:  # fast path: surfaceMember -> href or Polygon
                href = ch.get(XLINK_HREF)
                if href is not None:
                    self.scope.refs.append((self._ref(href), in_solid, sign, ch.sourceline))
                    continue
                for g in ch[:]:
                    gtag = g.tag
                    if gtag in _POLYGON_TAGS and g.get("srsName") is None and g.get("srsDimension") is None:
                        self._polygon(g, d, ctx, dim)
                    elif isinstance(gtag, str):
                        self._geometry(g, d, ctx, dim)
            elif isinstance(tag, str):
                self._geometry(ch, d, ctx, dim)

    def _geom_property(self, el: etree._Element, d: _Draft, cls: str, sid: str | None) -> bool:
        """Handle a `lodX<Geometry>` property; False when `el` is not one."""
        lod = _prop_lod(el.tag)
        if lod < 0:
            return False
        ctx = (cls, sid, lod, False, None, 1)
        if el.get(XLINK_HREF) is not None:
            self._geometry(el, d, ctx, 3)
            return True
        for g in el[:]:  # the property's geometry (a property element carries no srsName)
            if isinstance(g.tag, str):
                self._geometry(g, d, ctx, 3)
        return True

    def _boundary(self, prop: etree._Element, d: _Draft) -> None:
        for surf in prop[:]:
            ln = local(surf.tag)
            if not ln:
                continue
            cls = BOUNDARY_CLASSES.get(ln, "unclassified")
            sid = self._id(surf)
            if sid:
                self.scope.ids.add(sid)
            for ch in surf:  # geometry properties among the surface's attributes
                lod = _PROP_LOD.get(ch.tag)
                if lod is None or lod >= 0:
                    self._geom_property(ch, d, cls, sid)

    def _installation(self, prop: etree._Element, d: _Draft) -> None:
        for inst in prop[:]:
            for ch in inst[:]:
                if not isinstance(ch.tag, str):
                    continue
                if local(ch.tag) in ("boundedBy", "boundary") and not _is_gml(ch.tag):
                    self._boundary(ch, d)
                else:
                    self._geom_property(ch, d, "unclassified", None)

    # ---- attributes ------------------------------------------------------------------------
    def _generic(self, el: etree._Element, d: _Draft, prefix: str = "") -> None:
        ln = local(el.tag)
        if ln == "genericAttribute":  # CityGML 3.0 wrapper
            for ch in el[:]:
                if isinstance(ch.tag, str):
                    self._generic(ch, d, prefix)
            return
        if ln in ("genericAttributeSet", "GenericAttributeSet"):
            name = el.get("name") or next((c.text for c in el if local(c.tag) == "name"), "") or ""
            for ch in el[:]:
                if local(ch.tag) not in ("name", "value"):
                    self._generic(ch, d, f"{prefix}{name.strip()}.")
            return
        kind = _GENERIC_KINDS.get(ln)
        if kind is None:
            return
        name = el.get("name")
        value_el = None
        for ch in el[:]:
            cl = local(ch.tag)
            if cl == "name" and name is None:
                name = (ch.text or "").strip()
            elif cl == "value":
                value_el = ch
        if not name or value_el is None:
            return
        text = (value_el.text or "").strip()
        try:
            d.attributes[prefix + name] = kind(text)
        except ValueError:
            d.attributes[prefix + name] = text

    def _standard(self, ln: str, el: etree._Element, d: _Draft) -> None:
        text = (el.text or "").strip()
        kind = STANDARD_ATTRIBUTES.get(ln, str)
        try:
            value: Any = kind(text)
        except ValueError:
            value = text
        if ln in MULTI_ATTRIBUTES and ln in d.attributes:
            prev = d.attributes[ln]
            d.attributes[ln] = (*prev, value) if isinstance(prev, tuple) else (prev, value)
        else:
            d.attributes[ln] = value

    # ---- building --------------------------------------------------------------------------
    def draft(self, el: etree._Element, bid: str, generated: bool, parent: str | None) -> _Draft:
        d = _Draft(id=bid, generated_id=generated, is_part=parent is not None, parent_id=parent)
        self.scope.ids.add(bid)
        n_parts = 0
        kinds = _DRAFT_KIND
        for ch in el[:]:
            tag = ch.tag
            if not isinstance(tag, str):
                continue
            kind = kinds.get(tag)
            if kind is None:
                kind = _draft_kind(tag)
            if kind == _D_BOUNDARY:
                self._boundary(ch, d)
            elif kind == _D_GENERIC:
                self._generic(ch, d)
            elif kind == _D_GEOMETRY:
                self._geom_property(ch, d, "unclassified", None)
            elif kind == _D_OTHER:
                continue
            elif kind == _D_STANDARD:
                self._standard(local(tag), ch, d)
            elif kind == _D_CORE:
                d.attributes[local(tag)] = (ch.text or "").strip()
            elif kind == _D_ENVELOPE:
                env = ch[0] if len(ch) else None
                if env is not None and env.get("srsName"):
                    d.envelope_srs = env.get("srsName")
            elif kind == _D_NAME:
                d.name = d.name if d.name is not None else (ch.text or "").strip()
            elif kind == _D_APPEARANCE:
                for app in ch[:]:
                    if local(app.tag) == "Appearance":
                        d.appearances.append(parse_appearance(app, self.id_attr, self.local_sd, d.id))
            elif kind == _D_PARTS:
                for part in ch[:]:
                    if local(part.tag) == "BuildingPart":
                        pid = self._id(part)
                        n_parts += 1
                        gen = not pid
                        d.parts.append(self.draft(part, pid or f"{bid}_part{n_parts}", gen, bid))
            elif kind == _D_INSTALLATION:
                self._installation(ch, d)
        return d

    def _unique(self, base: str) -> str:
        out = to_ncname(base)
        while out in self.scope.ids:
            out += "_g"
        self.scope.ids.add(out)
        return out

    def build(self, d: _Draft, parent_srs: str | None) -> Building:
        srs = d.srs or d.envelope_srs or parent_srs
        polys: list[Polygon] = []
        for k, rec in enumerate(d.polys):
            gen_pid = rec.id is None
            pid = rec.id if rec.id is not None else self._unique(f"{d.id}_poly{k}")
            rings = []
            for j, (rid, coords) in enumerate(rec.rings):
                gen_r = rid is None
                rings.append(Ring(rid if rid else self._unique(f"{pid}_ring{j}"), coords, gen_r))
            polys.append(
                Polygon(
                    id=pid,
                    exterior=rings[0],
                    interiors=tuple(rings[1:]),
                    surface_class=rec.surface_class,
                    lod=rec.lod,
                    surface_id=rec.surface_id,
                    in_solid=rec.in_solid,
                    generated_id=gen_pid,
                    collection_id=rec.collection_id,
                    solid_reversed=rec.solid_reversed,
                )
            )
        registry: MutableMapping[str, SurfaceData] = {}
        if d.appearances:
            registry = {**self.global_sd, **self.local_sd}
        return Building(
            id=d.id,
            polygons=tuple(polys),
            parts=tuple(self.build(p, srs) for p in d.parts),
            attributes=d.attributes,
            is_part=d.is_part,
            parent_id=d.parent_id,
            srs_name=srs if srs is not None else self.default_srs,
            appearances=tuple(finish_appearance(a, registry) for a in d.appearances),
            name=d.name,
            generated_id=d.generated_id,
        )

    def resolve(self) -> None:
        """Apply the `xlink:href` references collected in the building."""
        for ref, in_solid, sign, line in self.scope.refs:
            rec = self.scope.polys.get(ref)
            targets = [rec] if rec is not None else self.scope.collections.get(ref)
            if targets is None:
                log.warning("line %s: xlink:href #%s not found in its building; reference dropped", line, ref)
                continue
            if in_solid:
                for t in targets:
                    t.in_solid = True
                    t.solid_reversed = sign < 0


class _CompiledReader(_BuildingReader):
    """`_BuildingReader` whose boundary and geometry properties are walked by `_walk` (unchecked
    ids only); `_walk.Bail` when a building holds something left to the Python walk."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        #: (owner element, node address) of references whose line libxml2 does not keep in the
        #: node (-k in `scope.refs`: entry k - 1); looked up for the references warned about
        self.far: list[tuple[etree._Element, int]] = []

    def _boundary(self, prop: etree._Element, d: _Draft) -> None:
        _walk.boundary(self, prop, d)

    def _geom_property(self, el: etree._Element, d: _Draft, cls: str, sid: str | None) -> bool:
        return _walk.geom_property(self, el, d, cls, sid)

    def resolve(self) -> None:
        """`_BuildingReader.resolve`, with the true line of each reference it warns about."""
        refs, polys, colls = self.scope.refs, self.scope.polys, self.scope.collections
        for k, (ref, in_solid, sign, line) in enumerate(refs):
            if type(line) is int and line < 0 and ref not in polys and ref not in colls:
                refs[k] = (ref, in_solid, sign, _walk.far_line(self.far, -line - 1))
        super().resolve()


if _walk is not None:
    _walk.setup(_PolyRec, BOUNDARY_CLASSES, ring_coords)


def read_building(
    el: etree._Element,
    *,
    id_attr: str,
    fallback_id: str,
    default_srs: str | None,
    surface_registry: Mapping[str, SurfaceData] | None = None,
    compiled: bool | None = None,
) -> Building:
    """A complete top-level building element -> `Building` (parts nested).

    Args:
        el: the `bldg:Building` element, fully parsed.
        id_attr: Clark name of `gml:id` for the file's GML version.
        fallback_id: id to use when the building has no `gml:id` (stable: from its position).
        default_srs: the model's `srsName`, used when the building's geometry names none.
        surface_registry: model-level surface data by id (for `xlink:href` from local appearances).
        compiled: walk the geometry with the compiled `_walk` (None: when it is built and not
            turned off, `COMPILED_WALK`); the Building is the same either way.
    """
    registry = surface_registry or {}
    # ids are checked all at once after the walk (the usual file: every id a plain NCName); a
    # building with any other id is read again with each id mapped as it is read
    draft = None
    use_compiled = COMPILED_WALK if compiled is None else (compiled and _walk is not None)
    if use_compiled:
        reader = _CompiledReader(id_attr, default_srs, registry, unchecked_ids=True)
        bid = reader._id(el)
        try:
            draft = reader.draft(el, bid or fallback_id, not bid, None)
        except _walk.Bail:  # something the compiled walk leaves to the Python walk: read again
            draft = None
    if draft is None:
        reader = _BuildingReader(id_attr, default_srs, registry, unchecked_ids=True)
        bid = reader._id(el)
        draft = reader.draft(el, bid or fallback_id, not bid, None)
    if not reader.ids_plain():
        reader = _BuildingReader(id_attr, default_srs, registry)
        bid = reader._id(el)
        draft = reader.draft(el, bid or fallback_id, not bid, None)
    reader.resolve()
    return reader.build(draft, None)

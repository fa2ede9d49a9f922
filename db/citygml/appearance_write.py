"""`citymodel.Appearance` -> CityGML 2.0 `app:Appearance` lxml elements.

In: appearances (input ones kept from the reader, and the job's results). Out: elements valid
against the CityGML 2.0 appearance schema, as `results-format.md` specifies: a
`ParameterizedTexture` with `imageURI`, `mimeType`, one `target uri="#<polygon id>"` per target
polygon holding a `TexCoordList` with one `textureCoordinates ring="#<ring id>"` per ring (`s t`
per vertex, closing vertex included).

A surface data object shared by several appearances (same `id`) is written in full once per
document and referenced with `xlink:href` afterwards (`SurfaceDataWriter.written` remembers it).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable

import numpy as np
from lxml import etree

from db.citygml.names import GML_NS, XLINK_HREF, app_ns, to_ncname
from workers.pipeline.geometry.citymodel import (
    Appearance,
    GeoreferencedTexture,
    ParameterizedTexture,
    SurfaceData,
    X3DMaterial,
)

APP = app_ns("2.0")
_GML_ID = f"{{{GML_NS}}}id"
_TEXTURE_TYPES = frozenset({"specific", "typical", "unknown"})
_WRAP_MODES = frozenset({"none", "wrap", "mirror", "clamp", "border"})


def xsd_double(value: float) -> str:
    """A float as XML Schema `double` text: shortest round-trip decimal, `NaN`, `INF`, `-INF`."""
    if math.isfinite(value):
        return repr(value)
    if math.isnan(value):
        return "NaN"
    return "INF" if value > 0 else "-INF"


def fmt(values: Iterable[float]) -> str:
    """Numbers as shortest round-trip decimal text (`repr`; `NaN`/`INF` spelled as XML Schema
    does), space separated."""
    vals = list(values)
    if all(map(math.isfinite, vals)):
        return " ".join(map(repr, vals))
    return " ".join(map(xsd_double, vals))


def _sub(parent: etree._Element, name: str, text: str | None = None, **attrib: str) -> etree._Element:
    el = etree.SubElement(parent, f"{{{APP}}}{name}", attrib)
    if text is not None:
        el.text = text
    return el


def _unit(v: float) -> bool:
    return 0.0 <= v <= 1.0


class SurfaceDataWriter:
    """Writes appearances; keeps the ids of surface data already written in the document.

    Args:
        ref: maps a target id (polygon or ring, as stored) to the id written in the document
            (identity unless an input id was not a valid NCName).
    """

    def __init__(self, ref: Callable[[str], str] = to_ncname) -> None:
        self.ref = ref
        self.written: set[str] = set()

    def appearance(self, parent: etree._Element, app: Appearance) -> None:
        """Append `app:appearance/app:Appearance` (local appearance) to `parent`."""
        prop = _sub(parent, "appearance")
        self.appearance_element(prop, app)

    def appearance_element(self, parent: etree._Element, app: Appearance) -> etree._Element:
        """Append an `app:Appearance` element to `parent` (a property element)."""
        el = _sub(parent, "Appearance")
        if app.id:
            el.set(_GML_ID, self.ref(app.id))
        _sub(el, "theme", app.theme)
        for sd in app.surface_data:
            member = _sub(el, "surfaceDataMember")
            sid = self.ref(sd.id)
            if sid in self.written:
                member.set(XLINK_HREF, f"#{sid}")
                continue
            self.written.add(sid)
            self._surface_data(member, sd, sid)
        return el

    def _surface_data(self, member: etree._Element, sd: SurfaceData, sid: str) -> None:
        if isinstance(sd, ParameterizedTexture):
            el = _sub(member, "ParameterizedTexture", **{_GML_ID: sid})
            self._texture_head(el, sd.image_uri, sd.mime_type, sd.texture_type, sd.wrap_mode, sd.border_color)
            for t in sd.targets:
                target = _sub(el, "target", uri=f"#{self.ref(t.polygon_id)}")
                tcl = _sub(target, "TexCoordList")
                for ring_id, st in t.ring_coords.items():
                    st = np.asarray(st, dtype=np.float64)
                    _sub(tcl, "textureCoordinates", fmt(st.ravel().tolist()), ring=f"#{self.ref(ring_id)}")
        elif isinstance(sd, X3DMaterial):
            el = _sub(member, "X3DMaterial", **{_GML_ID: sid})
            if not sd.is_front:
                _sub(el, "isFront", "false")
            if sd.ambient_intensity is not None and _unit(sd.ambient_intensity):
                _sub(el, "ambientIntensity", xsd_double(float(sd.ambient_intensity)))
            for name, col in (
                ("diffuseColor", sd.diffuse_color),
                ("emissiveColor", sd.emissive_color),
                ("specularColor", sd.specular_color),
            ):
                if col is not None and len(col) == 3 and all(_unit(c) for c in col):
                    _sub(el, name, fmt(float(c) for c in col))
            for name, val in (("shininess", sd.shininess), ("transparency", sd.transparency)):
                if val is not None and _unit(val):
                    _sub(el, name, xsd_double(float(val)))
            if sd.is_smooth is not None:
                _sub(el, "isSmooth", "true" if sd.is_smooth else "false")
            for t in sd.targets:
                _sub(el, "target", f"#{self.ref(t)}")
        elif isinstance(sd, GeoreferencedTexture):
            el = _sub(member, "GeoreferencedTexture", **{_GML_ID: sid})
            self._texture_head(el, sd.image_uri, sd.mime_type, None, None, None)
            if sd.prefer_world_file is not None:
                _sub(el, "preferWorldFile", "true" if sd.prefer_world_file else "false")
            if sd.reference_point is not None and len(sd.reference_point) in (2, 3):
                rp = _sub(el, "referencePoint")
                point = etree.SubElement(rp, f"{{{GML_NS}}}Point")
                pos = etree.SubElement(point, f"{{{GML_NS}}}pos")
                pos.text = fmt(float(v) for v in sd.reference_point)
            if sd.orientation is not None and len(sd.orientation) == 4:
                _sub(el, "orientation", fmt(float(v) for v in sd.orientation))
            for t in sd.targets:
                _sub(el, "target", f"#{self.ref(t)}")
        else:  # pragma: no cover - SurfaceData is a closed union
            raise TypeError(f"unsupported surface data {type(sd).__name__}")

    @staticmethod
    def _texture_head(
        el: etree._Element,
        image_uri: str,
        mime_type: str | None,
        texture_type: str | None,
        wrap_mode: str | None,
        border_color: str | None,
    ) -> None:
        _sub(el, "imageURI", image_uri)
        if mime_type:
            _sub(el, "mimeType", mime_type)
        if texture_type in _TEXTURE_TYPES:
            _sub(el, "textureType", texture_type)
        if wrap_mode in _WRAP_MODES:
            _sub(el, "wrapMode", wrap_mode)
        if border_color:
            try:
                vals = [float(v) for v in border_color.split()]
            except ValueError:
                vals = []
            if len(vals) in (3, 4) and all(_unit(v) for v in vals):
                _sub(el, "borderColor", border_color.strip())

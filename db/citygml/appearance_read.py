"""Reading CityGML 1.0 / 2.0 appearances (`app:Appearance`) into `citymodel.Appearance`.

In: an `app:Appearance` lxml element (local appearance of a building, or the content of a
CityModel's `app:appearanceMember`). Out: an `AppearanceDraft` whose surface data are parsed and
registered by `gml:id`; surface data referenced with `xlink:href` (shared between themes, possibly
defined later in the same building) are resolved by `finish_appearance` once the whole building
has been read, so that a shared `ParameterizedTexture` is one object in every theme that uses it.

CityGML 3.0 appearances (different structure) are not read.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, MutableMapping
from dataclasses import dataclass, field

import numpy as np
from lxml import etree

from db.citygml.names import XLINK_HREF, CityGMLError, get_id, local, ref_id
from workers.pipeline.geometry.citymodel import (
    Appearance,
    GeoreferencedTexture,
    ParameterizedTexture,
    SurfaceData,
    TextureTarget,
    X3DMaterial,
)

log = logging.getLogger(__name__)


@dataclass
class AppearanceDraft:
    """An appearance whose `xlink:href` surface-data members are not yet resolved.

    `members` holds parsed surface data or the referenced id (str, without `#`)."""

    theme: str
    id: str | None
    members: list[SurfaceData | str] = field(default_factory=list)
    line: int | None = None


def _floats(text: str | None, el: etree._Element, n: int | None = None) -> tuple[float, ...]:
    """Whitespace-separated numbers of an element's text (`n` of them when given)."""
    try:
        vals = tuple(float(v) for v in (text or "").split())
    except ValueError as exc:
        raise CityGMLError(f"<{local(el.tag)}>: not a list of numbers", line=el.sourceline) from exc
    if n is not None and len(vals) != n:
        raise CityGMLError(f"<{local(el.tag)}>: expected {n} numbers, got {len(vals)}", line=el.sourceline)
    return vals


def _bool(text: str | None) -> bool | None:
    t = (text or "").strip().lower()
    if t in ("true", "1"):
        return True
    if t in ("false", "0"):
        return False
    return None


def _parameterized(el: etree._Element, sid: str) -> ParameterizedTexture:
    fields: dict[str, str] = {}
    targets: list[TextureTarget] = []
    for ch in el:
        ln = local(ch.tag)
        if ln == "target":
            rings: dict[str, np.ndarray] = {}
            for tcl in ch:
                if local(tcl.tag) != "TexCoordList":
                    continue  # TexCoordGen (a transformation matrix) is not kept
                for tc in tcl:
                    if local(tc.tag) != "textureCoordinates":
                        continue
                    vals = _floats(tc.text, tc)
                    if len(vals) % 2:
                        raise CityGMLError("textureCoordinates: odd number of values", line=tc.sourceline)
                    rings[ref_id(tc.get("ring"))] = np.asarray(vals, dtype=np.float64).reshape(-1, 2)
            targets.append(TextureTarget(polygon_id=ref_id(ch.get("uri")), ring_coords=rings))
        elif ln:
            fields[ln] = (ch.text or "").strip()
    return ParameterizedTexture(
        id=sid,
        image_uri=fields.get("imageURI", ""),
        targets=tuple(targets),
        mime_type=fields.get("mimeType", "image/png") or "image/png",
        texture_type=fields.get("textureType"),
        wrap_mode=fields.get("wrapMode"),
        border_color=fields.get("borderColor"),
    )


def _x3d(el: etree._Element, sid: str) -> X3DMaterial:
    kw: dict[str, object] = {}
    targets: list[str] = []
    for ch in el:
        ln = local(ch.tag)
        if ln == "target":
            targets.append(ref_id(ch.text))
        elif ln in ("diffuseColor", "specularColor", "emissiveColor"):
            key = {"diffuseColor": "diffuse_color", "specularColor": "specular_color"}.get(
                ln, "emissive_color"
            )
            kw[key] = _floats(ch.text, ch, 3)
        elif ln in ("ambientIntensity", "shininess", "transparency"):
            kw[{"ambientIntensity": "ambient_intensity"}.get(ln, ln)] = _floats(ch.text, ch, 1)[0]
        elif ln == "isSmooth":
            kw["is_smooth"] = _bool(ch.text)
        elif ln == "isFront":
            kw["is_front"] = _bool(ch.text) is not False
    return X3DMaterial(id=sid, targets=tuple(targets), **kw)  # type: ignore[arg-type]


def _georeferenced(el: etree._Element, sid: str) -> GeoreferencedTexture:
    kw: dict[str, object] = {}
    targets: list[str] = []
    image_uri = ""
    for ch in el:
        ln = local(ch.tag)
        if ln == "target":
            targets.append(ref_id(ch.get("uri") or ch.text))
        elif ln == "imageURI":
            image_uri = (ch.text or "").strip()
        elif ln == "mimeType":
            kw["mime_type"] = (ch.text or "").strip()
        elif ln == "preferWorldFile":
            kw["prefer_world_file"] = _bool(ch.text)
        elif ln == "orientation":
            kw["orientation"] = _floats(ch.text, ch, 4)
        elif ln == "referencePoint":
            pos = [p for p in ch.iter() if local(p.tag) in ("pos", "coordinates")]
            if pos:
                kw["reference_point"] = _floats(pos[0].text.replace(",", " ") if pos[0].text else "", pos[0])
    return GeoreferencedTexture(id=sid, image_uri=image_uri, targets=tuple(targets), **kw)  # type: ignore[arg-type]


_PARSERS = {
    "ParameterizedTexture": _parameterized,
    "X3DMaterial": _x3d,
    "GeoreferencedTexture": _georeferenced,
}


def parse_appearance(
    el: etree._Element, id_attr: str, registry: MutableMapping[str, SurfaceData], prefix: str
) -> AppearanceDraft:
    """Parse an `app:Appearance` element.

    Args:
        el: the `app:Appearance` element.
        id_attr: Clark name of `gml:id` for the file's GML version.
        registry: surface data by `gml:id`; inline surface data are added to it.
        prefix: prefix for ids generated for surface data without `gml:id` (e.g. the building id).
    """
    draft = AppearanceDraft(theme="", id=get_id(el, id_attr), line=el.sourceline)
    for ch in el:
        ln = local(ch.tag)
        if ln == "theme":
            draft.theme = (ch.text or "").strip()
        elif ln in ("surfaceDataMember", "surfaceData"):
            href = ch.get(XLINK_HREF)
            if href is not None:
                draft.members.append(ref_id(href))
                continue
            for sd in ch:
                parser = _PARSERS.get(local(sd.tag))
                if parser is None:
                    continue
                sid = get_id(sd, id_attr) or f"{prefix}_sd{len(registry)}"
                obj = parser(sd, sid)
                registry[sid] = obj
                draft.members.append(obj)
    return draft


def finish_appearance(draft: AppearanceDraft, registry: Mapping[str, SurfaceData]) -> Appearance:
    """Resolve the draft's `xlink:href` members against `registry` (unresolvable ones are dropped
    with a warning in the log) -> `Appearance`."""
    members: list[SurfaceData] = []
    for m in draft.members:
        if isinstance(m, str):
            obj = registry.get(m)
            if obj is None:
                log.warning("line %s: surface data #%s not found; reference dropped", draft.line, m)
                continue
            members.append(obj)
        else:
            members.append(m)
    return Appearance(theme=draft.theme, surface_data=tuple(members), id=draft.id)

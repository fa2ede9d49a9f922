"""Streaming CityGML reader (1.0, 2.0 fully; 3.0 buildings: geometry, ids, attributes).

In: a CityGML file path. Out: `ModelHeader` (version, srsName, envelope, name, CityModel-level
appearances) and `citymodel.Building` objects, one per top-level `bldg:Building`, with its
`BuildingPart`s nested in `parts`. Coordinates are the file's, in its CRS (see `citymodel`).

Memory does not grow with the file: lxml `iterparse` hands over each building once its end tag
has been read; it is converted (`building_read.read_building`) and its element, with everything
before it, is dropped from the tree.

Safety: entities are never resolved, DTDs never loaded, the network never touched; a document
with a DOCTYPE declaration (DTD, entity definitions: billion laughs, XXE) is refused. Every
problem raises `CityGMLError` naming the file and line. `huge_tree=True` lifts libxml2's limits
(text nodes > 10 MB, very deep trees) for files that need it; it is off by default.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable, Iterator
from dataclasses import replace
from os import PathLike
from pathlib import Path
from typing import BinaryIO

import numpy as np
from lxml import etree

from db.citygml.appearance_read import finish_appearance, parse_appearance
from db.citygml.building_read import read_building
from db.citygml.names import (
    APPEARANCE_MEMBER_TAGS,
    BUILDING_TAGS,
    CITY_OBJECT_MEMBER_TAGS,
    CORE_VERSIONS,
    ENVELOPE_TAGS,
    GML32_NS,
    GML_NS,
    CityGMLError,
    gml_id_attr,
    local,
    namespace,
)
from workers.pipeline.geometry.citymodel import Appearance, Building, ModelHeader, SurfaceData

__all__ = ["CityGMLError", "iter_buildings", "open_model", "read_header", "read_model"]

log = logging.getLogger(__name__)

_CITY_MODEL_TAGS = frozenset(f"{{{ns}}}CityModel" for ns in CORE_VERSIONS)
_NAME_TAGS = frozenset({f"{{{GML_NS}}}name", f"{{{GML32_NS}}}name"})
_TAGS = sorted(
    _CITY_MODEL_TAGS
    | BUILDING_TAGS
    | APPEARANCE_MEMBER_TAGS
    | CITY_OBJECT_MEMBER_TAGS
    | ENVELOPE_TAGS
    | _NAME_TAGS
)
#: Elements whose building children are top-level buildings.
_BUILDING_PARENTS = CITY_OBJECT_MEMBER_TAGS | frozenset(
    {f"{{{GML_NS}}}featureMembers", f"{{{GML32_NS}}}featureMembers"}
)
_PROLOG_LIMIT = 1 << 20
_DOCTYPE = re.compile(rb"<!DOCTYPE|<\x00!\x00D\x00O\x00C\x00T\x00Y\x00P\x00E")


def _check_prolog(path: Path) -> None:
    """Refuse a document whose prolog (before the root element) has a DOCTYPE declaration."""
    with open(path, "rb") as f:
        head = f.read(_PROLOG_LIMIT)
    # The prolog ends at the first '<' that starts neither a PI, a comment nor a declaration.
    pos = 0
    while True:
        lt = head.find(b"<", pos)
        if lt < 0 or lt + 1 >= len(head):
            break
        nxt = head[lt + 1 : lt + 2]
        if head.startswith(b"<!--", lt):
            end = head.find(b"-->", lt + 4)
            pos = end + 3 if end >= 0 else len(head)
        elif nxt == b"?":
            end = head.find(b"?>", lt + 2)
            pos = end + 2 if end >= 0 else len(head)
        elif nxt == b"!" or nxt == b"\x00":
            break
        else:
            return
    m = _DOCTYPE.search(head)
    if m:
        line = head[: m.start()].count(b"\n") + 1
        raise CityGMLError(
            "DOCTYPE declarations (DTDs, entity definitions) are refused: "
            "no entity is expanded, no DTD is loaded",
            path=path,
            line=line,
        )


def _envelope(env: etree._Element) -> tuple[tuple[np.ndarray, np.ndarray] | None, str | None]:
    """`gml:Envelope` -> ((lower (3,), upper (3,)) or None, srsName)."""
    corners: dict[str, np.ndarray] = {}
    for ch in env:
        ln = local(ch.tag)
        if ln in ("lowerCorner", "upperCorner"):
            try:
                corners[ln] = np.array((ch.text or "").split(), dtype=np.float64)
            except ValueError as exc:
                raise CityGMLError(f"<{ln}>: not a list of numbers", line=ch.sourceline) from exc
        elif ln == "pos" or ln == "coordinates":
            key = "lowerCorner" if "lowerCorner" not in corners else "upperCorner"
            corners[key] = np.array((ch.text or "").replace(",", " ").split(), dtype=np.float64)
    lo, hi = corners.get("lowerCorner"), corners.get("upperCorner")
    box = (lo, hi) if lo is not None and hi is not None and lo.shape == hi.shape else None
    return box, env.get("srsName")


class _Stream:
    """One pass over a file, yielding `("header", ModelHeader)` (exactly once, before the first
    building), `("building", Building)` and `("appearance", Appearance)` for CityModel-level
    appearances that come after the header. `source` (optional) opens the bytes to parse instead
    of the file (e.g. a part of it behind its header, `db.import_stream`); `path` still names the
    file in messages and its prolog is checked."""

    def __init__(
        self, path: str | PathLike[str], huge_tree: bool, source: Callable[[], BinaryIO] | None = None
    ) -> None:
        self.path = Path(path)
        self.huge_tree = huge_tree
        self.source = source
        self.surface_data: dict[str, SurfaceData] = {}

    def events(self) -> Iterator[tuple[str, object]]:
        if not self.path.is_file():
            raise CityGMLError("no such file", path=self.path)
        _check_prolog(self.path)
        try:
            yield from self._events()
        except etree.XMLSyntaxError as exc:
            line = exc.lineno if exc.lineno else None
            msg = str(exc.msg if getattr(exc, "msg", None) else exc)
            if "huge" in msg.lower() and not self.huge_tree:
                msg += " (pass huge_tree=True for files with very large text nodes)"
            raise CityGMLError(f"XML error: {msg}", path=self.path, line=line) from None
        except CityGMLError as exc:
            if exc.path is None:
                raise CityGMLError(exc.message, path=self.path, line=exc.line) from None
            raise

    def _events(self) -> Iterator[tuple[str, object]]:
        version: str | None = None
        id_attr = gml_id_attr("2.0")
        header: ModelHeader | None = None
        pending: list[Appearance] = []
        envelope: tuple[np.ndarray, np.ndarray] | None = None
        srs: str | None = None
        name: str | None = None
        root: etree._Element | None = None
        n_buildings = 0
        with open(self.path, "rb") if self.source is None else self.source() as f:
            it = etree.iterparse(
                f,
                events=("end",),
                tag=_TAGS,
                resolve_entities=False,
                no_network=True,
                load_dtd=False,
                dtd_validation=False,
                huge_tree=self.huge_tree,
                remove_comments=True,
                remove_pis=True,
                # whitespace between elements (indentation) is never read: not building those
                # text nodes saves ~20 % of the parse; a leaf's text is kept even when blank
                remove_blank_text=True,
            )
            first = True
            for _event, el in it:
                if first:
                    first = False
                    r = el.getroottree().getroot()
                    if r.tag not in _CITY_MODEL_TAGS:
                        raise CityGMLError(
                            f"not a CityGML document: root element is <{r.tag}>, expected a CityGML "
                            "1.0/2.0/3.0 CityModel",
                            line=r.sourceline,
                        )
                    if r.getroottree().docinfo.doctype:
                        raise CityGMLError("DOCTYPE declarations are refused", line=1)
                    root = r
                    version = CORE_VERSIONS[namespace(r.tag)]
                    id_attr = gml_id_attr(version)
                tag = el.tag
                parent = el.getparent()
                if tag in BUILDING_TAGS:
                    if parent is None or parent.tag not in _BUILDING_PARENTS:
                        continue  # nested (e.g. in a CityObjectGroup): not a top-level building
                    n_buildings += 1
                    b = read_building(
                        el,
                        id_attr=id_attr,
                        fallback_id=f"building{n_buildings}",
                        default_srs=srs,
                        surface_registry=self.surface_data,
                    )
                    el.clear()
                    while el.getprevious() is not None:  # several buildings in one gml:featureMembers
                        del parent[0]
                    if n_buildings == 1:
                        if header is None:
                            header = ModelHeader(version, srs, envelope, name, tuple(pending))
                            pending.clear()
                        if header.srs_name is None:
                            header = replace(header, srs_name=b.srs_name)
                        yield "header", header
                    yield "building", b
                elif tag in CITY_OBJECT_MEMBER_TAGS or tag in APPEARANCE_MEMBER_TAGS:
                    if tag in APPEARANCE_MEMBER_TAGS:
                        for app in el:
                            if local(app.tag) == "Appearance":
                                draft = parse_appearance(app, id_attr, self.surface_data, "model")
                                a = finish_appearance(draft, self.surface_data)
                                (pending if n_buildings == 0 else []).append(a)
                                if n_buildings:
                                    yield "appearance", a
                    el.clear()
                    while el.getprevious() is not None:
                        del el.getparent()[0]
                elif parent is not None and parent is root:
                    if tag in _NAME_TAGS and name is None:
                        name = (el.text or "").strip()
                elif tag in ENVELOPE_TAGS and parent is not None and parent.getparent() is root:
                    envelope, srs = _envelope(el)
            if root is None:
                r = it.root
                if r is not None:
                    raise CityGMLError(
                        f"not a CityGML document: root element is <{r.tag}>, expected a CityGML "
                        "1.0/2.0/3.0 CityModel",
                        line=r.sourceline,
                    )
                raise CityGMLError("empty document", line=1)
            if n_buildings == 0:
                yield "header", ModelHeader(version or "2.0", srs, envelope, name, tuple(pending))


def read_header(path: str | PathLike[str], *, huge_tree: bool = False) -> ModelHeader:
    """Version, srsName, envelope, name of a CityGML file (reads up to its first building).

    `srs_name` is the CityModel envelope's, or else the first building's."""
    gen = _Stream(path, huge_tree).events()
    try:
        for kind, obj in gen:
            if kind == "header":
                return obj  # type: ignore[return-value]
    finally:
        gen.close()
    raise CityGMLError("no CityModel found", path=path)  # pragma: no cover - events always yield a header


def iter_buildings(path: str | PathLike[str], *, huge_tree: bool = False) -> Iterator[Building]:
    """Top-level buildings of a CityGML file, streamed in document order (parts nested)."""
    for kind, obj in _Stream(path, huge_tree).events():
        if kind == "building":
            yield obj  # type: ignore[misc]


def open_model(
    path: str | PathLike[str], *, huge_tree: bool = False
) -> tuple[ModelHeader, Iterator[Building], list[Appearance]]:
    """Streaming access to a whole model: `(header, buildings, late_appearances)`.

    The header is read at once; `buildings` streams the top-level buildings; CityModel-level
    appearances that stand after the first building are appended to `late_appearances` while
    `buildings` is consumed (complete once it is exhausted). One pass over the file."""
    events = _Stream(path, huge_tree).events()
    late: list[Appearance] = []
    header: ModelHeader | None = None
    for kind, obj in events:
        if kind == "header":
            header = obj  # type: ignore[assignment]
            break
    assert header is not None

    def buildings() -> Iterator[Building]:
        for kind, obj in events:
            if kind == "building":
                yield obj  # type: ignore[misc]
            elif kind == "appearance":
                late.append(obj)  # type: ignore[arg-type]

    return header, buildings(), late


def read_model(path: str | PathLike[str], *, huge_tree: bool = False) -> tuple[ModelHeader, list[Building]]:
    """The whole model: header (with every CityModel-level appearance, wherever it stands in the
    file) and all top-level buildings. Holds all buildings in memory: use `iter_buildings` for
    large files."""
    header: ModelHeader | None = None
    buildings: list[Building] = []
    late: list[Appearance] = []
    for kind, obj in _Stream(path, huge_tree).events():
        if kind == "header":
            header = obj  # type: ignore[assignment]
        elif kind == "building":
            buildings.append(obj)  # type: ignore[arg-type]
        else:
            late.append(obj)  # type: ignore[arg-type]
    assert header is not None
    if late:
        header = replace(header, appearances=(*header.appearances, *late))
    return header, buildings

# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False
"""Compiled geometry walk of a CityGML building (the hot part of `building_read`), over lxml's
libxml2 nodes without creating Python proxies for them.

In: the `_BuildingReader` of `building_read` (unchecked-ids mode), a boundary property or a
`lodX<Geometry>` property element, the building's `_Draft`. Out: the same `_PolyRec`s, ids,
collections and references, in the same order, as `_BuildingReader._boundary` /
`_geom_property` record; rings `(N, 3)` float64 parsed with CPython's own correctly rounded
`PyOS_string_to_double` (what `float()` and numpy use for such text: the same doubles).

Anything the walk does not take exactly as the Python walk does (an attribute value that is not
one text node, a posList with other characters than digits, signs, `.`, `e`/`E` and ASCII
whitespace, an `srsDimension` other than "2"/"3", an unsupported ring, a polygon without exactly
one exterior ring) raises `Bail`: the caller then reads the whole building again with the Python
walk. Rings that are not one 3D `posList` go through the Python `ring_coords` on a proxy.
Only struct fields of libxml2's nodes are read (lxml's headers); no libxml2 function is called.
"""

from cpython.buffer cimport PyBUF_C_CONTIGUOUS, PyBUF_WRITABLE, PyBuffer_Release, PyObject_GetBuffer
from cpython.conversion cimport PyOS_string_to_double
from libc.string cimport strcmp

from lxml.includes cimport tree
from lxml.includes.tree cimport xmlAttr, xmlNode
cimport lxml.includes.etreepublic as cetree

import numpy as np

cetree.import_lxml__etree()

class Bail(Exception):
    """The building holds something the compiled walk leaves to the Python walk."""


cdef const char* GML = b"http://www.opengis.net/gml"
cdef const char* GML32 = b"http://www.opengis.net/gml/3.2"
cdef const char* XLINK = b"http://www.w3.org/1999/xlink"

# set by `setup` (building_read's objects; no import cycle)
cdef object _PolyRec = None
cdef object _BOUNDARY_CLASSES = None
cdef object _ring_coords = None
cdef bytes _id_ns = b""
cdef int _ready = 0


def setup(polyrec: type, boundary_classes: dict, ring_coords: object) -> None:
    """Hand over the Python objects the walk builds or calls (`building_read` does, at import)."""
    global _PolyRec, _BOUNDARY_CLASSES, _ring_coords, _ready
    _PolyRec = polyrec
    _BOUNDARY_CLASSES = boundary_classes
    _ring_coords = ring_coords
    _ready = 1


cdef inline bint _is_elem(xmlNode* n) noexcept:
    return n.type == tree.XML_ELEMENT_NODE


cdef inline bint _is_elemlike(xmlNode* n) noexcept:
    """What lxml iterates as a child (`el[:]`, `len(el)`): elements, comments, PIs, entity refs."""
    return (n.type == tree.XML_ELEMENT_NODE or n.type == tree.XML_COMMENT_NODE
            or n.type == tree.XML_PI_NODE or n.type == tree.XML_ENTITY_REF_NODE)


cdef inline bint _in_gml(xmlNode* n) noexcept:
    """The node is in the GML 3.1 or 3.2 namespace (exactly, as the tag sets of `building_read`)."""
    if n.ns is NULL or n.ns.href is NULL:
        return False
    cdef const char* h = <const char*>n.ns.href
    return strcmp(h, GML) == 0 or strcmp(h, GML32) == 0


cdef inline bint _name_is(xmlNode* n, const char* name) noexcept:
    return strcmp(<const char*>n.name, name) == 0


cdef object _attr(xmlNode* n, const char* ns, const char* name):
    """`el.get(...)`: the attribute's value (str) or None; `ns` NULL for an attribute without
    namespace. `Bail` for a value that is not one text node."""
    cdef xmlAttr* a = n.properties
    cdef xmlNode* t
    while a is not NULL:
        if strcmp(<const char*>a.name, name) == 0:
            if ns is NULL:
                ok = a.ns is NULL
            else:
                ok = a.ns is not NULL and a.ns.href is not NULL and strcmp(<const char*>a.ns.href, ns) == 0
            if ok:
                t = a.children
                if t is NULL:
                    return ""
                if t.next is not NULL or t.type != tree.XML_TEXT_NODE or t.content is NULL:
                    raise Bail("attribute value of several nodes")
                return (<bytes>(<const char*>t.content)).decode("utf-8")
        a = a.next
    return None


cdef inline bint _has_attr(xmlNode* n, const char* ns, const char* name) noexcept:
    cdef xmlAttr* a = n.properties
    while a is not NULL:
        if strcmp(<const char*>a.name, name) == 0:
            if ns is NULL:
                if a.ns is NULL:
                    return True
            elif a.ns is not NULL and a.ns.href is not NULL and strcmp(<const char*>a.ns.href, ns) == 0:
                return True
        a = a.next
    return False


cdef class _Ctx:
    """What one call of `boundary` / `geom_property` works with: the reader's collections (looked
    up once, not per polygon), the owner element (for proxies) and the surface in force."""

    cdef object reader, owner, d, raw, ids, polys, collections, refs, dpolys, far
    cdef bytes id_ns_bytes
    cdef const char* id_ns

    def __cinit__(self, reader: object, owner: object, d: object) -> None:
        if not _ready or reader.raw_ids is None:
            raise Bail("not set up")
        id_attr = reader.id_attr
        if not id_attr.startswith("{") or not id_attr.endswith("}id"):
            raise Bail("id attribute")
        self.id_ns_bytes = id_attr[1 : len(id_attr) - 3].encode("utf-8")
        self.id_ns = self.id_ns_bytes
        scope = reader.scope
        self.reader, self.owner, self.d = reader, owner, d
        self.raw, self.ids, self.polys = reader.raw_ids, scope.ids, scope.polys
        self.collections, self.refs, self.dpolys = scope.collections, scope.refs, d.polys
        self.far = reader.far


cdef object _id(_Ctx c, xmlNode* n):
    """`_BuildingReader._id` in unchecked mode: the `gml:id` as written (collected in `raw_ids`)."""
    value = _attr(n, c.id_ns, b"id")
    if not value:
        return None
    c.raw.append(value)
    return value


cdef object _ref(_Ctx c, str href):
    """`_BuildingReader._ref` in unchecked mode."""
    if href[:1] != "#":
        return c.reader._ref(href)
    value = href[1:]
    c.raw.append(value)
    return value


cdef object _proxy(object owner, xmlNode* n):
    """An lxml element for node `n` of the document of `owner` (an lxml element)."""
    return cetree.elementFactory((<cetree._Element>owner)._doc, n)


cdef inline bint _space(char c) noexcept:
    return c == 32 or c == 9 or c == 10 or c == 13 or c == 11 or c == 12


cdef double[23] _POW10 = [1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14,
                          1e15, 1e16, 1e17, 1e18, 1e19, 1e20, 1e21, 1e22]


cdef bint _decimal(const char* s, Py_ssize_t n, double* out) noexcept:
    """A plain decimal `[+-]digits[.digits]` (at least one digit) whose digits make an integer
    m < 2**53 with k <= 22 digits after the point: out = +-(m / 10**k), True. Both are exact
    doubles, so the one division, correctly rounded, is the correctly rounded value of the decimal:
    what `float()` gives (Clinger's fast path). False for any other token (then `float()`'s own
    parser reads it)."""
    cdef Py_ssize_t i = 0
    cdef bint neg = False, point = False
    cdef int digits = 0, frac = 0
    cdef unsigned long long m = 0
    cdef char c
    if n == 0:
        return False
    if s[0] == 45 or s[0] == 43:  # - +
        neg = s[0] == 45
        i = 1
    while i < n:
        c = s[i]
        if c >= 48 and c <= 57:
            if m != 0 or c != 48:
                digits += 1
                if digits > 16:
                    return False
            m = m * 10 + <unsigned long long>(c - 48)
            if point:
                frac += 1
        elif c == 46 and not point:
            point = True
        else:
            return False
        i += 1
    if (n - (1 if (s[0] == 45 or s[0] == 43) else 0) - (1 if point else 0)) == 0:
        return False  # no digit
    if m >= 9007199254740992ULL or frac > 22:
        return False
    out[0] = -(<double>m / _POW10[frac]) if neg else <double>m / _POW10[frac]
    return True


def parse_decimal(token: bytes) -> object:
    """The value `_poslist3` reads from one token (its fast path or CPython's parser), None when
    neither takes it; for tests."""
    cdef double v
    cdef char* end = NULL
    cdef const char* s = token
    if _decimal(s, len(token), &v):
        return v
    try:
        v = PyOS_string_to_double(s, &end, NULL)
    except ValueError:
        return None
    return v if end == s + len(token) else None


cdef object _poslist3(xmlNode* pl):
    """The text of a `posList` -> `(N, 3)` float64, or None when it is not the plain case (then
    the Python `ring_coords` reads it): one text node (or none), only number characters and
    ASCII whitespace, a multiple of 3 numbers, each a whole number token."""
    cdef xmlNode* t = pl.children
    cdef const char* s
    cdef const char* p
    cdef char* end
    cdef char c
    cdef Py_ssize_t count = 0, k = 0
    cdef bint intok = False
    cdef char buf[64]
    cdef Py_ssize_t blen
    cdef Py_buffer view
    cdef double* data
    cdef double v
    if t is NULL:
        return np.zeros((0, 3), dtype=np.float64)
    if t.next is not NULL or t.type != tree.XML_TEXT_NODE or t.content is NULL:
        return None
    s = <const char*>t.content
    p = s
    while p[0] != 0:  # count the tokens, refuse any other character
        c = p[0]
        if _space(c):
            intok = False
        elif (c >= 48 and c <= 57) or c == 46 or c == 43 or c == 45 or c == 101 or c == 69:
            if not intok:
                count += 1
                intok = True
        else:
            return None
        p += 1
    if count % 3:
        return None
    out = np.empty((count // 3, 3), dtype=np.float64)
    PyObject_GetBuffer(out, &view, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS)
    data = <double*>view.buf
    try:
        p = s
        while k < count:
            while _space(p[0]):
                p += 1
            blen = 0
            while p[0] != 0 and not _space(p[0]):
                if blen >= 63:
                    return None
                buf[blen] = p[0]
                blen += 1
                p += 1
            buf[blen] = 0
            if not _decimal(buf, blen, &v):
                end = NULL
                try:
                    v = PyOS_string_to_double(buf, &end, NULL)  # overflow: +-inf, as float()
                except ValueError:
                    return None
                if end != buf + blen:
                    return None
            data[k] = v
            k += 1
    finally:
        PyBuffer_Release(&view)
    return out


cdef object _ring(_Ctx c, xmlNode* ring, int dim):
    """`ring_coords(ring, dim)` (`gml_coords`): the fast path here, any other through Python."""
    cdef xmlNode* ch = ring.children
    cdef xmlNode* pl = NULL
    cdef int n = 0
    while ch is not NULL:
        if _is_elemlike(ch):
            n += 1
            pl = ch
        ch = ch.next
    if n == 1 and _is_elem(pl) and _in_gml(pl) and _name_is(pl, b"posList"):
        d = _attr(pl, NULL, b"srsDimension") or _attr(ring, NULL, b"srsDimension")
        if d == "3" or (not d and dim == 3):
            out = _poslist3(pl)
            if out is not None:
                return out
    return _ring_coords(_proxy(c.owner, ring), dim)


cdef void _polygon(_Ctx c, xmlNode* el, object cls, object sid, int lod, bint in_solid, object coll,
                   int sign, int dim) except *:
    """`_BuildingReader._polygon`."""
    cdef xmlNode* ch = el.children
    cdef xmlNode* ring
    cdef int role
    rings = []
    interiors = []
    while ch is not NULL:
        if _is_elem(ch) and _in_gml(ch):
            if _name_is(ch, b"exterior") or _name_is(ch, b"outerBoundaryIs"):
                role = 1
            elif _name_is(ch, b"interior") or _name_is(ch, b"innerBoundaryIs"):
                role = 0
            else:
                role = -1
            if role >= 0:
                ring = ch.children
                while ring is not NULL:
                    if _is_elem(ring):
                        if not (_in_gml(ring) and _name_is(ring, b"LinearRing")):
                            raise Bail("unsupported ring type")
                        coords = _ring(c, ring, dim)
                        if sign < 0:
                            coords = coords[::-1].copy()
                        rid = _id(c, ring)
                        if rid:
                            c.ids.add(rid)
                        (rings if role else interiors).append((rid, coords))
                    ring = ring.next
        ch = ch.next
    if len(rings) != 1:
        raise Bail("not exactly one exterior ring")
    pid = _id(c, el)
    rec = _PolyRec(pid, rings + interiors if interiors else rings, cls, lod, sid, in_solid, coll)
    c.dpolys.append(rec)
    if pid:
        c.ids.add(pid)
        c.polys[pid] = rec
    if coll:
        c.collections.setdefault(coll, []).append(rec)


cdef object _line(_Ctx c, xmlNode* n):
    """`el.sourceline` of node `n` when the node holds it; else -k: the k-th entry of the
    reader's `far` list, looked up only for a reference that is warned about (`resolve`)."""
    if 0 < n.line < 65535:
        return n.line
    c.far.append((c.owner, <size_t>n))
    return -len(c.far)


def far_line(far: list, k: int) -> object:
    """The `sourceline` of the node of entry `k` of a reader's `far` list."""
    owner, address = far[k]
    return _proxy(owner, <xmlNode*><size_t>address).sourceline


cdef int _dim_attr(xmlNode* n, int dim) except -2:
    """`dim` replaced by the node's `srsDimension` when it has one ("2" or "3"; `Bail` else)."""
    sdim = _attr(n, NULL, b"srsDimension")
    if sdim:
        if sdim == "3":
            return 3
        if sdim == "2":
            return 2
        raise Bail("srsDimension")
    return dim


cdef void _geometry(_Ctx c, xmlNode* el, object cls, object sid, int lod, bint in_solid, object coll,
                    int sign, int dim) except *:
    """`_BuildingReader._geometry`."""
    cdef xmlNode* ch
    cdef xmlNode* g
    cdef const char* ln
    href = _attr(el, XLINK, b"href")
    if href is not None:
        c.refs.append((_ref(c, href), in_solid, sign, _line(c, el)))
        return
    ln = <const char*>el.name
    if ln[0] == 0:
        return
    if (strcmp(ln, b"LineString") == 0 or strcmp(ln, b"MultiCurve") == 0 or strcmp(ln, b"Curve") == 0
            or strcmp(ln, b"CompositeCurve") == 0 or strcmp(ln, b"Point") == 0
            or strcmp(ln, b"MultiPoint") == 0):
        return
    dim = _dim_attr(el, dim)
    srs = _attr(el, NULL, b"srsName")
    if srs and c.d.srs is None:
        c.d.srs = srs
    if (strcmp(ln, b"Polygon") == 0 or strcmp(ln, b"PolygonPatch") == 0 or strcmp(ln, b"Triangle") == 0
            or strcmp(ln, b"Rectangle") == 0):
        _polygon(c, el, cls, sid, lod, in_solid, coll, sign, dim)
        return
    if strcmp(ln, b"OrientableSurface") == 0:
        o = _attr(el, NULL, b"orientation")
        if (o if o is not None else "+").strip() == "-":
            sign = -sign
    elif strcmp(ln, b"Solid") == 0:
        in_solid = True
    elif (strcmp(ln, b"MultiSurface") == 0 or strcmp(ln, b"CompositeSurface") == 0
          or strcmp(ln, b"Shell") == 0 or strcmp(ln, b"Surface") == 0
          or strcmp(ln, b"TriangulatedSurface") == 0):
        gid = _id(c, el)
        if gid:
            coll = gid
            c.ids.add(gid)
    ch = el.children
    while ch is not NULL:
        if _is_elem(ch):
            if _in_gml(ch) and _name_is(ch, b"surfaceMember"):
                href = _attr(ch, XLINK, b"href")
                if href is not None:
                    c.refs.append((_ref(c, href), in_solid, sign, _line(c, ch)))
                else:
                    g = ch.children
                    while g is not NULL:
                        if _is_elem(g):
                            if (_in_gml(g) and _name_is(g, b"Polygon") and not _has_attr(g, NULL, b"srsName")
                                    and not _has_attr(g, NULL, b"srsDimension")):
                                _polygon(c, g, cls, sid, lod, in_solid, coll, sign, dim)
                            else:
                                _geometry(c, g, cls, sid, lod, in_solid, coll, sign, dim)
                        g = g.next
            else:
                _geometry(c, ch, cls, sid, lod, in_solid, coll, sign, dim)
        ch = ch.next


cdef int _prop_lod(xmlNode* n) except -2:
    """`building_read._prop_lod`: LoD of a `lodX<Solid|MultiSurface|Geometry|FootPrint|RoofEdge>`
    element (any namespace), -1 for any other."""
    cdef const char* ln = <const char*>n.name
    cdef unsigned char c3
    if not (ln[0] == 108 and ln[1] == 111 and ln[2] == 100 and ln[3] != 0):  # "lod" + one more
        return -1
    c3 = <unsigned char>ln[3]
    if c3 >= 128:
        raise Bail("non-ASCII character in a lod tag")
    if not (c3 >= 48 and c3 <= 57):
        return -1
    rest = ln + 4
    if (strcmp(rest, b"Solid") == 0 or strcmp(rest, b"MultiSurface") == 0 or strcmp(rest, b"Geometry") == 0
            or strcmp(rest, b"FootPrint") == 0 or strcmp(rest, b"RoofEdge") == 0):
        return c3 - 48
    return -1


cdef bint _geom_property(_Ctx c, xmlNode* el, object cls, object sid) except -1:
    """`_BuildingReader._geom_property`."""
    cdef int lod = _prop_lod(el)
    cdef xmlNode* g
    if lod < 0:
        return False
    if _has_attr(el, XLINK, b"href"):
        _geometry(c, el, cls, sid, lod, False, None, 1, 3)
        return True
    g = el.children
    while g is not NULL:
        if _is_elem(g):
            _geometry(c, g, cls, sid, lod, False, None, 1, 3)
        g = g.next
    return True


def geom_property(reader: object, el: object, d: object, cls: str, sid: object) -> bool:
    """`_BuildingReader._geom_property(el, d, cls, sid)` (unchecked-ids mode)."""
    cdef _Ctx c = _Ctx(reader, el, d)
    return _geom_property(c, (<cetree._Element>el)._c_node, cls, sid)


def boundary(reader: object, prop: object, d: object) -> None:
    """`_BuildingReader._boundary(prop, d)` (unchecked-ids mode)."""
    cdef _Ctx c = _Ctx(reader, prop, d)
    cdef xmlNode* surf = (<cetree._Element>prop)._c_node.children
    cdef xmlNode* ch
    while surf is not NULL:
        if _is_elem(surf):
            name = (<bytes>(<const char*>surf.name)).decode("utf-8")
            if name:
                cls = _BOUNDARY_CLASSES.get(name, "unclassified")
                sid = _id(c, surf)
                if sid:
                    c.ids.add(sid)
                ch = surf.children
                while ch is not NULL:
                    if _is_elem(ch):
                        _geom_property(c, ch, cls, sid)
                    ch = ch.next
        surf = surf.next


def selftest() -> bool:
    """True when this build reads the nodes of the lxml loaded now as lxml does (the lxml and
    libxml2 headers it was compiled with match): names, namespaces, attributes, a posList."""
    from lxml import etree

    el = etree.fromstring(
        b'<a xmlns:g="http://www.opengis.net/gml" xmlns:x="http://www.w3.org/1999/xlink">'
        b'<g:posList srsDimension="3">1 2 3 4.5 -6e1 7</g:posList><g:surfaceMember x:href="#p"/></a>'
    )
    cdef xmlNode* a = (<cetree._Element>el)._c_node
    cdef xmlNode* pl = a.children
    if not (_is_elem(a) and _name_is(a, b"a") and pl is not NULL and _is_elem(pl) and _in_gml(pl)):
        return False
    if not (_name_is(pl, b"posList") and _attr(pl, NULL, b"srsDimension") == "3"):
        return False
    xyz = _poslist3(pl)
    if xyz is None or xyz.tolist() != [[1.0, 2.0, 3.0], [4.5, -60.0, 7.0]]:
        return False
    sm = pl.next
    return sm is not NULL and _name_is(sm, b"surfaceMember") and _attr(sm, XLINK, b"href") == "#p"

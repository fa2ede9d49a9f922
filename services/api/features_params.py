"""Query parameters of the OGC API - Features items requests: CRS URIs (Part 2), `bbox`,
`limit`, the opaque keyset cursor and the property filters; each bad value a 400 problem naming
the parameter.

In: the raw query parameters of a request, the collection, the database SRID. Out: an
`ItemsQuery` (frozen) the service layer turns into SQL.
"""

from __future__ import annotations

import base64
import hashlib
import json
import math
import uuid
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from db.errors import CityDBError, NotFoundError
from services.api.features_collections import Collection

__all__ = [
    "CRS84",
    "CRS84H",
    "DEFAULT_LIMIT",
    "MAX_LIMIT",
    "Crs",
    "Cursor",
    "FeatureParamError",
    "ItemsQuery",
    "crs_uri",
    "encode_cursor",
    "parse_crs",
    "parse_item_id",
    "parse_items_query",
]

CRS84 = "http://www.opengis.net/def/crs/OGC/1.3/CRS84"
CRS84H = "http://www.opengis.net/def/crs/OGC/0/CRS84h"
DEFAULT_LIMIT = 100
MAX_LIMIT = 10_000
#: query parameters every items request accepts (besides the collection's filters)
COMMON = frozenset({"limit", "bbox", "bbox-crs", "crs", "cursor", "f"})


class FeatureParamError(CityDBError):
    """A query parameter of a Features request that cannot be served (OGC: 400)."""

    status_code = 400


@dataclass(frozen=True)
class Crs:
    """An output or bbox CRS: its URI as the client named it, and the SRID PostGIS transforms
    into (4979 for CRS84/CRS84h: longitude, latitude, height kept; else the database SRID)."""

    uri: str
    srid: int

    @property
    def geographic(self) -> bool:
        """True for CRS84 / CRS84h (longitude, latitude in degrees)."""
        return self.srid == 4979


def crs_uri(srid: int) -> str:
    """The OGC URI of EPSG code `srid`.

    >>> crs_uri(25833)
    'http://www.opengis.net/def/crs/EPSG/0/25833'
    """
    return f"http://www.opengis.net/def/crs/EPSG/0/{srid}"


def parse_crs(value: str | None, db_srid: int, *, name: str = "crs") -> Crs:
    """The CRS named by `value` (default CRS84): CRS84, CRS84h or the database CRS, as an OGC
    URI (also `EPSG:n`, `urn:ogc:def:crs:EPSG::n`, `[EPSG:n]`, `OGC:CRS84`). Raises
    `FeatureParamError` for any other.

    >>> parse_crs(None, 25833)
    Crs(uri='http://www.opengis.net/def/crs/OGC/1.3/CRS84', srid=4979)
    >>> parse_crs("EPSG:25833", 25833).uri
    'http://www.opengis.net/def/crs/EPSG/0/25833'
    """
    if value is None or not value.strip():
        return Crs(CRS84, 4979)
    v = value.strip().strip("[]")
    low = v.lower().rstrip("/")
    if low in (CRS84.lower(), "ogc:crs84", "urn:ogc:def:crs:ogc:1.3:crs84", "crs84"):
        return Crs(CRS84, 4979)
    if low in (CRS84H.lower(), "ogc:crs84h", "urn:ogc:def:crs:ogc:0:crs84h", "crs84h"):
        return Crs(CRS84H, 4979)
    db = str(db_srid)
    if low in (crs_uri(db_srid).lower(), f"epsg:{db}", f"urn:ogc:def:crs:epsg::{db}"):
        return Crs(crs_uri(db_srid), db_srid)
    raise FeatureParamError(f"{name}: {value[:200]!r} is not offered; use {CRS84} or {crs_uri(db_srid)}")


def _parse_bbox(value: str, crs: Crs) -> tuple[float, float, float, float]:
    """`minx,miny,maxx,maxy` (or with minz and maxz: 6 numbers, heights ignored) in `crs`."""
    try:
        vals = [float(v) for v in value.split(",")]
    except ValueError:
        raise FeatureParamError(
            f"bbox: expected 4 or 6 comma-separated numbers, got {value[:200]!r}"
        ) from None
    if len(vals) == 6:
        vals = [vals[0], vals[1], vals[3], vals[4]]
    if len(vals) != 4 or not all(math.isfinite(v) and abs(v) < 1e12 for v in vals):
        raise FeatureParamError(f"bbox: expected 4 or 6 comma-separated numbers, got {value[:200]!r}")
    x0, y0, x1, y1 = vals
    if y0 > y1 or x0 > x1:
        raise FeatureParamError(f"bbox: the lower corner comes first (min <= max), got {value[:200]!r}")
    if crs.geographic and not (-180 <= x0 <= 180 and -180 <= x1 <= 180 and -90 <= y0 <= y1 <= 90):
        raise FeatureParamError(f"bbox: longitude and latitude out of range in CRS84: {value[:200]!r}")
    return x0, y0, x1, y1


@dataclass(frozen=True)
class Cursor:
    """Where a page starts: after (`forward`) or before the feature id `key`; `matched` carries
    the first page's numberMatched for the query with fingerprint `query`."""

    key: Any
    forward: bool
    matched: int | None
    query: str


def encode_cursor(cursor: Cursor) -> str:
    """The opaque `cursor` parameter value of `cursor` (base64url of a small JSON document)."""
    doc = {"k": cursor.key, "d": "n" if cursor.forward else "p", "m": cursor.matched, "q": cursor.query}
    raw = json.dumps(doc, separators=(",", ":")).encode()
    return base64.urlsafe_b64encode(raw).decode().rstrip("=")


def _decode_cursor(value: str, key_kind: str) -> Cursor:
    try:
        raw = base64.urlsafe_b64decode(value + "=" * (-len(value) % 4))
        doc = json.loads(raw)
        key = doc["k"]
        key = str(uuid.UUID(str(key))) if key_kind == "uuid" else int(key)
        if key_kind == "int" and not -(2**63) <= key < 2**63:
            raise ValueError(key)
        matched = doc.get("m")
        if matched is not None and (not isinstance(matched, int) or matched < 0):
            raise ValueError(matched)
        return Cursor(key, doc["d"] != "p", matched, str(doc.get("q", "")))
    except (ValueError, TypeError, KeyError, AttributeError):
        raise FeatureParamError(
            "cursor: not a cursor of this API (take the `next` or `prev` link as given)"
        ) from None


def parse_item_id(collection: Collection, value: str) -> Any:
    """The feature id `value` of `collection` as its key type; `NotFoundError` when it cannot be
    one (an id of another form names no feature)."""
    try:
        if collection.key_kind == "uuid":
            return str(uuid.UUID(value))
        key = int(value)
        if not 0 < key < 2**63:
            raise ValueError(value)
        return key
    except ValueError:
        raise NotFoundError(f"collection {collection.id!r} has no feature {value[:200]!r}") from None


def _parse_filter(kind: str, name: str, value: str) -> Any:
    if len(value) > 500:
        raise FeatureParamError(f"{name}: value too long")
    try:
        if kind == "float":
            v = float(value)
            if not math.isfinite(v):
                raise ValueError(value)
            return v
        if kind == "uuid":
            return uuid.UUID(value)
    except ValueError:
        what = "a number" if kind == "float" else "a job id (UUID)"
        raise FeatureParamError(f"{name}: expected {what}, got {value[:200]!r}") from None
    if "\x00" in value:
        raise FeatureParamError(f"{name}: invalid character")
    return value


@dataclass(frozen=True)
class ItemsQuery:
    """A validated items request: page size, output CRS, bbox (in `bbox_crs`), property filters
    (name -> typed value), the cursor (None: first page) and the query fingerprint."""

    limit: int
    crs: Crs
    bbox: tuple[float, float, float, float] | None
    bbox_crs: Crs
    filters: dict[str, Any]
    cursor: Cursor | None
    fingerprint: str


def parse_items_query(params: Mapping[str, list[str]], collection: Collection, db_srid: int) -> ItemsQuery:
    """Validate the query parameters (name -> values) of an items request of `collection`:
    unknown or repeated parameters and bad values raise `FeatureParamError`; `limit` above
    `MAX_LIMIT` is clamped."""
    allowed = COMMON | {f.name for f in collection.filters}
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise FeatureParamError(
            f"unknown query parameter {unknown[0][:100]!r} for collection {collection.id!r}; "
            f"accepted: {', '.join(sorted(allowed))}"
        )
    for name, values in params.items():
        if len(values) > 1:
            raise FeatureParamError(f"{name}: given {len(values)} times; give it once")
    one = {k: v[0] for k, v in params.items()}
    limit = DEFAULT_LIMIT
    if "limit" in one:
        try:
            limit = int(one["limit"])
        except ValueError:
            raise FeatureParamError(f"limit: expected an integer, got {one['limit'][:100]!r}") from None
        if limit < 1:
            raise FeatureParamError(f"limit: must be at least 1, got {limit}")
        limit = min(limit, MAX_LIMIT)
    if one.get("f", "json").lower() not in ("json", "geojson"):
        raise FeatureParamError(f"f: only json (GeoJSON) is served, got {one['f'][:100]!r}")
    crs = parse_crs(one.get("crs"), db_srid)
    bbox_crs = parse_crs(one.get("bbox-crs"), db_srid, name="bbox-crs")
    bbox = _parse_bbox(one["bbox"], bbox_crs) if "bbox" in one else None
    filters = {}
    for f in collection.filters:
        if f.name in one:
            filters[f.name] = _parse_filter(f.kind, f.name, one[f.name])
    basis = json.dumps(
        [
            collection.id,
            sorted((k, str(v)) for k, v in filters.items()),
            bbox,
            bbox_crs.srid if bbox else None,
        ]
    )
    fingerprint = hashlib.sha256(basis.encode()).hexdigest()[:12]
    cursor = _decode_cursor(one["cursor"], collection.key_kind) if "cursor" in one else None
    return ItemsQuery(limit, crs, bbox, bbox_crs, filters, cursor, fingerprint)

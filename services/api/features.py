"""OGC API - Features (Part 1 Core + GeoJSON, Part 2 CRS by reference) over the city model
database: the service layer of `routes_features` (`docs/features.md`).

In: an engine, the collection id, the raw query parameters, the API's base URL. Out: JSON-ready
dicts (collections) and the bytes of GeoJSON documents (items), with their `Content-Crs`.

- Features are built as JSON text by PostgreSQL (`row_to_json`, `ST_AsGeoJSON`, `db.feature_json`),
  so that a page costs one query and no JSON parsing in Python; pages of more than
  `STREAM_ABOVE` features are streamed from a server-side cursor. A collection that keeps its
  features' texts in CRS84 with its rows (`facades`: `db.facade_features`) has its CRS84 pages
  read them (an index scan over stored text); the features whose text is missing, or was
  written by another definition, are written by PostgreSQL in a second query.
- Paging is keyset paging on the feature id (`WHERE id > last ORDER BY id LIMIT n + 1`), never
  OFFSET: a page deep in a collection costs what the first one does. The `next` / `prev` links
  carry an opaque cursor (`features_params.Cursor`).
- numberMatched is an exact count (capped at `features_sql.COUNT_CAP`, above which it is left
  out), made once for the first page of a query and carried in its cursors, and kept
  `features_sql.COUNT_TTL_S` seconds per process for the same query: deep pages never count again,
  and a first page may show a count up to that old.
- Geometries are stored in the database SRID (`db.srid`); CRS84 / CRS84h output is
  `ST_Transform(geometry, 4979)`: longitude, latitude, and the model's heights unchanged.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterator, Mapping
from typing import Any
from urllib.parse import urlencode

from sqlalchemy import Engine

from db.errors import NotFoundError
from services.api import features_sql
from services.api.features_collections import COLLECTIONS, Collection
from services.api.features_db import Db
from services.api.features_params import (
    CRS84,
    CRS84H,
    Crs,
    Cursor,
    ItemsQuery,
    crs_uri,
    encode_cursor,
    parse_crs,
    parse_item_id,
    parse_items_query,
)

__all__ = [
    "FEATURES_CONFORMANCE",
    "GEOJSON",
    "collection_view",
    "collections_view",
    "item_document",
    "items_document",
]

FEATURES_CONFORMANCE = [
    "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/core",
    "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/geojson",
    "http://www.opengis.net/spec/ogcapi-features-1/1.0/conf/oas30",
    "http://www.opengis.net/spec/ogcapi-features-2/1.0/conf/crs",
]
GEOJSON = "application/geo+json"
STREAM_ABOVE = 1000
#: the opening of every items page, before its features
_HEAD = b'{"type":"FeatureCollection","features":['


class NoSuchCollectionError(NotFoundError):
    """No collection of that id."""


def _collection(collection_id: str) -> Collection:
    c = COLLECTIONS.get(collection_id)
    if c is None:
        raise NoSuchCollectionError(
            f"no collection {collection_id[:200]!r}; collections: {', '.join(COLLECTIONS)}"
        )
    return c


def _collection_doc(c: Collection, base: str, srid: int, extent: dict[str, list[float]] | None) -> dict:
    href = f"{base}/collections/{c.id}"
    doc: dict[str, Any] = {
        "id": c.id,
        "title": c.title,
        "description": c.description,
        "itemType": "feature",
        "crs": [CRS84, CRS84H, crs_uri(srid)],
        "storageCrs": crs_uri(srid),
        "links": [
            {"href": href, "rel": "self", "type": "application/json", "title": c.title},
            {"href": f"{href}/items", "rel": "items", "type": GEOJSON, "title": f"{c.title} (GeoJSON)"},
        ],
    }
    if extent:
        doc["extent"] = {
            "spatial": {
                "bbox": [[round(v, 9) for v in extent["crs84"]]],
                "crs": CRS84,
                "storageCrsBbox": [[round(v, 6) for v in extent["storage"]]],
            }
        }
    return doc


def collections_view(engine: Engine, *, base: str) -> dict[str, Any]:
    """`GET /collections`: every collection with its extent, CRS list and links."""
    srid = features_sql.database_srid_cached(engine)
    with Db(engine) as db:
        extent = features_sql.data_extent(db, srid)
    return {
        "collections": [_collection_doc(c, base, srid, extent) for c in COLLECTIONS.values()],
        "links": [{"href": f"{base}/collections", "rel": "self", "type": "application/json"}],
        "crs": [CRS84, CRS84H, crs_uri(srid)],
    }


def collection_view(engine: Engine, *, collection_id: str, base: str) -> dict[str, Any]:
    """`GET /collections/{id}` (`NotFoundError` for an unknown id)."""
    c = _collection(collection_id)
    srid = features_sql.database_srid_cached(engine)
    with Db(engine) as db:
        return _collection_doc(c, base, srid, features_sql.data_extent(db, srid))


# -- items -------------------------------------------------------------------------------------
def _link(href: str, rel: str, title: str) -> dict[str, str]:
    return {"href": href, "rel": rel, "type": GEOJSON, "title": title}


def _page_url_prefix(base: str, path: str, raw: Mapping[str, list[str]], limit: int) -> str:
    """The URL of another page of the same query up to its cursor's value (which, base64url
    without padding, needs no quoting): the request's parameters, `limit`, `&cursor=`."""
    params = [(k, v[0]) for k, v in raw.items() if k not in ("cursor", "limit")]
    params.append(("limit", str(limit)))
    return f"{base}{path}?{urlencode(params)}&cursor="


def _legacy_crs(crs: Crs) -> str:
    """The GeoJSON 2008 `crs` member for output in the database CRS (read by GDAL's GeoJSON
    driver and older clients; RFC 7946 readers ignore it as a foreign member)."""
    if crs.geographic:
        return ""
    epsg = crs.uri.rsplit("/", 1)[1]
    return f',"crs":{{"type":"name","properties":{{"name":"urn:ogc:def:crs:EPSG::{epsg}"}}}}'


def items_document(
    engine: Engine,
    *,
    collection_id: str,
    params: Mapping[str, list[str]],
    base: str,
    path: str,
    self_url: str,
) -> tuple[Iterator[bytes], Crs, bool]:
    """`GET /collections/{id}/items`: (the FeatureCollection as chunks of bytes, the output CRS,
    whether to stream it). Raises `NotFoundError` (collection) and `FeatureParamError` (400).

    A page of at most `STREAM_ABOVE` features is fetched at once (its features' JSON texts joined
    as the bytes PostgreSQL sent, never decoded nor parsed: one chunk); a larger forward page is
    streamed from a server-side cursor."""
    c = _collection(collection_id)
    srid = features_sql.database_srid_cached(engine)
    q = parse_items_query(params, c, srid)
    cur = q.cursor
    forward = cur is None or cur.forward
    stream = q.limit > STREAM_ABOVE and forward
    db = Db(engine, autocommit=not stream)  # a server-side cursor needs a transaction
    try:
        props = features_sql.properties(db, c)
        from_sql, where, binds = features_sql.where_clause(c, q, db, srid)
        matched = cur.matched if cur is not None and cur.query == q.fingerprint else None
        if matched is None:
            matched = features_sql.count_matched(db, c, q, from_sql, where, binds)
        if cur is not None:
            where = f"{where} AND {c.key} {'>' if forward else '<'} :cursor_key"
            binds["cursor_key"] = cur.key
        stored = features_sql.stored_text_ready(db, c)
        sql = features_sql.page_sql(c, props, q.crs, from_sql, where, forward, q.limit, stored)
        page = _Page(db, c, q, props, srid, matched, base, path, params, self_url)
        if stream:
            return page.chunks(db.stream(sql, binds, raw_text=True)), q.crs, True
        rows = db.rows(sql, binds, raw_text=True)  # in key order: ascending, or descending before the cursor
        more = len(rows) > q.limit  # one row more than a page: more after (forward) or before it
        rows = rows[: q.limit] if forward else rows[q.limit - 1 :: -1] if more else rows[::-1]
        texts = page.texts(rows)
    except BaseException:
        db.close()
        raise
    db.close()
    tail = page.tail(
        len(texts), rows[0][0] if rows else None, rows[-1][0] if rows else None,
        more_after=more if forward else True,
        more_before=cur is not None if forward else more,
    )  # fmt: skip
    return iter([b"".join((_HEAD, b",".join(texts), tail))]), q.crs, False


class _Page:
    """One items request's page after its query: the features' texts (those a stored-text page
    lacks written by PostgreSQL) and the FeatureCollection's tail."""

    def __init__(
        self,
        db: Db,
        c: Collection,
        q: ItemsQuery,
        props: tuple[tuple[str, str], ...],
        srid: int,
        matched: int | None,
        base: str,
        path: str,
        params: Mapping[str, list[str]],
        self_url: str,
    ) -> None:
        self.db, self.c, self.q, self.props, self.srid = db, c, q, props, srid
        self.matched, self.base, self.path, self.params, self.self_url = matched, base, path, params, self_url

    def texts(self, rows: list[tuple]) -> list[bytes]:
        """The feature texts (UTF-8) of `rows` (key, text or None: a stored text of another
        definition, or none), in their order; the missing ones written by PostgreSQL in one query
        (a feature gone since the page's query is left out)."""
        missing = [r[0] for r in rows if r[1] is None]
        if not missing:
            return [r[1] for r in rows]
        sql = features_sql.features_by_key_sql(self.c, self.props, self.q.crs)
        written = dict(self.db.rows(sql, {"keys": missing, "srid": self.srid}, raw_text=True))
        return [f if f is not None else written[k] for k, f in rows if f is not None or k in written]

    def tail(self, n: int, first: Any, last: Any, *, more_after: bool, more_before: bool) -> bytes:
        """The FeatureCollection's end (`_tail`) for `n` features from key `first` to `last`."""
        return _tail(
            self.c, self.q, self.matched, self.base, self.path, self.params, self.self_url, n, first, last,
            more_after=more_after, more_before=more_before,
        )  # fmt: skip

    def chunks(self, result: Iterator[tuple]) -> Iterator[bytes]:
        """A streamed forward page: the FeatureCollection of `result`'s rows (key, feature text or
        None; the first `q.limit`) in chunks of 500 features, then its tail; closes the
        connection at the end."""
        try:
            yield _HEAD
            rows = iter(result)
            n, read, first, last = 0, 0, None, None
            while read < self.q.limit:
                batch = list(itertools.islice(rows, min(500, self.q.limit - read)))
                if not batch:
                    break
                read += len(batch)
                first = batch[0][0] if first is None else first
                last = batch[-1][0]
                texts = self.texts(batch)
                if texts:
                    yield (b"," if n else b"") + b",".join(texts)
                n += len(texts)
            more_after = read == self.q.limit and next(rows, None) is not None
            yield self.tail(n, first, last, more_after=more_after, more_before=self.q.cursor is not None)
        finally:
            self.db.close()


def _tail(
    c: Collection,
    q: ItemsQuery,
    matched: int | None,
    base: str,
    path: str,
    params: Mapping[str, list[str]],
    self_url: str,
    n: int,
    first: Any,
    last: Any,
    *,
    more_after: bool,
    more_before: bool,
) -> bytes:
    """The end of a FeatureCollection after its features: `]`, numberReturned (`n`),
    numberMatched, the links (`next` after the key `last` when `more_after`, `prev` before the key
    `first` when `more_before`; keys as read, int or text), the legacy `crs` member, `}`."""
    links = [_link(self_url, "self", "this page")]
    key = str if c.key_kind == "uuid" else int
    url = _page_url_prefix(base, path, params, q.limit)
    if more_after and last is not None:
        nxt = Cursor(key(last), True, matched, q.fingerprint)
        links.append(_link(url + encode_cursor(nxt), "next", "next page"))
    if more_before and first is not None:
        prv = Cursor(key(first), False, matched, q.fingerprint)
        links.append(_link(url + encode_cursor(prv), "prev", "previous page"))
    links.append({"href": f"{base}/collections/{c.id}", "rel": "collection", "type": "application/json"})
    tail: dict[str, Any] = {"numberReturned": n}
    if matched is not None:
        tail["numberMatched"] = matched
    tail["links"] = links
    return ("]," + json.dumps(tail, separators=(",", ":"))[1:-1] + _legacy_crs(q.crs) + "}").encode()


def item_document(
    engine: Engine, *, collection_id: str, feature_id: str, crs: str | None, base: str
) -> tuple[bytes, Crs]:
    """`GET /collections/{id}/items/{featureId}`: (the Feature as bytes, the output CRS);
    `NotFoundError` for an unknown collection or feature."""
    c = _collection(collection_id)
    key = parse_item_id(c, feature_id)
    srid = features_sql.database_srid_cached(engine)
    out = parse_crs(crs, srid)
    with Db(engine) as db:
        from_sql = c.from_sql.format(**{s: "" for s in c.slots})
        props = features_sql.properties(db, c)
        sql = (
            f"SELECT {features_sql.feature_select(c, props, out)} FROM {from_sql}"
            f"{features_sql.feature_lateral(props)} "
        )
        row = db.first(f"{sql} WHERE ({c.where}) AND {c.key} = :key", {"key": key, "srid": srid})
    if row is None:
        raise NotFoundError(f"collection {c.id!r} has no feature {feature_id[:200]!r}")
    href = f"{base}/collections/{c.id}/items/{row[0]}"
    links = [
        {"href": href, "rel": "self", "type": GEOJSON},
        {"href": f"{base}/collections/{c.id}", "rel": "collection", "type": "application/json"},
    ]
    body = row[1][:-1] + ',"links":' + json.dumps(links, separators=(",", ":")) + _legacy_crs(out) + "}"
    return body.encode(), out

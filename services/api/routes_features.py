"""OGC API - Features routes: collections, items, one item (`docs/features.md`). Thin: each
translates HTTP to a call of `features` and back. Read access as the rest of the API
(`ReadAccess`). The items routes are declared per collection so that the API document names each
one's property filters; their query parameters are validated by `features_params` (400 problems,
also for unknown parameters)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any

from fastapi import APIRouter, Path, Query, Request, Response
from fastapi.responses import StreamingResponse

from services.api import features
from services.api.deps import EngineDep, ReadAccess
from services.api.features_collections import COLLECTIONS, Collection
from services.api.features_params import CRS84, DEFAULT_LIMIT, MAX_LIMIT
from services.api.problems import problem_responses
from services.api.routes_processes import AUTH, base_url

router = APIRouter()
TAG = "Features"
_CRS_DOC = f"Output CRS: {CRS84} (default), CRS84h or the storageCrs (see the collection)."


def _param(name: str, description: str, schema: dict[str, Any] | None = None) -> dict[str, Any]:
    return {
        "name": name,
        "in": "query",
        "required": False,
        "description": description,
        "schema": schema or {"type": "string"},
        "style": "form",
        "explode": False,
    }


def _items_parameters(c: Collection) -> list[dict[str, Any]]:
    """The OpenAPI query parameters of the items route of `c`."""
    common = [
        _param(
            "limit",
            f"Features per page (default {DEFAULT_LIMIT}; more than {MAX_LIMIT} is clamped).",
            {"type": "integer", "minimum": 1, "default": DEFAULT_LIMIT},
        ),
        _param("bbox", "minx,miny,maxx,maxy (or 6 numbers with heights) in bbox-crs.", {"type": "string"}),
        _param("bbox-crs", "CRS of bbox (default CRS84).", {"type": "string", "format": "uri"}),
        _param("crs", _CRS_DOC, {"type": "string", "format": "uri"}),
        _param("cursor", "Opaque: from a next or prev link.", {"type": "string"}),
    ]
    kinds = {"float": {"type": "number"}, "uuid": {"type": "string", "format": "uuid"}}
    return common + [_param(f.name, f.description, kinds.get(f.kind)) for f in c.filters]


_GEOJSON_200 = {200: {"content": {features.GEOJSON: {}}, "description": "GeoJSON."}}


@router.get("/collections", tags=[TAG], responses=AUTH)
def collections(request: Request, engine: EngineDep, _: ReadAccess) -> dict:
    """The feature collections: buildings, facades, anomalies, jobs (extent, CRS, links)."""
    return features.collections_view(engine, base=base_url(request))


@router.get("/collections/{collectionId}", tags=[TAG], responses={**AUTH, **problem_responses(404)})
def collection(
    request: Request,
    engine: EngineDep,
    _: ReadAccess,
    collectionId: Annotated[str, Path(max_length=200)],
) -> dict:
    """One collection: extent (CRS84 and storageCrs), CRS list, storageCrs, links."""
    return features.collection_view(engine, collection_id=collectionId, base=base_url(request))


def _items_route(c: Collection) -> Callable[..., Response]:
    def items(request: Request, engine: EngineDep, _: ReadAccess) -> Response:
        """Items of the collection (a GeoJSON FeatureCollection), keyset-paged."""
        params: dict[str, list[str]] = {}
        for k, v in request.query_params.multi_items():
            params.setdefault(k, []).append(v)
        chunks, crs, stream = features.items_document(
            engine,
            collection_id=c.id,
            params=params,
            base=base_url(request),
            path=request.url.path,
            self_url=str(request.url),
        )
        headers = {"Content-Crs": f"<{crs.uri}>"}
        if stream:
            return StreamingResponse(chunks, media_type=features.GEOJSON, headers=headers)
        return Response(b"".join(chunks), media_type=features.GEOJSON, headers=headers)

    items.__name__ = f"items_{c.id}"
    items.__doc__ = f"{c.description} Filters: {', '.join(f.name for f in c.filters)}, bbox."
    return items


def _item_route(c: Collection) -> Callable[..., Response]:
    def item(
        request: Request,
        engine: EngineDep,
        _: ReadAccess,
        featureId: Annotated[str, Path(max_length=200)],
        crs: Annotated[str | None, Query(max_length=500, description=_CRS_DOC)] = None,
    ) -> Response:
        """One feature of the collection."""
        body, out = features.item_document(
            engine, collection_id=c.id, feature_id=featureId, crs=crs, base=base_url(request)
        )
        return Response(body, media_type=features.GEOJSON, headers={"Content-Crs": f"<{out.uri}>"})

    item.__name__ = f"item_{c.id}"
    return item


for _c in COLLECTIONS.values():
    router.add_api_route(
        f"/collections/{_c.id}/items",
        _items_route(_c),
        methods=["GET"],
        tags=[TAG],
        summary=f"{_c.title}: items",
        response_class=Response,
        responses={**_GEOJSON_200, **AUTH, **problem_responses(400)},
        openapi_extra={"parameters": _items_parameters(_c)},
    )
    router.add_api_route(
        f"/collections/{_c.id}/items/{{featureId}}",
        _item_route(_c),
        methods=["GET"],
        tags=[TAG],
        summary=f"{_c.title}: one item",
        response_class=Response,
        responses={**_GEOJSON_200, **AUTH, **problem_responses(400, 404)},
    )

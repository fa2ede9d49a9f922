"""One tile's content: the meshes of its buildings as one GLB with thermal textures, feature
ids and metadata.

In: `BuildingMesh`es (model CRS), the model CRS -> ECEF transformation, the tile's
`local_from_ecef` (4×4, z-up local frame of the tile), a reader of 16-bit texture tiles by URI,
the value and display scales and per-surface figures. Out: the GLB bytes and the tile's bounds
`(min (3,), max (3,))` in its local z-up frame.

The glTF (docs/3dtiles.md):
- one node, no matrix; one mesh whose primitives share one vertex set: POSITION (float32, the
  local frame turned y-up, metres: never raw ECEF), NORMAL (per polygon), TEXCOORD_0 and
  `_FEATURE_ID_0` (the surface's feature id, float); one primitive per texture image (material:
  the display image, `KHR_materials_unlit`, double-sided) and one for untextured polygons (grey);
- `EXT_mesh_features`: feature id set `surface` (one feature per polygon) into property table 0;
- `EXT_structural_metadata`: class `surface` (building and surface `gml:id`, semantic class,
  mean and typical temperature in kelvin, observed share; `noData` -1), one property table of
  it; class `thermal` with the per-texel `temperature` (normalized UINT16 with the kelvin
  `offset` and `scale`, `noData` 0), one property texture per image (the value image, channels
  red = low byte, green = high byte, nearest sampling), referenced by its primitive.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from db.tiles3d.frames import EcefTransform, yup
from db.tiles3d.glb import ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER, GltfBuilder
from db.tiles3d.images import DisplayScale, ValueScale, display_png, value_png
from db.tiles3d.mesh import BuildingMesh

__all__ = ["NO_DATA", "ContentResult", "SurfaceFigures", "metadata_schema", "tile_content"]

#: `noData` of the surface class's float properties (kelvin; never a real temperature)
NO_DATA = -1.0
NEAREST, LINEAR = 9728, 9729
UNTEXTURED_RGBA = [0.6, 0.6, 0.6, 1.0]


@dataclass(frozen=True)
class SurfaceFigures:
    """Thermal figures of one polygon (kelvin, or counts for uncalibrated input; NaN = none)."""

    mean: float = float("nan")
    typical: float = float("nan")
    p05: float = float("nan")
    p95: float = float("nan")
    observed_share: float = float("nan")


@dataclass(frozen=True)
class ContentResult:
    """A written tile content: GLB bytes, its local bounds (z-up, metres), counts."""

    glb: bytes
    lo: np.ndarray
    hi: np.ndarray
    buildings: int
    surfaces: int
    triangles: int
    images: int


def metadata_schema(values: ValueScale) -> dict[str, Any]:
    """The `EXT_structural_metadata` schema of the content (classes `surface` and `thermal`)."""
    unit = "kelvin" if values.unit == "K" else "counts"
    fig = {"type": "SCALAR", "componentType": "FLOAT32", "noData": NO_DATA}
    return {
        "id": "citytherm",
        "name": "citytherm thermal textures",
        "version": "1",
        "classes": {
            "surface": {
                "description": "A CityGML surface polygon with its thermal figures.",
                "properties": {
                    "building": {"type": "STRING", "description": "gml:id of the top-level building."},
                    "surface": {"type": "STRING", "description": "gml:id of the polygon."},
                    "surfaceClass": {"type": "STRING", "description": "CityGML class, e.g. WallSurface."},
                    "meanTemperature": {**fig, "description": f"Mean of the observed texels, {unit}."},
                    "typicalTemperature": {**fig, "description": f"Typical temperature, {unit}."},
                    "observedShare": {**fig, "description": "Share of the texels observed, 0..1."},
                },
            },
            "thermal": {
                "description": "Per-texel value of the thermal texture.",
                "properties": {
                    "temperature": {
                        "type": "SCALAR",
                        "componentType": "UINT16",
                        "normalized": True,
                        "offset": values.offset,
                        "scale": values.metadata_scale,
                        "noData": 0,
                        "description": f"{unit}: offset + scale * DN / 65535; DN 0 is not observed.",
                    }
                },
            },
        },
    }


def _strings(gltf: GltfBuilder, items: Sequence[str]) -> dict[str, Any]:
    data = [s.encode("utf-8") for s in items]
    offsets = np.zeros(len(data) + 1, dtype=np.uint32)
    offsets[1:] = np.cumsum([len(d) for d in data])
    return {
        "values": gltf.view(b"".join(data)),
        "stringOffsets": gltf.view(offsets.tobytes()),
        "stringOffsetType": "UINT32",
    }


def _floats(gltf: GltfBuilder, values: Sequence[float]) -> dict[str, Any]:
    a = np.array(values, dtype=np.float64)
    a[~np.isfinite(a)] = NO_DATA
    return {"values": gltf.view(a.astype(np.float32).tobytes())}


def _normals(local: np.ndarray, tris: np.ndarray, tri_feature: np.ndarray, n_features: int) -> np.ndarray:
    """Per-vertex unit normals `(V, 3)` (z-up local frame): each polygon's area-weighted triangle
    normal; up for vertices of degenerate or no triangles."""
    a, b, c = local[tris[:, 0]], local[tris[:, 1]], local[tris[:, 2]]
    cross = np.cross(b - a, c - a)
    per_feature = np.zeros((n_features, 3))
    np.add.at(per_feature, tri_feature, cross)
    length = np.linalg.norm(per_feature, axis=1, keepdims=True)
    per_feature = np.where(length > 1e-12, per_feature / np.maximum(length, 1e-300), [0.0, 0.0, 1.0])
    out = np.tile([0.0, 0.0, 1.0], (len(local), 1))
    out[tris.reshape(-1)] = np.repeat(per_feature[tri_feature], 3, axis=0)
    return out


def tile_content(
    meshes: Sequence[BuildingMesh],
    ecef: EcefTransform,
    local_from_ecef: np.ndarray,
    read_tile: Callable[[str], np.ndarray],
    values: ValueScale,
    display: DisplayScale,
    figures: Mapping[str, SurfaceFigures],
) -> ContentResult:
    """The GLB of one tile (see the module docstring)."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
    surf_offsets = np.cumsum([0] + [len(m.surfaces) for m in meshes])
    model = np.concatenate([m.vertices for m in meshes]) if meshes else np.zeros((0, 3))
    ecef_pts = ecef.points(model)
    local = ecef_pts @ local_from_ecef[:3, :3].T + local_from_ecef[:3, 3]
    uv = np.concatenate([m.uv for m in meshes]) if meshes else np.zeros((0, 2), np.float32)
    tris = np.concatenate([m.triangles + offsets[k] for k, m in enumerate(meshes)])
    tri_feature = np.concatenate([m.triangle_surface + surf_offsets[k] for k, m in enumerate(meshes)])
    uris: dict[str, int] = {}
    parts = []
    for m in meshes:  # each mesh's image index -> the tile's (first use order), -1 stays -1
        lookup = np.array([uris.setdefault(u, len(uris)) for u in m.images] + [-1], dtype=np.int64)
        parts.append(lookup[m.triangle_image])
    tri_image = np.concatenate(parts) if parts else np.zeros(0, np.int64)
    surfaces = [s for m in meshes for s in m.surfaces]
    n_feat = len(surfaces)
    vertex_feature = np.zeros(len(local), dtype=np.float32)
    vertex_feature[tris.reshape(-1)] = np.repeat(tri_feature, 3).astype(np.float32)
    normals = _normals(local, tris, tri_feature, max(n_feat, 1))

    gltf = GltfBuilder()
    for ext in ("EXT_mesh_features", "EXT_structural_metadata", "KHR_materials_unlit"):
        gltf.use_extension(ext)
    attributes = {
        "POSITION": gltf.accessor(yup(local).astype(np.float32), ARRAY_BUFFER, bounds=True),
        "NORMAL": gltf.accessor(yup(normals).astype(np.float32), ARRAY_BUFFER),
        "TEXCOORD_0": gltf.accessor(uv.astype(np.float32), ARRAY_BUFFER),
        "_FEATURE_ID_0": gltf.accessor(vertex_feature, ARRAY_BUFFER),
    }
    feature_set = {"featureCount": n_feat, "attribute": 0, "propertyTable": 0, "label": "surface"}
    feature_ids = {"featureIds": [feature_set]}
    display_sampler = gltf.sampler(NEAREST, LINEAR)
    value_sampler = gltf.sampler(NEAREST, NEAREST)
    property_textures = []
    primitives = []
    for uri, k in [*uris.items(), ("", -1)]:
        sel = tri_image == k
        if not sel.any():
            continue
        prim: dict[str, Any] = {
            "attributes": dict(attributes),
            "indices": gltf.accessor(tris[sel].reshape(-1).astype(np.uint32), ELEMENT_ARRAY_BUFFER),
            "mode": 4,
            "extensions": {"EXT_mesh_features": feature_ids},
        }
        if k >= 0:
            dn = read_tile(uri)
            tex_display = gltf.texture(gltf.image(display_png(dn, values, display)), display_sampler)
            tex_value = gltf.texture(gltf.image(value_png(dn)), value_sampler)
            prim["material"] = gltf.add(
                "materials",
                {
                    "name": uri,
                    "pbrMetallicRoughness": {
                        "baseColorTexture": {"index": tex_display, "texCoord": 0},
                        "metallicFactor": 0.0,
                        "roughnessFactor": 1.0,
                    },
                    "doubleSided": True,
                    "extensions": {"KHR_materials_unlit": {}},
                },
            )
            prim["extensions"]["EXT_structural_metadata"] = {"propertyTextures": [len(property_textures)]}
            property_textures.append(
                {
                    "name": uri,
                    "class": "thermal",
                    "properties": {"temperature": {"index": tex_value, "texCoord": 0, "channels": [0, 1]}},
                }
            )
        else:
            del prim["attributes"]["TEXCOORD_0"]
            prim["material"] = gltf.add(
                "materials",
                {
                    "name": "untextured",
                    "pbrMetallicRoughness": {
                        "baseColorFactor": UNTEXTURED_RGBA,
                        "metallicFactor": 0.0,
                        "roughnessFactor": 1.0,
                    },
                    "doubleSided": True,
                },
            )
        primitives.append(prim)
    figs = [figures.get(s.surface, SurfaceFigures()) for s in surfaces]
    table = {
        "name": "surfaces",
        "class": "surface",
        "count": n_feat,
        "properties": {
            "building": _strings(gltf, [s.building for s in surfaces]),
            "surface": _strings(gltf, [s.surface for s in surfaces]),
            "surfaceClass": _strings(gltf, [s.surface_class for s in surfaces]),
            "meanTemperature": _floats(gltf, [f.mean for f in figs]),
            "typicalTemperature": _floats(gltf, [f.typical for f in figs]),
            "observedShare": _floats(gltf, [f.observed_share for f in figs]),
        },
    }
    metadata: dict[str, Any] = {"schema": metadata_schema(values), "propertyTables": [table]}
    if property_textures:
        metadata["propertyTextures"] = property_textures
    gltf.doc["extensions"] = {"EXT_structural_metadata": metadata}
    gltf.add("meshes", {"name": "buildings", "primitives": primitives})
    gltf.add("nodes", {"name": "tile", "mesh": 0})
    gltf.doc["scenes"] = [{"nodes": [0]}]
    gltf.doc["scene"] = 0
    return ContentResult(
        glb=gltf.glb(),
        lo=local.min(axis=0),
        hi=local.max(axis=0),
        buildings=len(meshes),
        surfaces=n_feat,
        triangles=len(tris),
        images=len(uris),
    )

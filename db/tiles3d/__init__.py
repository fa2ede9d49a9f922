"""3D Tiles 1.1 export of a textured city model (issue 17; `docs/3dtiles.md`).

In: a textured model: a results folder (`citytherm run`, `docs/results-format.md`) or a model's
newest job theme in the database (exported to a cached folder first, `database`). Out: a tileset
folder: `tileset.json` (explicit quadtree, `refine: ADD`, geometric error by level, root
`transform` to ECEF) and one GLB per leaf tile: buildings triangulated in a local frame, the
thermal texture as an 8-bit colour-mapped display image plus the per-texel temperature as an
`EXT_structural_metadata` property texture, surfaces as `EXT_mesh_features` feature ids with a
property table (building and surface `gml:id`, class, mean and typical temperature).

Entry points: `folder_source(path)` -> `ThermalSource`; `export_3dtiles(source, out, options)`
-> `TilesetSummary`; `database.model_tileset(...)` (the API's cached tileset of a model).
Modules: `frames` (CRS -> ECEF -> local frames), `mesh` (triangles and UVs of a building),
`images` (display and value images), `glb` (GLB writer/reader), `content` (one tile's GLB),
`tiling` (quadtree, tileset.json), `source` (what is read), `export` (the two passes).
"""

from db.tiles3d.export import TilesetSummary, TilesOptions, export_3dtiles
from db.tiles3d.source import SourceError, ThermalSource, folder_source

__all__ = [
    "SourceError",
    "ThermalSource",
    "TilesOptions",
    "TilesetSummary",
    "export_3dtiles",
    "folder_source",
]

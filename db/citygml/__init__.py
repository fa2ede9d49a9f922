"""CityGML in and out: streaming reader (CityGML 1.0/2.0/3.0 buildings), CityGML 2.0 writer with
appearances, schema validation and per-polygon geometry checks.

Public API (all raise `CityGMLError`, a `ValueError` with `.path` and `.line`):
    read_header(path) -> ModelHeader
    iter_buildings(path) -> Iterator[Building]              # streamed, parts nested
    read_model(path) -> (ModelHeader, list[Building])       # header with all model appearances
    open_model(path) -> (ModelHeader, Iterator[Building], late model appearances: list)
    write_citygml(path, buildings, *, srs_name, extra_appearances=None, envelope=None,
                  model_appearances=(), name=None, trailing_appearances=()) -> int
    envelope_of(buildings) -> (lower (3,), upper (3,)) | None
    validate_citygml2(path) -> list[str]                    # empty = valid
    db.citygml.checks: check_building(building) -> list[PolygonCheck], CheckOptions

Ids: every id in the model is a valid NCName: input ids that are not (e.g. starting with a
digit) are mapped by `names.to_ncname` everywhere (definitions, xlinks, texture targets);
polygons and rings without `gml:id` get `<building>_poly<k>` / `<polygon>_ring<j>`.

Not read (and therefore not written): addresses, external references, terrain intersection
curves, openings (windows/doors), interior rooms, CityGML 3.0 appearances, `TexCoordGen`
parameterisations; BuildingInstallation polygons are kept as the building's own. An
`xlink:href` to a polygon outside its building is logged and dropped.
"""

from db.citygml.names import CityGMLError
from db.citygml.reader import iter_buildings, open_model, read_header, read_model
from db.citygml.validate import validate_citygml2
from db.citygml.writer import envelope_of, write_citygml

__all__ = [
    "CityGMLError",
    "envelope_of",
    "iter_buildings",
    "open_model",
    "read_header",
    "read_model",
    "validate_citygml2",
    "write_citygml",
]

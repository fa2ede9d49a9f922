"""CityGML in and out: streaming reader (CityGML 1.0/2.0/3.0 buildings), CityGML 2.0 writer with
appearances, schema validation and per-polygon geometry checks.

Public API:
    read_header(path) -> ModelHeader
    iter_buildings(path) -> Iterator[Building]
    read_model(path) -> (ModelHeader, list[Building])
    write_citygml(path, buildings, *, srs_name, extra_appearances=None, envelope=None, ...)
    validate_citygml2(path) -> list[str]
    CityGMLError (a ValueError; `.path`, `.line`)
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

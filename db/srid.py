"""The database's one SRID and the transformations between a model's own CRS and it.

Every geometry column is typed with the database SRID (migration 0007, as 3DCityDB keeps one SRID
per database), so GIS clients see one declared CRS per layer. A model keeps its own CRS in
`city_model.srs_name` / `city_model.srid`: the importer transforms its geometries into the
database SRID (horizontal, heights kept; `workers.pipeline.geometry.transform`), the export and the
job stages transform them back. Numeric columns that are not geometries (`frame_pose` centres and
rotations, `thermal_anomaly.centre`, surface planes) are in the database SRID too where derived
from stored geometry (planes), and in the model's own CRS where they carry a job's results
(`frame_pose.*_center`, `thermal_anomaly.centre`), so that results read back unchanged.

In: a connection, CRS names as written in CityGML (`EPSG:25833`, URNs, AdV names). Out: the SRID,
`CrsTransform`s.
"""

from __future__ import annotations

from typing import Any

from db.errors import CityDBError, InputDataError
from workers.pipeline.geometry.crs import UnknownCRSError, horizontal_epsg
from workers.pipeline.geometry.transform import CrsTransform, CrsTransformError

__all__ = ["database_srid", "from_database", "model_epsg", "to_database"]


def database_srid(conn: Any) -> int:
    """The SRID the geometry columns are typed with (`surface.geometry`'s typmod). Raises
    `CityDBError` for a schema older than migration 0007 (columns untyped)."""
    from sqlalchemy import text

    srid = conn.execute(
        text(
            "SELECT srid FROM geometry_columns WHERE f_table_schema = current_schema() "
            "AND f_table_name = 'surface' AND f_geometry_column = 'geometry'"
        )
    ).scalar()
    if not srid:
        raise CityDBError("the database schema is not typed with an SRID: run `citytherm db upgrade`")
    return int(srid)


def model_epsg(srs_name: str | None, *, what: str = "the city model") -> int:
    """EPSG code of the horizontal CRS of `srs_name`. Raises `InputDataError` (naming `what`) when
    there is none or it is unknown: nothing is stored without a CRS."""
    if not srs_name:
        raise InputDataError(f"{what} names no CRS (no srsName anywhere): give it, e.g. --crs EPSG:25832")
    try:
        epsg = horizontal_epsg(srs_name)
    except UnknownCRSError as exc:
        raise InputDataError(f"{what}: {exc}; give the CRS, e.g. --crs EPSG:25832") from exc
    if not epsg:
        raise InputDataError(f"{what}: CRS {srs_name!r} has no EPSG code; give it, e.g. --crs EPSG:25832")
    return int(epsg)


def to_database(srs_name: str, db_srid: int) -> CrsTransform:
    """From a model's CRS into the database SRID. Raises `InputDataError` when that cannot be done
    exactly (e.g. a change of height system)."""
    try:
        return CrsTransform(srs_name, f"EPSG:{db_srid}")
    except CrsTransformError as exc:
        raise InputDataError(str(exc)) from exc


def from_database(srs_name: str, db_srid: int) -> CrsTransform:
    """From the database SRID back into a model's CRS (heights kept), rounded to the micrometre:
    a model imported into a database of another SRID exports with the digits it was written with
    (the round trip through PROJ is off by about 2 nm)."""
    return CrsTransform(f"EPSG:{db_srid}", srs_name, decimals=6)

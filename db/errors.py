"""Errors of the city model database layer (`db/`: import, store, export).

Each carries its HTTP meaning (`status_code`) so the service can map it with one handler.
"""

from __future__ import annotations

__all__ = ["CityDBError", "InputDataError", "ModelExistsError", "NotFoundError"]


class CityDBError(RuntimeError):
    """Base class of the database layer's errors."""

    status_code: int = 500


class ModelExistsError(CityDBError):
    """A city model of that name exists already (import without `replace`)."""

    status_code = 409


class NotFoundError(CityDBError):
    """A city model, job or building that was asked for does not exist."""

    status_code = 404


class InputDataError(CityDBError):
    """A result or file to store is inconsistent (e.g. a texture names a tile that is missing)."""

    status_code = 422

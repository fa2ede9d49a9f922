"""The optional `conditions` object of `sequence.json` (`docs/sequence-format.md`): the weather
of the survey, which the change between two surveys needs (`workers.pipeline.change`).

In: the decoded JSON value of `conditions`. Out: a `workers.pipeline.geometry.manifest.Conditions`.
Refusals raise `ConditionsError` (or the error type the caller gives: the package reader gives
its `PackageError`) whose message starts with the field (`conditions.air_temperature_c: ...`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from datetime import datetime
from typing import Any

from workers.pipeline.geometry.manifest import Conditions

#: plausible outside air temperatures, degrees Celsius (the records on Earth, with a margin)
AIR_TEMPERATURE_RANGE_C = (-95.0, 65.0)
CONDITIONS_MEMBERS = ("air_temperature_c", "recorded_at")
#: ISO 8601 date and time with seconds optional and a UTC offset required (PostgreSQL reads it)
_ISO_TIME = re.compile(r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}(:\d{2}(\.\d{1,6})?)?(Z|[+-]\d{2}:\d{2})")


class ConditionsError(ValueError):
    """A `conditions` object that must be refused. `.field` is the offending field."""

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        super().__init__(f"{field}: {message}")


ErrorType = Callable[[str, str], ValueError]


def parse_conditions(d: Any, error: ErrorType = ConditionsError) -> Conditions:
    """The manifest's `conditions` object -> `Conditions`: `air_temperature_c` a finite number of
    degrees Celsius within `AIR_TEMPERATURE_RANGE_C`, `recorded_at` an ISO 8601 date-time with a
    UTC offset; unknown members are refused (a kelvin value under another name must not pass).
    Refusals raise `error(field, message)`."""
    if not isinstance(d, Mapping):
        raise error("conditions", f"expected a JSON object, got {d!r}")
    for key in d:
        if key not in CONDITIONS_MEMBERS:
            raise error(f"conditions.{key}", f"unknown member (known: {', '.join(CONDITIONS_MEMBERS)})")
    air = d.get("air_temperature_c")
    if air is not None:
        air = _celsius(air, error)
        lo, hi = AIR_TEMPERATURE_RANGE_C
        if not lo <= air <= hi:
            raise error(
                "conditions.air_temperature_c",
                f"{air!r} °C is not an outside air temperature (kelvin given?)",
            )
    when = d.get("recorded_at")
    if when is not None:
        if not isinstance(when, str) or not _ISO_TIME.fullmatch(when):
            raise error(
                "conditions.recorded_at",
                f"expected an ISO 8601 time with UTC offset, e.g. 2025-01-15T21:30:00Z, got {when!r}",
            )
        try:
            datetime.fromisoformat(when.replace("Z", "+00:00"))
        except ValueError as exc:
            raise error("conditions.recorded_at", f"{when!r}: {exc}") from None
    return Conditions(air_temperature_c=air, recorded_at=when)


def _celsius(value: Any, error: ErrorType) -> float:
    """A finite JSON number (bool is not a number)."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise error("conditions.air_temperature_c", f"expected a finite number, got {value!r}")
    return float(value)
